"""The network against the classical methods on scenes rendered by urd's virtual camera
(`urd.virtual_bench`; the same as ``urd bench --virtual``), printed as Markdown.

    python tools/bench_virtual.py [--size 768x512] [--pairs 4] [--weights PATH] [--methods ...]
"""

import argparse
import time
from pathlib import Path

from urd.virtual_bench import DEFAULT_METHODS, run_virtual_bench

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--size", default="768x512", help="scene size WxH (px)")
parser.add_argument("--pairs", type=int, default=4, help="photo pairs per angle of incidence")
parser.add_argument("--weights", type=Path, default=None, help="network weights (default: shipped)")
parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
args = parser.parse_args()
started = time.time()
width, height = (int(v) for v in args.size.split("x"))
print(run_virtual_bench(tuple(args.methods), args.weights, (width, height), args.pairs))
print(f"{time.time() - started:.0f} s")
