"""``urd demo``: the whole pipeline on the simulated rig with bundled photos."""

from __future__ import annotations

from pathlib import Path

import typer

from urd.cli.common import bad, parse_size, report_truth, run_guarded, show_previews, within
from urd.core.progress import TerminalProgress

#: The demo's smallest sensor side (px): ECC alignment accepts shifts up to 5% of the width, and the
#: simulated rig shakes the camera by up to 4 px between shots.
DEMO_MIN_SIDE = 128


def demo(
    folder: Path = typer.Argument(Path("urd-demo"), help="Dataset folder for the demo, created; when it exists, a fresh FOLDER-2, FOLDER-3 … (said on the first line)."),
    size: str = typer.Option("1536x1024", help=f"Virtual sensor size WIDTHxHEIGHT (even sides, at least {DEMO_MIN_SIDE} px)."),
    seed: int = typer.Option(0, callback=within(0), help="Random seed of the simulated rig."),
    precision: str = typer.Option("auto", help="Network arithmetic: auto, fp32 or bf16."),
) -> None:
    """Run the whole pipeline on the simulated rig with bundled images (no hardware, no download).

    \b
    Example:
      urd demo
      urd demo urd-demo --size 768x512 --seed 1
    """
    from separate.precision import resolve
    from urd.demo import run_demo

    width, height = parse_size(size, min_side=DEMO_MIN_SIDE)
    try:
        resolve(precision)
    except ValueError as exc:
        raise bad("--precision", str(exc)) from None
    bar = TerminalProgress()
    result = run_guarded(run_demo, folder, width, height, seed, precision,
                         lambda line: (bar.break_line(), typer.echo(line)), progress=bar)
    report_truth(result.truth_metrics)
    show_previews(result.files)
