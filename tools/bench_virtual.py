"""The network against the classical methods on scenes rendered by urd's virtual camera
(`urd.virtual_bench`; the same as ``urd bench --virtual``), printed as Markdown.

    python tools/bench_virtual.py [--size 768x512] [--pairs 4] [--weights PATH] [--methods ...]
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

from separate.methods import METHODS
from urd.core.errors import UrdError
from urd.virtual_bench import DEFAULT_METHODS, run_virtual_bench


class Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """The module docstring as written; each option's default after its help, where it has one."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        return action.help if action.default is None else super()._get_help_string(action)


def scene_size(text: str) -> tuple[int, int]:
    """'WxH' → (W, H) px, each 32-20000 (the virtual camera's range)."""
    match = re.fullmatch(r"(\d+)x(\d+)", text)
    if not match or not all(32 <= int(v) <= 20000 for v in match.groups()):
        raise argparse.ArgumentTypeError(f"expected WxH with each side 32-20000 px, e.g. 768x512, got {text!r}")
    return int(match[1]), int(match[2])


def positive(text: str) -> int:
    """An integer of at least 1."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return int(text)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--size", type=scene_size, default="768x512", help="scene size WxH (px)")
    parser.add_argument("--pairs", type=positive, default=4, help="photo pairs per angle of incidence")
    parser.add_argument("--weights", type=Path, default=None, help="network weights (default: shipped)")
    parser.add_argument("--methods", nargs="+", choices=sorted(METHODS), default=list(DEFAULT_METHODS), metavar="METHOD",
                        help=f"methods to score, some of {', '.join(sorted(METHODS))}")
    args = parser.parse_args()
    started = time.time()
    try:
        print(run_virtual_bench(tuple(args.methods), args.weights, args.size, args.pairs))
    except UrdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{time.time() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
