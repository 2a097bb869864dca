"""Print the synthetic benchmark table (README's "Results"): every method on the same seeded
bsds500/test patches through the full synthesis pipeline.

    python tools/bench_synthetic.py [--count 64] [--size 256] [--methods none,direct,network,...] [--by-aoi]
                                    [--reference auto|DEG]

--reference: the methods' reference angle, "auto" (estimated from the shots, the default) or
degrees (0: the first shot, urd's rule before the reference was estimated).

With both network and direct it prints their paired T̂ PSNR difference (mean over patches,
95% bootstrap interval, patches won). --by-aoi adds T̂ PSNR per band of the patches' mean
angle of incidence (patch count in brackets).
"""

import argparse
import time

from separate.bench import format_aoi_table, format_paired, format_table, run_benchmark
from separate.methods import METHODS

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--count", type=int, default=64)
parser.add_argument("--size", type=int, default=256)
parser.add_argument("--by-aoi", action="store_true", help="also T PSNR per angle-of-incidence band")
parser.add_argument("--reference", default="auto", help="auto, or the reference angle in degrees (0: the first shot)")
parser.add_argument("--methods", default=",".join(["none", "direct", "network"] + [m for m in METHODS if m not in ("none", "network")]))
args = parser.parse_args()
started = time.perf_counter()
reference = args.reference if args.reference == "auto" else float(args.reference)
rows = run_benchmark(args.methods.split(","), args.count, args.size, reference=reference)
print(format_table(rows))
if {"network", "direct"} <= {r["method"] for r in rows}:
    print("\n" + format_paired(rows, "network", "direct"))
if args.by_aoi:
    print("\nT PSNR (dB) by mean angle of incidence\n" + format_aoi_table(rows))
print(f"\n{args.count} patches of {args.size}x{args.size}, seed 2018, reference {args.reference}; {time.perf_counter() - started:.0f} s")
