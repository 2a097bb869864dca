"""Grid texture and highlight halos of the network's output, measured (issue 16).

    python tools/bench_texture.py [--count 16] [--size 256] [--weights PATH]

Grid texture: the decoder's stride-2 transposed convolutions (kernel 2) give each output phase of a
2×2 cell its own weights, three times over, so a bias between phases shows as a fixed 2/4/8-px
pattern. Measured as the RMS over the 64 phases (y mod 8, x mod 8) of the mean high-pass of an
image at that phase (high-pass: the image minus its 9×9 box blur), relative to the image's mean,
in per mille. Scene content and noise average out over the phases; a fixed pattern does not. Tiles
start on the 8-px grid, so the phases are the same in every tile. The input S0 gives the floor.

Sets: the benchmark patches (`separate.bench.benchmark_set`: bsds500/test, the full synthesis
pipeline, shots at 0/45/90); flat scenes (each layer one colour times a smooth ramp, the shots
with sensor noise), where the texture is most visible; and the real captures in
../shared/data/polarization (reduced to 1024 px), where they are present.

Halos: benchmark patches shot brighter (exposure × 2, 4: the brightest pixels clip at 1.0 in some
shots). T̂ PSNR on the pixels within 8 px of a clipped pixel (not clipped themselves) and on the
rest, against the observable T of the same exposure; "none" (T̂ = S0) for comparison.

Linear values, peak 1; seeded (2018).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from separate import metrics, optics
from separate.bench import SEED, benchmark_set, largest_size, reshoot
from separate.synthesis import noise_std
from urd.core import samples

from toolargs import Formatter, at_least, check_patch_side, load_network

PERIOD = 8
RING_PX = 8


def grid_per_mille(image: np.ndarray) -> float:
    """RMS over the 64 phases of the mean 9×9 high-pass of an H×W×C image, per mille of its mean."""
    lum = image.mean(axis=-1).astype(np.float32)
    high = lum - cv2.blur(lum, (9, 9), borderType=cv2.BORDER_REFLECT)
    h, w = (s // PERIOD * PERIOD for s in high.shape)
    phases = high[16 : h - 16, 16 : w - 16].reshape((h - 32) // PERIOD, PERIOD, (w - 32) // PERIOD, PERIOD).mean(axis=(0, 2))
    return float(1000 * np.sqrt(np.mean((phases - phases.mean()) ** 2)) / max(float(lum.mean()), 1e-12))


def flat_scene(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Smooth observable layers (size×size×3) and their θ, φ⊥ (rad): each layer one colour times
    a gentle ramp, the reflection 10-40% of the light."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    layers = []
    for level in (rng.uniform(0.3, 0.6), rng.uniform(0.05, 0.2)):
        ramp = 1 + 0.3 * (rng.uniform(-1, 1) * yy + rng.uniform(-1, 1) * xx)
        layers.append((level * ramp[..., None] * rng.uniform(0.7, 1.0, 3)).astype(np.float32))
    return layers[0], layers[1], rng.uniform(0.6, 1.2), rng.uniform(0, np.pi)


def s0_of(shots: np.ndarray, angles_deg) -> np.ndarray:
    """The unpolarized image S0 of a stack (`separate.optics.stokes_from_images`)."""
    return optics.stokes_from_images(shots, np.radians(angles_deg))[0]


def shoot(t_obs: np.ndarray, r_obs: np.ndarray, theta: float, phi_perp: float, angles_deg, rng) -> np.ndarray:
    """Shots of observable layers through a polarizer (`separate.optics.render`), with sensor noise."""
    i_r, i_t = optics.radiances_from_layers(r_obs, t_obs, theta)
    shots = np.stack([optics.render(i_r, i_t, theta, phi_perp, np.radians(a)) for a in angles_deg])
    shots = shots + rng.normal(0.0, 1.0, shots.shape) * noise_std(shots, 1e-3, 1e-6)
    return np.clip(shots, 0.0, 1.0).astype(np.float32)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--count", type=at_least(1), default=16, help="benchmark patches and flat scenes, each")
    parser.add_argument("--size", type=at_least(32), default=256, help="patch side (px)")
    parser.add_argument("--weights", type=Path, default=None, help="network weights or checkpoint (default: shipped)")
    args = parser.parse_args()
    check_patch_side(parser, args.size, largest_size())
    started = time.perf_counter()
    network = load_network(args.weights)
    angles = [0.0, 45.0, 90.0]

    print(f"Grid texture (per mille of the mean; RMS of the 8×8 phase means of the 9×9 high-pass), {args.count} scenes per set")
    print("| set | S0 (input) | T̂ | R̂ |")
    print("|---|---|---|---|")
    data = benchmark_set(args.count, args.size)
    rows = {"benchmark (bsds500/test)": [], "flat scenes": []}
    for i in range(args.count):
        shots = data["obs"][i]
        r_hat, t_hat = network(shots, angles)
        rows["benchmark (bsds500/test)"].append([grid_per_mille(s0_of(shots, angles)), grid_per_mille(t_hat), grid_per_mille(r_hat)])
    rng = np.random.default_rng(SEED)
    for _ in range(args.count):
        t_obs, r_obs, theta, phi_perp = flat_scene(rng, args.size)
        shots = shoot(t_obs, r_obs, theta, phi_perp, angles, rng)
        r_hat, t_hat = network(shots, angles)
        rows["flat scenes"].append([grid_per_mille(s0_of(shots, angles)), grid_per_mille(t_hat), grid_per_mille(r_hat)])
    for capture in samples.captures():
        stack, capture_angles = samples.load(capture, max_side=1024)
        r_hat, t_hat = network(stack, capture_angles)
        rows[capture.name] = [[grid_per_mille(s0_of(stack, capture_angles)), grid_per_mille(t_hat), grid_per_mille(r_hat)]]
    for label, values in rows.items():
        s0, t, r = np.mean(values, axis=0)
        print(f"| {label} | {s0:.3f} | {t:.3f} | {r:.3f} |")

    print(f"\nHighlight halos: T̂ PSNR (dB) within {RING_PX} px of clipped pixels / elsewhere, {args.count} benchmark patches")
    print("| exposure | clipped pixels | network near | network elsewhere | none near | none elsewhere |")
    print("|---|---|---|---|---|---|")
    kernel = np.ones((2 * RING_PX + 1, 2 * RING_PX + 1), np.uint8)
    for gain in (2.0, 4.0):
        near, far, none_near, none_far, clipped_share = [], [], [], [], []
        for i in range(args.count):
            sample = {k: v[i] for k, v in data.items()}
            sample = {**sample, "r": sample["r"] * gain, "t": sample["t"] * gain}
            shots = reshoot(sample, np.radians(angles) + sample["phi_perp"][0, 0], np.random.default_rng([SEED, i]))
            clipped = (shots >= 1.0).any(axis=(0, 3))
            if not clipped.any():
                continue
            ring = (cv2.dilate(clipped.view(np.uint8), kernel) > 0) & ~clipped
            rest = ~(ring | clipped)
            presented = list(np.degrees(np.radians(angles) + sample["phi_perp"][0, 0]))
            t_hat = network(shots, presented)[1]
            s0 = s0_of(shots, presented)
            for where, out, est in ((ring, near, t_hat), (rest, far, t_hat), (ring, none_near, s0), (rest, none_far, s0)):
                if where.any():
                    out.append(float(metrics.psnr(est[where], sample["t"][where])))
            clipped_share.append(float(clipped.mean()))
        print(f"| ×{gain:g} | {100 * np.mean(clipped_share):.1f}% of {len(clipped_share)} patches | {np.mean(near):.2f} | "
              f"{np.mean(far):.2f} | {np.mean(none_near):.2f} | {np.mean(none_far):.2f} |")
    print(f"\nseed {SEED}; {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
