"""Speed and memory of the user path on a 24-megapixel scene (6000×4000), printed.

Captures a scene of three DNG shots with the simulated rig (not timed), then runs
``urd ingest`` (decode + align + write) and ``urd separate`` (load + network + write) each in
its own process, timing the wall clock and reading the process's peak resident memory; the
network runs at ``--precision`` (auto: bf16 where the CPU runs it natively, else fp32), the
precision the CLI reports is printed. Last, the shipped network's FLOPs over ``urd separate``'s
wall time (the whole command in a fresh process) against this CPU's fp32 matmul rate, measured
before and after the commands, each in a fresh process (`tools/bench_speed.py`'s counts), taking
the higher of the two: on a shared machine a single reading can be half the CPU's rate.

    python tools/bench_24mp.py [--size 6000x4000] [--folder /tmp/urd-bench-24mp] [--precision auto] [--tile N] [--runs N]
    python tools/bench_24mp.py --size 2448x1632 --runs 3       # 4 MP, three separations

Single runs on a shared 2-core machine spread by 5-15%: ``--runs N`` separates the scene N
times (each a fresh process, ``--force`` after the first) and prints every run and the median.

--folder is a scratch dataset, removed and made anew on each run; a folder that this tool did
not make is refused (even a dataset), so that a mistyped path deletes nothing of yours.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from separate.provenance import cpu_model

from toolargs import Formatter, positive, scene_size, scratch


# A wrapper process runs one command and reports its own children's peak RSS (KiB): the
# peak of RUSAGE_CHILDREN in this process would be the maximum over every command run so far.
WRAPPER = ("import resource, subprocess, sys; done = subprocess.run(sys.argv[1:]); "
           "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(done.returncode)")


RATE = ("import sys, torch; sys.path.insert(0, sys.argv[1]); from bench_speed import matmul_gflops; "
        "print(matmul_gflops(torch.float32, 5)[0])")


def fp32_rate() -> float:
    """This CPU's fp32 matmul rate (GFLOP/s, `bench_speed.matmul_gflops`), read in a fresh process."""
    done = subprocess.run([sys.executable, "-c", RATE, os.path.dirname(os.path.abspath(__file__))],
                          capture_output=True, text=True, check=True)
    return float(done.stdout.split()[-1])


def run(args: list[str]) -> tuple[float, float, str]:
    """Run ``python -m urd.cli ARGS`` in a child; return (seconds, peak RSS in GiB, its stderr)."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", WRAPPER, sys.executable, "-m", "urd.cli", *args],
                          capture_output=True, text=True)
    elapsed = time.perf_counter() - started
    if done.returncode:
        sys.exit(f"urd {' '.join(args)} failed:\n{done.stderr}")
    lines = done.stderr.strip().splitlines()
    return elapsed, int(lines[-1]) / 1024**2, "\n".join(lines[:-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--size", type=scene_size(), default="6000x4000", help="scene size WxH (px)")
    parser.add_argument("--folder", type=Path, default=Path("/tmp/urd-bench-24mp"),
                        help="scratch dataset folder, removed and made anew")
    parser.add_argument("--precision", default="auto", choices=["auto", "fp32", "bf16"], help="the network's precision")
    parser.add_argument("--tile", type=positive, default=None, help="network tile (px) (default: the CLI's)")
    parser.add_argument("--runs", type=positive, default=1, help="separations of the scene, each in a fresh process")
    args = parser.parse_args()
    width, height = args.size
    size = f"{width}x{height}"
    folder = scratch(args.folder)
    rate_before = fp32_rate()
    capture = subprocess.run([sys.executable, "-m", "urd.cli", "capture", str(folder), "--stage", "sim", "--camera", "virtual",
                              "--sim-size", size, "--sim-shake", "8"], capture_output=True, text=True)
    if capture.returncode:
        sys.exit(f"urd capture failed:\n{capture.stderr}")
    ingest_s, ingest_gb, _ = run(["ingest", str(folder / "scene_01")])
    separate_args = ["separate", "scene_01", "--dataset", str(folder), "--precision", args.precision]
    separations = [run(separate_args + (["--tile", str(args.tile)] if args.tile else []) + (["--force"] if k else []))
                   for k in range(args.runs)]
    separate_s = statistics.median(seconds for seconds, _, _ in separations)          # even N: the mean of the middle two
    separate_gb, log = max(gb for _, gb, _ in separations), separations[0][2]         # every run tells one precision
    precision = next((line.split(":", 1)[1].strip() for line in log.splitlines() if line.startswith("precision:")),
                     args.precision)
    capped = [f"{k}={os.environ[k]}" for k in ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS")
              if k in os.environ]
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores" + (f"; instruction sets capped: {' '.join(capped)}" if capped else ""))
    print(f"scene {size}, 3 shots; network precision {precision}" + (f", tile {args.tile} px" if args.tile else ""))
    print(f"urd ingest   (decode + align + write):  {ingest_s:6.1f} s, peak memory {ingest_gb:.2f} GiB")
    if args.runs > 1:
        print("urd separate runs: " + ", ".join(f"{seconds:.1f} s" for seconds, _, _ in separations) +
              "; their median below, and the highest peak memory")
    print(f"urd separate (load + network + write):  {separate_s:6.1f} s, peak memory {separate_gb:.2f} GiB")
    rate_after = fp32_rate()
    from bench_speed import flops_per_mp          # after the timed commands: this process stays out of their way
    from separate.infer import load_model

    network_gflop = flops_per_mp(load_model()[0]) * width * height / 1e15
    rate = max(rate_before, rate_after)
    end_to_end = (f"network {network_gflop:.0f} GFLOP (the image's pixels; the tiles' overlap is not counted) in urd "
                  f"separate's {separate_s:.1f} s: {network_gflop / separate_s:.0f} GFLOP/s end to end")
    if precision.endswith("on cuda"):                   # the CLI's "precision: bf16 (native) on cuda": no CPU ratio
        print(f"{end_to_end}, the network on the GPU (this CPU's fp32 matmul rate, {rate:.0f} GFLOP/s, does not bound it)")
    else:
        print(f"{end_to_end}, {network_gflop / separate_s / rate:.0%} of this CPU's fp32 matmul rate ({rate:.0f} GFLOP/s, "
              f"the higher of {rate_before:.0f} before and {rate_after:.0f} after the commands)")


if __name__ == "__main__":
    main()
