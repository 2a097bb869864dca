"""Time every separation method on a 1-megapixel simulated-rig scene (1224×816), printed.

    python tools/bench_baselines.py [--folder /tmp/urd-bench-1mp]

Captures the scene with the simulated rig and ingests it (not timed) into --folder, a scratch
dataset removed and made anew on each run (a folder this tool did not make is refused, even a
dataset), then times each method of `separate.methods.METHODS` on its aligned stack.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from separate.methods import METHODS, get_method
from urd.core.dataset import Dataset
from urd.core.errors import UrdError

from toolargs import Formatter, scratch


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--folder", type=Path, default=Path("/tmp/urd-bench-1mp"),
                        help="scratch dataset folder, removed and made anew")
    args = parser.parse_args()
    folder = scratch(args.folder)
    for step in (["capture", str(folder), "--stage", "sim", "--camera", "virtual", "--sim-size", "1224x816"],
                 ["ingest", str(folder / "scene_01")]):
        done = subprocess.run([sys.executable, "-m", "urd.cli", *step], capture_output=True, text=True)
        if done.returncode:
            print(f"error: urd {step[0]} failed: {done.stderr.strip()}", file=sys.stderr)
            return 1
    try:
        stack, angles = Dataset.open(folder).scene("scene_01").load_stack()
    except UrdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"1-megapixel scene {stack.shape[2]}x{stack.shape[1]}, {len(angles)} shots")
    for name in METHODS:
        run, _ = get_method(name)
        started = time.perf_counter()
        run(stack, angles)
        print(f"{name:16s} {time.perf_counter() - started:7.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
