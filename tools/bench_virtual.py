"""The network against the classical methods on scenes rendered by urd's virtual camera
(`urd.virtual_bench`; the same as ``urd bench --virtual``), printed as Markdown.

    python tools/bench_virtual.py [--size 768x512] [--pairs 4] [--weights PATH] [--methods ...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from separate.methods import METHODS
from urd.core.errors import UrdError
from urd.virtual_bench import DEFAULT_METHODS, run_virtual_bench

from toolargs import Formatter, positive, scene_size


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--size", type=scene_size(), default="768x512", help="scene size WxH (px)")
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
