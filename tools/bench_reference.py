"""T̂ PSNR against the glass's s-direction and against the angle set, on the synthetic benchmark.

    python tools/bench_reference.py [--count 16] [--size 128] [--weights PATH] [--skip-schechner]

The scenes are the benchmark's patches (`separate.bench.benchmark_set`: bsds500/test, DR + LCG,
abrupt reflections), shot again with `separate.bench.reshoot` (±4° angle errors, sensor noise,
no new non-rigid deformation), so that every row sees the same layers:

1. φ⊥ − φ0, the s-direction relative to the first shot, swept over [0°, 180°) in 22.5° steps
   with shots at φ0 + 0/45/90°, 0/60/120° and 0/45/90/135° (the same angle errors and noise
   pattern for every step); network and Schechner with the reference estimated ("auto"), with
   the true φ⊥ ("oracle"), and (0/45/90) with urd's former rule, φ⊥ within ±45° of the first
   shot ("first"). 0/45/90 is not symmetric under rotation: its Stokes fit has 3× the noise
   variance in S2 as in S1, so even the oracle varies with φ⊥; the other two sets are symmetric;
2. the network with 3 (0/45/90 and 0/60/120), 4 (0/45/90/135) and 6 (30° steps) shots, φ0
   uniform in [0°, 180°) per patch, reference estimated; also with the true φ⊥ as the reference
   ("oracle") and with the first shot's angle.

Linear values, peak 1, mean over patches; seeded (2018).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from separate import metrics
from separate.bench import SEED, benchmark_set, largest_size, reshoot
from separate.methods import get_method

from toolargs import Formatter, at_least, check_patch_side, load_network

SWEEP_DEG = np.arange(0.0, 180.0, 22.5)
SWEEP_SETS_DEG = {"0/45/90": (0, 45, 90), "0/60/120": (0, 60, 120), "0/45/90/135": (0, 45, 90, 135)}
ANGLE_SETS_DEG = {"3: 0/45/90": (0, 45, 90), "3: 0/60/120": (0, 60, 120), "4: 0/45/90/135": (0, 45, 90, 135),
                  "6: 0/30/.../150": (0, 30, 60, 90, 120, 150)}


def psnr_t(run, shots, angles_deg, t_obs, reference_deg=None) -> float:
    """T̂ PSNR (dB) of ``run`` on ``shots`` against ``t_obs``."""
    return float(metrics.psnr(run(shots, list(angles_deg), reference_deg)[1], t_obs))


def sweep_tables(methods: dict, samples: list[dict], size: int) -> None:
    """Print part 1: T̂ PSNR by φ⊥ − φ0 per angle set, method and reference rule."""
    count = len(samples)
    for set_label, offsets in SWEEP_SETS_DEG.items():
        rules = ("auto", "oracle", "first") if set_label == "0/45/90" else ("auto", "oracle")
        print(f"T PSNR (dB) by phi_perp - phi0 (shots at phi0 + {set_label}), {count} patches of {size}x{size}")
        print("| method | " + " | ".join(f"{d:g}°" for d in SWEEP_DEG) + " | max − min |")
        print("|---|" + "---|" * (len(SWEEP_DEG) + 1))
        sweep = {f"{m} ({rule})": np.zeros((count, len(SWEEP_DEG))) for m in methods for rule in rules}
        for i, sample in enumerate(samples):
            phi_perp_deg = float(np.degrees(sample["phi_perp"][0, 0]))
            for j, delta in enumerate(SWEEP_DEG):
                nominal = phi_perp_deg - delta + np.asarray(offsets, np.float64)
                shots = reshoot(sample, np.radians(nominal), np.random.default_rng([SEED, i]))   # same errors and noise for every δ
                given = {"auto": None, "oracle": phi_perp_deg, "first": nominal[0]}
                for name, run in methods.items():
                    for rule in rules:
                        sweep[f"{name} ({rule})"][i, j] = psnr_t(run, shots, nominal, sample["t"], given[rule])
        for label, values in sweep.items():
            means = values.mean(axis=0)
            print(f"| {label} | " + " | ".join(f"{v:.2f}" for v in means) + f" | {np.ptp(means):.2f} |")
        print()


def angle_set_table(network, samples: list[dict]) -> None:
    """Print part 2: the network's T̂ PSNR by angle set, φ0 uniform."""
    count = len(samples)
    print(f"T PSNR (dB) of the network by angle set (phi0 uniform), {count} patches")
    print("| shots | auto | oracle (true phi_perp) | first shot |")
    print("|---|---|---|---|")
    rng = np.random.default_rng([SEED, 1])
    phi0 = rng.uniform(0.0, 180.0, count)
    for label, offsets in ANGLE_SETS_DEG.items():
        rows = []
        for i, sample in enumerate(samples):
            nominal = phi0[i] + np.asarray(offsets, np.float64)
            shots = reshoot(sample, np.radians(nominal), np.random.default_rng([SEED, i, 99]))
            truth = float(np.degrees(sample["phi_perp"][0, 0]))
            rows.append([psnr_t(network, shots, nominal, sample["t"]), psnr_t(network, shots, nominal, sample["t"], truth),
                         psnr_t(network, shots, nominal, sample["t"], nominal[0])])
        auto, oracle, first = np.mean(rows, axis=0)
        print(f"| {label} | {auto:.2f} | {oracle:.2f} | {first:.2f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--count", type=at_least(1), default=16, help="benchmark patches")
    parser.add_argument("--size", type=at_least(32), default=128, help="patch side (px)")
    parser.add_argument("--weights", type=Path, default=None, help="network weights or checkpoint (default: shipped)")
    parser.add_argument("--skip-schechner", action="store_true", help="network only (Schechner takes ~0.4 s per patch and angle)")
    args = parser.parse_args()
    check_patch_side(parser, args.size, largest_size())
    started = time.perf_counter()
    network = load_network(args.weights)
    methods = {"network": network}
    if not args.skip_schechner:
        methods["schechner"] = get_method("schechner")[0]
    data = benchmark_set(args.count, args.size)
    samples = [{k: v[i] for k, v in data.items()} for i in range(args.count)]
    sweep_tables(methods, samples, args.size)
    angle_set_table(network, samples)
    none = np.mean([metrics.psnr(s["r"] + s["t"], s["t"]) for s in samples])
    print(f"\nno separation: {none:.2f} dB; seed {SEED}; {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
