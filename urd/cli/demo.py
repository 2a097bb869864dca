"""``urd demo``: the whole pipeline on the simulated rig with bundled photos."""

from __future__ import annotations

from pathlib import Path

import typer

from urd.cli.common import bad, parse_size, report_truth, run_guarded, show_previews
from urd.core.progress import TerminalProgress


def demo(
    folder: Path = typer.Argument(Path("urd-demo"), help="Dataset folder for the demo, created; when it exists, a fresh FOLDER-2, FOLDER-3 … (said on the first line)."),
    size: str = typer.Option("1536x1024", help="Virtual sensor size WIDTHxHEIGHT."),
    seed: int = typer.Option(0, help="Random seed of the simulated rig."),
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

    width, height = parse_size(size)
    try:
        resolve(precision)
    except ValueError as exc:
        raise bad("--precision", str(exc)) from None
    result = run_guarded(run_demo, folder, width, height, seed, precision, typer.echo, progress=TerminalProgress())
    report_truth(result.truth_metrics)
    show_previews(result.files)
