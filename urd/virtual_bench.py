"""The virtual-camera benchmark (``urd bench --virtual``): the network against the classical
methods on scenes rendered by urd's virtual camera, where the physical model of the closed-form
inversions holds.

Two sets, each a table of T̂ and R̂ PSNR (dB, linear values, peak 1, mean over scenes), and a
table of the angle-of-incidence estimate against the truth on the first set:

1. **angles of incidence**: one flat pane (`acquire.virtual_camera.make_glass_scene`, not
   curved) at θ = `THETAS_DEG`, φ⊥ 30/50/70/90° turning 6° down the frame and θ changing
   along the plane of incidence (the image direction φ⊥ − 90°), for ``pairs`` photo pairs
   (bsds500/test from ../shared/data, else scikit-image's bundled photos); shots at 0/45/90°
   with ±2° angle errors and the camera's shot and read noise, aligned (no shake, no mosaic);
2. **wide view**: the same panes at θ = 50° with φ⊥ turning by `WIDE_TURN_DEG` across the
   frame (a wide-angle lens in front of a shop window); each polarization method with the
   per-pixel reference field ("auto") and with one global reference ("global").

θ estimate: the median over pixels of |θ̂ − θ| (deg), for the per-pixel field
(`separate.incidence.estimate_incidence_field`, what the network uses) and for one number per
view (`separate.incidence.estimate_incidence_deg`); θ turns across these panes by the
perspective (the table gives its range).

Seeded (`SEED`); every method sees the same shots. It lives above `acquire` and `separate`
because it renders with the one and scores the other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from acquire.virtual_camera import GlassScene, VirtualCamera, make_glass_scene
from separate import metrics
from separate.methods import get_method
from separate.presentation import field_at
from separate.incidence import estimate_incidence_deg, estimate_incidence_field
from separate.reference import estimate_reference_field
from separate.synthesis import SHARED_NATURAL
from urd.core.progress import Progress

THETAS_DEG = (20.0, 35.0, 50.0, 65.0, 75.0)
WIDE_TURN_DEG = 50.0
SEED = 2018
POLARIZATION_METHODS = ("network", "schechner", "kong", "farid")
DEFAULT_METHODS = ("none",) + POLARIZATION_METHODS


def photo_pairs(count: int) -> list[tuple[Path | None, Path | None]]:
    """``count`` seeded (reflection, transmission) photo files from bsds500/test; (None, None)
    pairs (the bundled photos) where that folder is absent."""
    folder = SHARED_NATURAL / "bsds500" / "test"
    if not folder.is_dir():
        return [(None, None)] * count
    files = sorted(folder.glob("*.jpg"))
    rng = np.random.default_rng(SEED)
    return [tuple(files[i] for i in rng.choice(len(files), 2, replace=False)) for _ in range(count)]


def shoot(scene: GlassScene, seed: int) -> tuple[np.ndarray, list[float], np.ndarray, np.ndarray]:
    """Shots (3, H, W, 3) at 0/45/90° with ±2° errors, the camera's gain and shot and read noise,
    the nominal angles (deg), and the layers (R_obs, T_obs) in the shots' units."""
    rng = np.random.default_rng(seed)
    truth = iter(np.array([0.0, 45.0, 90.0]) + rng.uniform(-2.0, 2.0, 3))
    camera = VirtualCamera(scene, lambda: next(truth), shake_px=0.0, shake_deg=0.0, seed=seed)
    white_dn = camera.white_level - camera.black_level
    shots = []
    for index in range(3):
        img = camera.render(float(camera.angle_source()), index)
        noise = np.sqrt(np.clip(img, 0, None) / camera.full_well + (camera.read_noise_dn / white_dn) ** 2)
        shots.append(np.clip(img + rng.standard_normal(img.shape).astype(np.float32) * noise, 0.0, 1.0))
    r_obs, t_obs = scene.layers()
    return np.stack(shots).astype(np.float32), [0.0, 45.0, 90.0], r_obs * camera.gain, t_obs * camera.gain


def _runs(methods: tuple[str, ...], references: tuple[str, ...], weights: Path | None) -> dict:
    """label → run for each method and reference policy (the S0-only 'none' once)."""
    runs = {}
    for name in methods:
        options = {"weights": weights} if name == "network" and weights else {}
        for reference in (("auto",) if name == "none" else references):
            label = name if len(references) == 1 or name == "none" else f"{name} ({reference})"
            runs[label] = get_method(name, reference=reference, **options)[0]
    return runs


def _score(runs: dict, scenes: list) -> dict[str, tuple[float, float]]:
    """label → (mean T̂ PSNR, mean R̂ PSNR) over ``scenes`` (dB)."""
    out = {}
    for label, run in runs.items():
        t_psnr, r_psnr = [], []
        for shots, angles, r_obs, t_obs in scenes:
            r_hat, t_hat = run(shots, angles)
            t_psnr.append(float(metrics.psnr(t_hat, t_obs)))
            r_psnr.append(float(metrics.psnr(r_hat, r_obs)))
        out[label] = (float(np.mean(t_psnr)), float(np.mean(r_psnr)))
    return out


def _incidence_errors(pane: GlassScene, shots: np.ndarray, angles: list[float]) -> tuple[float, float, float, float]:
    """Median |θ̂ − θ| (deg) of the per-pixel field and of the one-number estimate, and the true
    θ range (deg) of a pane."""
    truth = np.degrees(pane.theta)
    reference = estimate_reference_field(shots, angles)
    field = field_at(estimate_incidence_field(shots, angles, reference), truth.shape)
    one = estimate_incidence_deg(shots, angles, reference)
    return (float(np.median(np.abs(field - truth))), float(np.median(np.abs(one - truth))),
            float(truth.min()), float(truth.max()))


def run_virtual_bench(methods: tuple[str, ...] = DEFAULT_METHODS, weights: Path | None = None,
                      size: tuple[int, int] = (768, 512), pairs: int = 4, progress: Progress | None = None) -> str:
    """Run both sets (module docstring) and return them as Markdown tables.

    Args:
        methods: method names (`separate.methods.METHODS`).
        weights: the network's weights (default: shipped).
        size: scene size (width, height) px.
        pairs: photo pairs per angle of incidence (and in the wide set).
        progress: called with (rows done, rows total, label).
    """
    width, height = size
    photos = photo_pairs(pairs)
    runs = _runs(tuple(methods), ("auto",), weights)
    lines = [f"## Virtual camera, {width}x{height}, {len(photos)} photo pairs per row, weights {weights or 'shipped'}", "",
             "T̂ / R̂ PSNR (dB) by angle of incidence θ:", "",
             "| θ | " + " | ".join(runs) + " |", "|---|" + "---|" * len(runs)]
    totals: dict[str, list[float]] = {label: [] for label in runs}
    incidence = []
    for k, theta in enumerate(THETAS_DEG):
        if progress:
            progress(k, len(THETAS_DEG) + 1, "bench --virtual")
        panes = [make_glass_scene(width, height, r, t, curved=False, theta_center_deg=theta, phi_perp_deg=30.0 + 20 * j)
                 for j, (r, t) in enumerate(photos)]
        scenes = [shoot(pane, seed=SEED + j) for j, pane in enumerate(panes)]
        incidence.append((theta, *np.mean([_incidence_errors(pane, scene[0], scene[1]) for pane, scene in zip(panes, scenes)], axis=0)))
        row = _score(runs, scenes)
        for label, (t_psnr, _) in row.items():
            totals[label].append(t_psnr)
        lines.append(f"| {theta:.0f}° | " + " | ".join(f"{t:.2f} / {r:.2f}" for t, r in row.values()) + " |")
    lines.append("| mean T̂ | " + " | ".join(f"{np.mean(v):.2f}" for v in totals.values()) + " |")
    lines += ["", "Angle-of-incidence estimate: median |θ̂ − θ| over the pixels (deg), mean over scenes:", "",
              "| θ | true range | per-pixel field | one per view |", "|---|---|---|---|"]
    lines += [f"| {theta:.0f}° | {lo:.0f}–{hi:.0f}° | {field:.1f} | {one:.1f} |" for theta, field, one, lo, hi in incidence]
    if progress:
        progress(len(THETAS_DEG), len(THETAS_DEG) + 1, "bench --virtual")
    wide_runs = _runs(tuple(m for m in methods if m in POLARIZATION_METHODS), ("auto", "global"), weights)
    scenes = []
    for j, (r, t) in enumerate(photos):
        scene = make_glass_scene(width, height, r, t, curved=False, theta_center_deg=50.0, phi_perp_deg=60.0 + 40 * j)
        xs = np.linspace(-0.5, 0.5, width)[None, :]
        scene.phi_perp = np.broadcast_to(np.radians(60.0 + 40 * j + WIDE_TURN_DEG * xs), (height, width)).astype(np.float32)
        scenes.append(shoot(scene, seed=SEED + 100 + j))
    lines += ["", f"Wide view: φ⊥ turning by {WIDE_TURN_DEG:.0f}° across the frame, θ = 50°; per-pixel reference "
              "field (auto) against one global reference:", "", "| method | T̂ PSNR | R̂ PSNR |", "|---|---|---|"]
    lines += [f"| {label} | {t:.2f} | {r:.2f} |" for label, (t, r) in _score(wide_runs, scenes).items()]
    if progress:
        progress(len(THETAS_DEG) + 1, len(THETAS_DEG) + 1, "bench --virtual")
    return "\n".join(lines) + "\n"
