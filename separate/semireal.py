"""The semi-real benchmark (``urd bench --semireal``): real scenes behind a rendered pane.

The paper's synthesis makes the transmitted layer unpolarized; real scenes are not (sky, foliage,
gloss, metal). Here the transmitted layer is a real capture without glass, the held-out side of
`urd.core.samples.no_glass_captures` (never used for training): its Stokes vector, fitted from
its own shots, passes through a pane's Fresnel transmission, and a natural photo (bsds500/test,
or scikit-image's bundled photos) is reflected off the same pane (`separate.optics.pane_stokes`).
The ground truth is exact: R_obs and T_obs are the S0 of the two parts.

Each scene (`SIZE`² crops, seeded, the same for every method):

* the pane: θ and φ⊥ per pixel as the training synthesis draws them (`separate.synthesis.surface_maps`:
  flat or curved, a wide view turning φ⊥ in `PHI_FIELD_PROB` of scenes);
* the reflection: an unpolarized photo, defocused in `DEFOCUS_PROB` of scenes, at a strength
  R_obs/T_obs drawn log-uniform in `STRENGTH` (`FAINT_STRENGTH` in the faint-reflection row);
  grey where the capture is mono;
* the shots: 3, 4 or 6 angles (`SHOT_SETS_DEG`) from a random first angle, each off by up to
  ±`ANGLE_ERROR_DEG`, exposed to a mean S0/2 in [0.1, 0.35] (never clipped; twice the training
  synthesis's exposure), with the training synthesis's shot and read noise levels; the methods
  get the nominal angles.

Conditions (rows): 3 shots (two scenes per capture), 4 and 6 shots (one each); the first 3-shot
scene again with the transmitted layer made unpolarized (what the paper's synthesis shows), and,
for colour captures, made grey (a mono camera: compared with the same scene in colour); and no
glass: the real stack alone, whose answer is R = 0 (scored by the share of light a method puts
into R̂, Σ R̂ / Σ S0); and a 3-shot scene with a faint reflection, where the transmitted light's
polarization can outweigh the reflection's and the side of φ⊥ is hardest to read.
"""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from separate import metrics, optics
from separate.bench import paired_gain
from separate.synthesis import (SynthesisConfig, capture_stokes, default_pool, draw_noise_levels, grey, noise_std, random_crop,
                                surface_maps)
from urd.core import samples
from urd.core.progress import Progress

SEED = 4410
SIZE = 256
SHOT_SETS_DEG = {3: (0.0, 45.0, 90.0), 4: (0.0, 45.0, 90.0, 135.0), 6: (0.0, 30.0, 60.0, 90.0, 120.0, 150.0)}
ANGLE_ERROR_DEG = 2.0
STRENGTH = (0.15, 1.0)
#: R_obs/T_obs of the faint-reflection scenes: a shop window in daylight, where the transmitted
#: light, polarized by the pane and by the scene, can outweigh the reflection's polarization.
FAINT_STRENGTH = (0.02, 0.15)
DEFOCUS_PROB = 0.3
PHI_FIELD_PROB = 0.3
DEFAULT_METHODS = ("none", "schechner", "kong", "farid", "network")
CLASSICAL = ("schechner", "kong", "farid")


@dataclasses.dataclass
class Scene:
    """One benchmark scene: shots (N, H, W, 3) float32 at nominal ``angles_deg``, the true
    observable layers ``r`` and ``t`` (H×W×3, the shots' units), its capture, condition and the
    capture's draw it renders (the variants of a draw share its crop, photo and pane), and the
    pane's θ and φ⊥ (H×W rad; None without glass)."""

    capture: str
    condition: str
    draw: int
    shots: np.ndarray
    angles_deg: list[float]
    r: np.ndarray
    t: np.ndarray
    theta: np.ndarray | None = None
    phi_perp: np.ndarray | None = None


def crop_stokes(rng: np.random.Generator, stokes: np.ndarray, clipped: np.ndarray, size: int) -> np.ndarray:
    """A ``size``² crop (smaller where the capture is) with the fewest clipped pixels of eight
    random tries."""
    h, w = stokes.shape[1:3]
    side = min(size, h, w)
    tries = [(int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))) for _ in range(8)]
    y, x = min(tries, key=lambda yx: clipped[yx[0]:yx[0] + side, yx[1]:yx[1] + side].mean())
    return np.ascontiguousarray(stokes[:, y:y + side, x:x + side])


def shoot(rng: np.random.Generator, stokes: np.ndarray, offsets_deg: Sequence[float]) -> tuple[np.ndarray, list[float], float]:
    """Shots of Stokes light (3, H, W, 3) at a random first angle + ``offsets_deg`` (each off by
    up to ±`ANGLE_ERROR_DEG`), exposed to a mean S0/2 in [0.1, 0.35] below clipping, with sensor
    noise: (shots (N, H, W, 3) in [0, 1], nominal angles (deg), exposure)."""
    nominal = rng.uniform(0.0, 180.0) + np.asarray(offsets_deg)
    true = np.radians(nominal + rng.uniform(-ANGLE_ERROR_DEG, ANGLE_ERROR_DEG, nominal.size))
    clean = np.stack([optics.intensity_from_stokes(stokes, float(phi)) for phi in true])
    exposure = min(rng.uniform(0.2, 0.7) / max(float(stokes[0].mean()), 1e-6), 0.95 / max(float(clean.max()), 1e-6))
    clean = clean * exposure
    shot_gain, read_var = draw_noise_levels(rng)
    noisy = clean + rng.standard_normal(clean.shape).astype(np.float32) * noise_std(clean, shot_gain, read_var)
    return np.clip(noisy, 0.0, 1.0).astype(np.float32), [float(a) for a in nominal], exposure


def glass_scene(rng: np.random.Generator, stokes_t: np.ndarray, photo: np.ndarray, offsets_deg: Sequence[float],
                mono: bool, strength_range: tuple[float, float] = STRENGTH,
                ) -> tuple[np.ndarray, list[float], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A real view (Stokes crop (3, P, P, 3)) behind a pane reflecting ``photo`` (uint8 RGB):
    (shots, nominal angles (deg), R_obs, T_obs, θ, φ⊥) as the module docstring draws them, the
    mean R_obs/T_obs log-uniform in ``strength_range``."""
    size = stokes_t.shape[1]
    refl = optics.photo_to_linear(random_crop(rng, photo, size))
    if mono:
        refl = grey(refl)
    if rng.random() < DEFOCUS_PROB:
        refl = cv2.GaussianBlur(refl, (0, 0), rng.uniform(1.5, 4.0))
    theta, phi_perp = surface_maps(rng, SynthesisConfig(patch=size, phi_field_prob=PHI_FIELD_PROB))
    zeros = np.zeros_like(refl)
    part_r, part_t = optics.pane_stokes(np.stack([refl, zeros, zeros]), stokes_t, theta, phi_perp)
    strength = np.exp(rng.uniform(*np.log(strength_range))) * float(part_t[0].mean()) / max(float(part_r[0].mean()), 1e-6)
    light = part_r * strength + part_t
    shots, angles, exposure = shoot(rng, light, offsets_deg)
    return shots, angles, part_r[0] * strength * exposure, part_t[0] * exposure, theta, phi_perp


def make_scenes(captures: Sequence[samples.Capture] | None = None, size: int = SIZE, seed: int = SEED,
                progress: Progress | None = None) -> list[Scene]:
    """Every condition's scenes (module docstring) from the held-out no-glass captures (or
    ``captures``), seeded; reflections from bsds500/test (bundled photos without ../shared/data)."""
    captures = samples.no_glass_captures(split="test") if captures is None else list(captures)
    if not captures:
        raise FileNotFoundError(f"no held-out no-glass captures in {samples.SHARED} (the real polarization "
                                "captures of ../shared/data: see its README)")
    photos = default_pool("test")
    scenes: list[Scene] = []
    for k, capture in enumerate(captures):
        if progress:
            progress(k, len(captures), f"semi-real scenes: {capture.name}")
        rng = np.random.default_rng([seed, zlib.crc32(capture.name.encode())])     # a capture's scenes whatever the list
        stokes, clipped = capture_stokes(capture)
        for draw, (shots_count, condition) in enumerate([(3, "3 shots"), (3, "3 shots"), (4, "4 shots"), (6, "6 shots")]):
            crop = crop_stokes(rng, stokes, clipped, size)
            photo = photos[int(rng.integers(len(photos)))]
            state = rng.bit_generator.state
            scenes.append(Scene(capture.name, condition, draw, *glass_scene(rng, crop, photo, SHOT_SETS_DEG[shots_count], capture.mono)))
            if draw != 0:
                continue
            variants = [("3 shots, T unpolarized", np.concatenate([crop[:1], np.zeros_like(crop[1:])]), capture.mono)]
            if not capture.mono:
                variants.append(("3 shots, colour made grey", grey(crop), True))
            after = rng.bit_generator.state
            for name, stokes_t, mono in variants:
                rng.bit_generator.state = state
                scenes.append(Scene(capture.name, name, draw, *glass_scene(rng, stokes_t, photo, SHOT_SETS_DEG[3], mono)))
            rng.bit_generator.state = after
        crop = crop_stokes(rng, stokes, clipped, 2 * size)
        shots, angles, exposure = shoot(rng, crop, SHOT_SETS_DEG[3])
        scenes.append(Scene(capture.name, "no glass", 0, shots, angles, np.zeros_like(crop[0]), crop[0] * exposure))
        crop = crop_stokes(rng, stokes, clipped, size)                  # drawn last: the scenes above stay as they were
        photo = photos[int(rng.integers(len(photos)))]
        scenes.append(Scene(capture.name, "3 shots, faint reflection", 0,
                            *glass_scene(rng, crop, photo, SHOT_SETS_DEG[3], capture.mono, FAINT_STRENGTH)))
    if progress:
        progress(len(captures), len(captures), "semi-real scenes")
    return scenes


def score_scenes(scenes: Sequence[Scene], runs: dict[str, Callable], progress: Progress | None = None) -> list[dict]:
    """One record per scene and method: T̂ and R̂ PSNR (dB, linear, peak 1) and the share of light
    put into R̂ (Σ R̂ / Σ S0 of the truth)."""
    records = []
    total = len(scenes) * len(runs)
    for i, scene in enumerate(scenes):
        for j, (name, run) in enumerate(runs.items()):
            if progress:
                progress(i * len(runs) + j, total, f"semi-real: {scene.capture} {scene.condition} {name}")
            r_hat, t_hat = run(scene.shots, scene.angles_deg)
            records.append({"capture": scene.capture, "condition": scene.condition, "draw": scene.draw, "method": name,
                            "psnr_t": float(metrics.psnr(t_hat, scene.t)), "psnr_r": float(metrics.psnr(r_hat, scene.r)),
                            "r_share": float(r_hat.sum() / max(float((scene.r + scene.t).sum()), 1e-9))})
    if progress:
        progress(total, total, "semi-real")
    return records


def format_tables(records: list[dict], methods: Sequence[str]) -> str:
    """The benchmark's Markdown tables: T̂ / R̂ PSNR per condition and method, the network's paired
    T̂ gain over the best classical method per condition, and the no-glass R̂ shares per capture."""
    conditions = [c for c in dict.fromkeys(r["condition"] for r in records) if c != "no glass"]
    methods = [m for m in methods if any(r["method"] == m for r in records)]
    lines = ["T̂ / R̂ PSNR (dB, linear, peak 1), mean over scenes:", "",
             "| condition | scenes | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
    gains = []
    for condition in conditions:
        rows = {m: [r for r in records if r["condition"] == condition and r["method"] == m] for m in methods}
        cells = [f"{np.mean([r['psnr_t'] for r in rows[m]]):.2f} / {np.mean([r['psnr_r'] for r in rows[m]]):.2f}" for m in methods]
        lines.append(f"| {condition} | {len(rows[methods[0]])} | " + " | ".join(cells) + " |")
        classical = [m for m in methods if m in CLASSICAL]
        for learned in (m for m in methods if m not in CLASSICAL and m != "none"):
            if not classical:
                break
            best = max(classical, key=lambda m: np.mean([r["psnr_t"] for r in rows[m]]))
            paired = [{"method": m, "psnr_t_per_patch": [r["psnr_t"] for r in rows[m]]} for m in (learned, best)]
            captures = [r["capture"] for r in rows[learned]]
            gains.append((condition, learned, best, paired_gain(paired, learned, best, groups=captures)))
    if gains:
        lines += ["", "T̂ PSNR of the network minus the best classical method's (paired over scenes, 95% bootstrap interval "
                  "resampling captures):", "",
                  "| condition | network | best classical | difference (dB) | network higher on |", "|---|---|---|---|---|"]
        lines += [f"| {c} | {n} | {b} | {g['mean']:+.2f} ({g['ci95'][0]:+.2f} to {g['ci95'][1]:+.2f}) | {g['wins']} of {g['count']} |"
                  for c, n, b, g in gains]
    grey_rows = [r for r in records if r["condition"] == "3 shots, colour made grey"]
    if grey_rows:
        colour = {(r["capture"], r["method"]): r["psnr_t"] for r in records if r["condition"] == "3 shots" and r["draw"] == 0}
        lines += ["", "Mono against colour: T̂ PSNR of the colour captures' first 3-shot scene made grey minus the same scene "
                  "in colour (dB, mean over captures):", "", "| " + " | ".join(methods) + " |", "|" + "---|" * len(methods)]
        lines.append("| " + " | ".join(f"{np.mean([r['psnr_t'] - colour[r['capture'], m] for r in grey_rows if r['method'] == m]):+.2f}"
                                       for m in methods) + " |")
    no_glass = [r for r in records if r["condition"] == "no glass"]
    if no_glass:
        captures = list(dict.fromkeys(r["capture"] for r in no_glass))
        share = {(r["capture"], r["method"]): r["r_share"] for r in no_glass}
        lines += ["", "No glass: the share of light put into R̂ (Σ R̂ / Σ S0; the answer is 0):", "",
                  "| capture | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
        lines += [f"| {c} | " + " | ".join(f"{share[c, m]:.1%}" for m in methods) + " |" for c in captures]
        lines.append("| **mean** | " + " | ".join(f"**{np.mean([share[c, m] for c in captures]):.1%}**" for m in methods) + " |")
    return "\n".join(lines) + "\n"


def run_semireal(methods: Sequence[str] = DEFAULT_METHODS, weights: Path | None = None, size: int = SIZE,
                 captures: Sequence[samples.Capture] | None = None, progress: Progress | None = None) -> tuple[str, list[dict]]:
    """Make the scenes, score every method (each with its default reference; LABEL=PATH: the
    network with the weights at PATH) and return the Markdown tables and the per-scene records."""
    from separate.methods import get_method

    runs = {}
    for method in methods:
        label, _, path = method.partition("=")
        if path:
            runs[label] = get_method("network", weights=Path(path))[0]
        else:
            runs[label] = get_method(label, **({"weights": weights} if label == "network" and weights else {}))[0]
    methods = list(runs)
    scenes = make_scenes(captures, size, progress=progress)
    records = score_scenes(scenes, runs, progress)
    names = ", ".join(dict.fromkeys(s.capture for s in scenes))
    header = (f"## Semi-real benchmark: {size}² crops of {len(set(s.capture for s in scenes))} held-out real captures "
              f"without glass behind a rendered pane, weights {weights or 'shipped'}\n\nCaptures: {names}.\n\n")
    return header + format_tables(records, methods), records
