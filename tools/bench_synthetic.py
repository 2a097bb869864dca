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

from __future__ import annotations

import argparse
import math
import sys
import time

from separate.bench import format_aoi_table, format_paired, format_table, largest_size, run_benchmark
from separate.methods import METHODS
from urd.core.errors import UrdError

from toolargs import Formatter, at_least, check_patch_side


def method_list(text: str) -> list[str]:
    """Comma-separated method names of `separate.methods.METHODS`, 'direct', or LABEL=PATH."""
    names = [name for name in text.split(",") if name]
    known = sorted(METHODS) + ["direct"]
    unknown = [name for name in names if "=" not in name and name not in known]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"expected some of {', '.join(known)} or LABEL=PATH, got {text!r}")
    return names


def reference_angle(text: str) -> str | float:
    """'auto' or a finite angle in degrees."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected 'auto' or an angle in degrees, got {text!r}")
    return value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--count", type=at_least(1), default=64, help="benchmark patches")
    parser.add_argument("--size", type=at_least(32), default=256, help="patch side (px)")
    parser.add_argument("--by-aoi", action="store_true", help="also T PSNR per angle-of-incidence band")
    parser.add_argument("--reference", type=reference_angle, default="auto",
                        help="auto, or the reference angle in degrees (0: the first shot)")
    parser.add_argument("--methods", type=method_list,
                        default=",".join(["none", "direct", "network"] + [m for m in METHODS if m not in ("none", "network")]),
                        help="comma-separated methods: names, 'direct' (the direct variant's shipped weights), "
                             "LABEL=PATH (the network with the weights at PATH)")
    args = parser.parse_args()
    check_patch_side(parser, args.size, largest_size())
    started = time.perf_counter()
    try:
        rows = run_benchmark(args.methods, args.count, args.size, reference=args.reference)
    except UrdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(format_table(rows))
    if {"network", "direct"} <= {r["method"] for r in rows}:
        print("\n" + format_paired(rows, "network", "direct"))
    if args.by_aoi:
        print("\nT PSNR (dB) by mean angle of incidence\n" + format_aoi_table(rows))
    print(f"\n{args.count} patches of {args.size}x{args.size}, seed 2018, reference {args.reference}; "
          f"{time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
