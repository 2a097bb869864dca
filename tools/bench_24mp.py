"""Speed and memory of the user path on a 24-megapixel scene (6000×4000), printed.

Captures a scene of three DNG shots with the simulated rig (not timed), then runs
``urd ingest`` (decode + align + write) and ``urd separate`` (load + network + write) each in
its own process, timing the wall clock and reading the process's peak resident memory.

    python tools/bench_24mp.py [--size 6000x4000] [--folder /tmp/urd-bench]
"""

import argparse
import os
import shutil
import subprocess
import sys
import time


# A wrapper process runs one command and reports its own children's peak RSS (KiB): the
# peak of RUSAGE_CHILDREN in this process would be the maximum over every command run so far.
WRAPPER = ("import resource, subprocess, sys; done = subprocess.run(sys.argv[1:]); "
           "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(done.returncode)")


def run(args: list[str]) -> tuple[float, float]:
    """Run ``python -m urd.cli ARGS`` in a child; return (seconds, peak RSS in GB)."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", WRAPPER, sys.executable, "-m", "urd.cli", *args],
                          capture_output=True, text=True)
    elapsed = time.perf_counter() - started
    if done.returncode:
        sys.exit(f"urd {' '.join(args)} failed:\n{done.stderr}")
    return elapsed, int(done.stderr.strip().splitlines()[-1]) / 1024**2


parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--size", default="6000x4000")
parser.add_argument("--folder", default="/tmp/urd-bench-24mp")
args = parser.parse_args()
shutil.rmtree(args.folder, ignore_errors=True)
subprocess.run([sys.executable, "-m", "urd.cli", "capture", args.folder, "--stage", "sim", "--camera", "virtual",
                "--sim-size", args.size, "--sim-shake", "8"], check=True, capture_output=True)
scene = os.path.join(args.folder, "scene_01")
ingest_s, ingest_gb = run(["ingest", scene])
separate_s, separate_gb = run(["separate", "scene_01", "--dataset", args.folder])
print(f"scene {args.size}, 3 shots, {os.cpu_count()} CPU cores")
print(f"urd ingest   (decode + align + write): {ingest_s:6.1f} s, peak memory {ingest_gb:.2f} GB")
print(f"urd separate (load + network bf16 + write): {separate_s:6.1f} s, peak memory {separate_gb:.2f} GB")
