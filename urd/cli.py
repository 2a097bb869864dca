"""The ``urd`` command line: a thin layer over acquire/, calib/, separate/ and urd.dataset.

Angles are degrees here and in manifests. Errors print one line and exit with status 1;
a command that is not built yet says so and exits with status 2.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from urd.errors import UrdError

app = typer.Typer(
    help="urd: photograph scenes through glass with a rotating polarizer and separate reflection from transmission.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def fail(message: str, code: int = 1) -> None:
    """Print an error line and exit with ``code``."""
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


def not_built(command: str) -> None:
    """Say that a command is not built yet and exit with status 2."""
    typer.secho(f"urd {command}: not built yet in urd {__import__('urd').__version__}", err=True)
    raise typer.Exit(2)


def parse_angles(text: str, min_distinct: int = 3) -> list[float]:
    """'0,45,90' → [0.0, 45.0, 90.0] (degrees); at least ``min_distinct`` distinct directions."""
    try:
        angles = [float(a) for a in text.split(",") if a.strip()]
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated degrees like 0,45,90, got {text!r}")
    if len({round(a % 180.0, 6) for a in angles}) < min_distinct:
        raise typer.BadParameter(f"expected at least {min_distinct} distinct polarizer angles (mod 180), got {text!r}")
    return angles


def run_guarded(func, *args, **kwargs):
    """Call ``func``, turning urd's errors into a one-line message and exit status 1."""
    try:
        return func(*args, **kwargs)
    except (UrdError, ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        fail("interrupted; completed files are kept and a re-run resumes", 130)


@app.command()
def capture(
    dataset: Path = typer.Argument(..., help="Dataset folder; created when new."),
    stage: str = typer.Option(..., help="Serial port of the ELL14 stage (e.g. /dev/ttyUSB0), or 'sim'."),
) -> None:
    """Capture one scene: home the polarizer stage, then move, verify, trigger and download at each angle."""
    not_built("capture")


@app.command()
def ingest(raw: Path = typer.Argument(..., help="Folder of RAW shots.")) -> None:
    """Decode RAW shots to linear images, group them into scenes and align each scene (ECC)."""
    not_built("ingest")


@app.command()
def calibrate() -> None:
    """Measure the polarizer: mounting offset from a sweep, per-shot angle errors of a scene."""
    not_built("calibrate")


@app.command()
def separate(scene: str = typer.Argument(..., help="Scene name (scene_12) or folder.")) -> None:
    """Separate a scene into reflection R̂ and transmission T̂ (network or a classical method)."""
    not_built("separate")


@app.command()
def train() -> None:
    """Train the separation network on synthesized data (config file, checkpoints, resume)."""
    not_built("train")


@app.command()
def bench() -> None:
    """Run the fixed synthetic benchmark and print RMSE / PSNR / SSIM per method."""
    not_built("bench")


@app.command()
def report() -> None:
    """Summarize a dataset: scenes, angles, alignment and calibration status, results."""
    not_built("report")


@app.command()
def demo() -> None:
    """Run the whole pipeline on the simulated rig with bundled images (no hardware, no download)."""
    not_built("demo")


def main() -> None:
    app(prog_name="urd")


if __name__ == "__main__":
    sys.exit(main())
