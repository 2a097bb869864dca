"""What the scripts in tools/ share to read their command line: the help formatter, the argparse
types they repeat, the patch benchmarks' --size check, the scratch benchmarks' --folder guard and
the network's loader.

Imported by the scripts in tools/ (``from toolargs import Formatter, at_least``): each runs as
``python tools/NAME.py``, which puts tools/ first on ``sys.path``; code that runs a script by
other means (``runpy.run_path``, a ``-c`` snippet) puts tools/ on ``sys.path`` itself. Not a
tool of its own.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


class Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """The module docstring as written; each option's default after its help, where it has one."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        return action.help if action.default is None else super()._get_help_string(action)


def at_least(low: int):
    """An argparse type: an integer of at least ``low``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected at least {low}, got {value}")
        return value
    return parse


def positive(text: str) -> int:
    """An argparse type: an integer of at least 1, written in digits only."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return int(text)


def scene_size(low: int = 32):
    """An argparse type: 'WxH' → (W, H) px, the virtual camera's sensor as `urd capture --sim-size`
    takes it (`urd.cli.common.parse_size`: each side even, ``low`` to 20000)."""
    import typer

    from urd.cli.common import parse_size

    def parse(text: str) -> tuple[int, int]:
        try:
            return parse_size(text, "--size", low)
        except typer.BadParameter as exc:
            raise argparse.ArgumentTypeError(exc.message) from None
    return parse


def check_patch_side(parser: argparse.ArgumentParser, side: int, largest: int) -> None:
    """A usage error (exit status 2) where --size ``side`` is over ``largest`` px, the shorter side of
    the test photos (`separate.bench.largest_size`: it loads them, so it is called after parsing)."""
    if side > largest:
        parser.error(f"argument --size: expected at most {largest} px (the shorter side of the test photos), got {side}")


#: The file a tool leaves in the scratch folder it makes: only such a folder (or an empty one) is removed.
SCRATCH_MARK = ".urd-tool-scratch"


def scratch(folder: Path) -> Path:
    """``folder`` removed and made anew, with `SCRATCH_MARK` in it; SystemExit where it exists and
    is a link, or neither empty nor marked as a tool's scratch folder (a dataset of yours is not
    removed), or cannot be removed or made."""
    if folder.is_symlink() or folder.exists() and not (
            folder.is_dir() and (not any(folder.iterdir()) or (folder / SCRATCH_MARK).is_file())):
        sys.exit(f"error: {folder} exists and is not a scratch folder this tool made (no {SCRATCH_MARK} in it, or a "
                 "link); this tool removes its --folder: choose another")
    try:
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        (folder / SCRATCH_MARK).write_text("made by a urd tool (tools/): removed and made anew on its next run\n")
    except OSError as exc:
        sys.exit(f"error: cannot make the scratch folder {folder} anew ({exc.strerror or exc})")
    return folder


def load_network(weights: Path | None):
    """The network's run function (`separate.methods.get_method`) with ``weights`` (None: shipped);
    SystemExit with the one-line reason where they cannot be loaded."""
    from separate.methods import get_method
    from urd.core.errors import UrdError

    try:
        return get_method("network", weights=weights)[0]
    except UrdError as exc:
        sys.exit(f"error: {exc}")
