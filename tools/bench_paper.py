"""Reproduce the paper's evaluation (`separate.bench_run`): cross-validation on held-out synthetic
sets (Table 1), robustness to angle errors, misalignment, noise, the s-direction, the number of
angles and calibration, and speed and memory; Markdown, CSV and PNG into OUT/quick or OUT/full.

    python tools/bench_paper.py [--quick] [--images DIR] [--out docs/bench] [--update-expected] [--24mp]

--quick: the reduced run (a few minutes on 2 cores), checked against separate/expected-quick.json
(exit status 1 naming every figure out of tolerance); with --update-expected it rewrites that
file instead (after new weights: python tools/bench_paper.py --quick --update-expected).
--images DIR: also cross-validate on the photos in DIR (JPEG, PNG, TIFF; 8 or 16 bit).
--24mp: (full run) also time the network and Schechner at 6000×4000.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from toolargs import Formatter


def main() -> int:
    from separate.bench_run import DEFAULT_OUT, run_evaluation
    from urd.core.errors import UrdError
    from urd.core.progress import TerminalProgress

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--quick", action="store_true", help="the reduced run, checked against the expected values")
    parser.add_argument("--images", type=Path, default=None, help="a folder of photos to cross-validate on as well (default: none)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (results go to OUT/quick or OUT/full)")
    parser.add_argument("--update-expected", action="store_true", help="(--quick) rewrite separate/expected-quick.json")
    parser.add_argument("--24mp", dest="large", action="store_true", help="(full run) also time 24 MP separations")
    args = parser.parse_args()
    if args.update_expected and not args.quick:
        parser.error("--update-expected needs --quick")
    if args.large and args.quick:
        parser.error("--24mp is part of the full run only")
    if args.images is not None and not args.images.is_dir():
        parser.error(f"argument --images: expected a folder of photos, got {args.images}")
    progress = TerminalProgress()
    try:
        result = run_evaluation(args.out, args.quick, args.images, progress, large=args.large,
                                update_expected=args.update_expected)
    except (UrdError, OSError) as exc:                 # a BenchmarkMismatch among them
        progress.close()
        print(f"error: {exc}", file=sys.stderr)
        return 1
    progress.close()
    print(f"{result['check']['line']}\nwritten: {result['folder']}/ ({', '.join(result['files'])}); "
          f"{result['seconds']['total']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
