"""The network against the classical methods on scenes rendered by urd's virtual camera.

    python tools/bench_virtual.py [--size 768x512] [--pairs 4] [--weights PATH] [--methods ...]

Two sets, printed as tables of T̂ and R̂ PSNR (dB, linear values, peak 1, mean over scenes):

1. **angles of incidence**: one flat pane (`acquire.virtual_camera.make_glass_scene`, not
   curved) at θ = 20/35/50/65/75°, φ⊥ turning 6° down the frame, for ``--pairs`` photo pairs
   (bsds500/test from ../shared/data, else scikit-image's bundled photos); shots at 0/45/90°
   with ±2° angle errors and the camera's shot and read noise, aligned (no shake, no mosaic):
   what the closed-form inversion is built for;
2. **wide view**: the same panes at θ = 50° with φ⊥ turning by 50° across the frame (a
   wide-angle lens in front of a shop window); each polarization method with the per-pixel
   reference field ("auto") and with one global reference ("global").

Seeded (2018); every method sees the same shots.
"""

import argparse
import time
from pathlib import Path

import numpy as np

from acquire.virtual_camera import GlassScene, VirtualCamera, make_glass_scene
from separate import metrics
from separate.methods import get_method
from separate.synthesis import SHARED_NATURAL

THETAS_DEG = (20.0, 35.0, 50.0, 65.0, 75.0)
WIDE_TURN_DEG = 50.0
SEED = 2018

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--size", default="768x512", help="scene size WxH (px)")
parser.add_argument("--pairs", type=int, default=4, help="photo pairs per angle of incidence")
parser.add_argument("--weights", type=Path, default=None, help="network weights (default: shipped)")
parser.add_argument("--methods", nargs="+", default=["none", "network", "schechner", "kong", "farid"])
args = parser.parse_args()
width, height = (int(v) for v in args.size.split("x"))


def photo_pairs(count: int) -> list[tuple[Path | None, Path | None]]:
    """``count`` (reflection, transmission) photo files; (None, None) pairs mean the bundled photos."""
    folder = SHARED_NATURAL / "bsds500" / "test"
    if not folder.is_dir():
        return [(None, None)] * count
    files = sorted(folder.glob("*.jpg"))
    rng = np.random.default_rng(SEED)
    return [tuple(files[i] for i in rng.choice(len(files), 2, replace=False)) for _ in range(count)]


def shoot(scene: GlassScene, seed: int) -> tuple[np.ndarray, list[float], np.ndarray, np.ndarray]:
    """Shots at 0/45/90° (±2° errors), the camera's gain and noise; the layers in the same units."""
    rng = np.random.default_rng(seed)
    truth = iter(np.array([0.0, 45.0, 90.0]) + rng.uniform(-2.0, 2.0, 3))
    camera = VirtualCamera(scene, lambda: next(truth), shake_px=0.0, shake_deg=0.0, seed=seed)
    shots = []
    for index in range(3):
        img = camera.render(float(camera.angle_source()), index)
        noise = np.sqrt(np.clip(img, 0, None) / camera.full_well + (camera.read_noise_dn / 3839.0) ** 2)
        shots.append(np.clip(img + rng.standard_normal(img.shape).astype(np.float32) * noise, 0.0, 1.0))
    r_obs, t_obs = scene.layers()
    return np.stack(shots).astype(np.float32), [0.0, 45.0, 90.0], r_obs * camera.gain, t_obs * camera.gain


def methods(names: list[str], references: tuple[str, ...]) -> dict:
    runs = {}
    for name in names:
        options = {"weights": args.weights} if name == "network" and args.weights else {}
        for reference in (references if name not in ("none",) else ("auto",)):
            label = name if len(references) == 1 or name == "none" else f"{name} ({reference})"
            runs[label] = get_method(name, reference=reference, **options)[0]
    return runs


def score(runs: dict, scenes: list) -> dict[str, tuple[float, float]]:
    out = {}
    for label, run in runs.items():
        t_psnr, r_psnr = [], []
        for shots, angles, r_obs, t_obs in scenes:
            r_hat, t_hat = run(shots, angles)
            t_psnr.append(float(metrics.psnr(t_hat, t_obs)))
            r_psnr.append(float(metrics.psnr(r_hat, r_obs)))
        out[label] = (float(np.mean(t_psnr)), float(np.mean(r_psnr)))
    return out


start = time.time()
pairs = photo_pairs(args.pairs)
runs = methods(args.methods, ("auto",))
print(f"# Virtual-camera scenes, {width}x{height}, {len(pairs)} photo pairs per row, weights {args.weights or 'shipped'}\n")
print("| θ | " + " | ".join(runs) + " |")
print("|---|" + "---|" * len(runs))
totals: dict[str, list[float]] = {label: [] for label in runs}
for theta in THETAS_DEG:
    scenes = [shoot(make_glass_scene(width, height, r, t, curved=False, theta_center_deg=theta, phi_perp_deg=30.0 + 20 * k),
                    seed=SEED + k) for k, (r, t) in enumerate(pairs)]
    row = score(runs, scenes)
    for label, (t_psnr, _) in row.items():
        totals[label].append(t_psnr)
    print(f"| {theta:.0f}° | " + " | ".join(f"T {t:.2f} / R {r:.2f}" for t, r in row.values()) + " |")
print("| mean T | " + " | ".join(f"{np.mean(v):.2f}" for v in totals.values()) + " |")

polarization = [m for m in args.methods if m in ("network", "schechner", "kong", "farid")]
runs = methods(polarization, ("auto", "global"))
print(f"\n# Wide view: φ⊥ turning by {WIDE_TURN_DEG:.0f}° across the frame, θ = 50°\n")
scenes = []
for k, (r, t) in enumerate(pairs):
    scene = make_glass_scene(width, height, r, t, curved=False, theta_center_deg=50.0)
    xs = np.linspace(-0.5, 0.5, width)[None, :]
    scene.phi_perp = np.broadcast_to(np.radians(60.0 + 40 * k + WIDE_TURN_DEG * xs), (height, width)).astype(np.float32)
    scenes.append(shoot(scene, seed=SEED + 100 + k))
print("| method | T̂ PSNR | R̂ PSNR |\n|---|---|---|")
for label, (t_psnr, r_psnr) in score(runs, scenes).items():
    print(f"| {label} | {t_psnr:.2f} | {r_psnr:.2f} |")
print(f"\n{time.time() - start:.0f} s")
