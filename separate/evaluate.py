"""The paper's evaluation (ECCV 2018 §4) reproduced: tables (Markdown, CSV) and plots (PNG).

Three parts, written by `run_evaluation` into ``out_dir/quick`` or ``out_dir/full``:

1. **Cross-validation** (the paper's Table 1): RMSE, PSNR and SSIM of R̂ and T̂ for every
   method on held-out synthetic sets made from photos no shipped model saw in training
   (training drew from bsds500/train + sunhays80, validation from bsds500/val):
   ``bsds500-test`` (../shared/data; skipped where absent, never replaced), scikit-image's
   bundled photos (``skimage-bundled``, `separate.synthesis.BUNDLED_PHOTOS`) and any folder
   the user names (`load_photos`). Each set is seeded patches through the full synthesis
   pipeline (DR + NRD + LCG, ±4° angle errors, sensor noise, the paper's angles), scored as
   `separate.bench` scores its benchmark (the ``bsds500-test`` set *is* that benchmark's set):
   the methods get the nominal angles 0/45/90 and pick their reference themselves.
2. **Robustness**: the layers of seeded bsds500/test patches (of the bundled photos where
   bsds500/test is absent; the quick check then skips these figures) rendered again with
   `separate.optics` under controlled conditions (`Condition`), one factor
   at a time from a base condition (exact angles 0/45/90, no misalignment, medium noise, φ⊥
   within ±45° of the first shot, as the synthesizer draws it): polarizer angle error,
   residual misalignment, noise, φ⊥ relative to the first shot, number of angles, nominal
   versus calibrated angles (`AXES`). Every condition of a patch uses the same random draws
   (`Draws`), so conditions and methods are compared on paired data; the network − direct
   T̂ PSNR gap gets a paired bootstrap interval (`separate.bench.paired_gain`).
   A method that refuses an input (ValueError, e.g. calibrated angles spanning less than
   90°) scores NaN on that patch: its means leave the patch out and the tables count refusals.
3. **Speed and memory**: each method on a 1-megapixel scene in a fresh process (seconds and
   peak resident memory of the call), synthesis throughput (patches/s) and training throughput
   (steps/s of `separate.train` on a tiny config); 24 MP with ``large``.

Quick mode (`settings_for`) runs a reduced version in minutes and checks its figures against
``docs/bench/expected-quick.json`` (`check_figures`, tolerances `TOLERANCES`), raising
`BenchmarkMismatch` naming every figure out of tolerance; ``update_expected`` rewrites it.
Plots are drawn with OpenCV (`plot_lines`, `plot_bars`). Figures are linear values, peak 1,
PSNR floored at 60 dB per patch (`separate.metrics`).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import datetime
import enum
import io
import json
import math
import multiprocessing
import os
import platform
import shlex
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from separate import metrics, optics
from separate.bench import DIRECT_WEIGHTS, SEED, format_table, paired_gain
from separate.synthesis import SHARED_NATURAL, AngleMode, SynthesisConfig, Synthesizer, load_image_pool, noise_std
from urd.dataset import atomic_path
from urd.errors import UrdError

REPO = Path(__file__).resolve().parent.parent
DEFAULT_OUT = REPO / "docs" / "bench"
EXPECTED_QUICK = DEFAULT_OUT / "expected-quick.json"
#: The command that rewrites the expected values of the quick run (after new weights).
UPDATE_COMMAND = "python tools/bench_paper.py --quick --update-expected"
EXPECTED_SCHEMA = "urd.bench.expected-quick"
ROBUST_SEED = SEED + 1
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: Photos are reduced to this many pixels on the long side, as `load_image_pool` does.
MAX_SIDE = 512
ALL_METHODS = ("none", "network", "direct", "schechner", "kong", "farid", "li-brown", "arvanitopoulos", "ceilnet")
QUICK_METHODS = ("none", "network", "direct", "schechner")
#: Methods timed at 24 MP (full run with ``large``).
LARGE_METHODS = ("network", "schechner")
MAX_SHOTS = 6
#: Seconds one isolated measurement (a method at 1 or 24 MP, the training steps) may take.
ISOLATED_TIMEOUT_S = 3600.0

Progress = Callable[[int, int, str], None]


class BenchmarkMismatch(UrdError, ValueError):
    """Figures of the quick evaluation differ from the committed expected values beyond their tolerance."""


# ----------------------------------------------------------------------------- photos


def to_pool_image(image: np.ndarray, max_side: int = MAX_SIDE) -> np.ndarray:
    """A decoded photo as the synthesizer's pool holds it: (H, W, 3) uint8 RGB.

    The synthesizer crops and resizes 8-bit display-encoded photos and decodes them with
    `separate.optics.photo_to_linear` (v/255)^2.2, so 16-bit values are taken as display-encoded too
    (as 16-bit PNG and TIFF exports of photos are) and rounded to 8 bits, v/257.

    Args:
        image: (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) uint8 or uint16, RGB(A) order; grey
            is repeated into three channels, alpha dropped.
        max_side: the long side is reduced to this (area averaging) when larger.
    """
    if not isinstance(image, np.ndarray):
        raise TypeError(f"expected a numpy array, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] in (1, 3, 4):
        image = image[..., :3] if image.shape[2] != 1 else image[..., 0]
    if image.ndim != 2 and not (image.ndim == 3 and image.shape[2] == 3):
        raise ValueError(f"expected a grey, RGB or RGBA image (H, W[, 1|3|4]), got shape {image.shape}")
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"expected an 8- or 16-bit integer image, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    scale = max_side / max(image.shape[:2])
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(image)


def load_photo(path: Path, max_side: int = MAX_SIDE) -> np.ndarray:
    """Read a JPEG, PNG or TIFF photo (8 or 16 bit, grey, RGB or RGBA) as `to_pool_image` gives it."""
    path = Path(path)
    if path.suffix.lower() not in PHOTO_SUFFIXES:
        raise ValueError(f"expected a photo ending in {', '.join(PHOTO_SUFFIXES)}, got {path.name}")
    if path.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            image = tifffile.imread(path)
        except Exception as exc:  # noqa: BLE001 - tifffile raises many types for unreadable files
            raise ValueError(f"cannot read image {path}: {exc}") from exc
    else:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"cannot read image {path}")
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    try:
        return to_pool_image(image, max_side)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def load_photos(folder: Path, max_side: int = MAX_SIDE) -> list[np.ndarray]:
    """Every photo in ``folder`` (not its subfolders), sorted by name, as `load_photo` reads it."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"expected a folder of photos, got {folder}")
    files = sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in PHOTO_SUFFIXES)
    if not files:
        raise ValueError(f"expected photos ({', '.join(PHOTO_SUFFIXES)}) in {folder}, got none")
    return [load_photo(f, max_side) for f in files]


def photo_pools(images_dir: Path | None = None) -> list[tuple[str, str, list[np.ndarray] | None]]:
    """The held-out photo sets: (name, description, pool or None where the photos are absent)."""
    bsds = SHARED_NATURAL / "bsds500" / "test"
    pools = [
        ("bsds500-test", "BSDS500 test split, 200 photos (../shared/data)", load_image_pool([bsds]) if bsds.is_dir() else None),
        ("skimage-bundled", "scikit-image's bundled photos", load_image_pool(None)),
    ]
    if images_dir is not None:
        pools.append((f"images-{Path(images_dir).name}", f"the photos in {images_dir}", load_photos(Path(images_dir))))
    return pools


def synthetic_set(pool: list[np.ndarray], count: int, size: int, seed: int = SEED) -> dict[str, np.ndarray]:
    """``count`` patches of ``size``² from ``pool`` through the full synthesis pipeline with the
    paper's angles (`separate.synthesis.Synthesizer`, ``AngleMode.CLASSIC``); for bsds500/test
    and the default seed, the same patches as `separate.bench.benchmark_set`."""
    if count < 1 or size < 64:
        raise ValueError(f"expected at least 1 patch of at least 64 px, got {count} of {size} px")
    usable = sum(min(img.shape[:2]) >= size for img in pool)
    if usable < 2:
        raise ValueError(f"expected at least 2 photos of at least {size} px on the short side, got {usable}")
    return Synthesizer(pool, SynthesisConfig(patch=size, angles=AngleMode.CLASSIC), seed=seed).batch(count)


# ----------------------------------------------------------------------------- conditions


class Noise(enum.Enum):
    """Sensor noise levels: the ends and the log-middle of the synthesizer's range."""

    LOW = "low"
    MEDIUM = "medium"
    HIGH = "high"


#: (shot-noise gain, read-noise variance) per level: a pixel of value v gets N(0, gain·v + read).
NOISE_GAINS = {Noise.LOW: (1e-4, 1e-7), Noise.MEDIUM: (10**-3.25, 1e-6), Noise.HIGH: (10**-2.5, 1e-5)}


@dataclasses.dataclass(frozen=True)
class Condition:
    """How the shots of a robustness patch are taken.

    Attributes:
        angle_error_deg: each shot's polarizer is off its nominal angle by e·u, u ~ U[−1, 1]
            drawn per shot (so within ±e, the paper's error model at e = 4°).
        misalign_px: shots 2.. are shifted by this many pixels, each in a random direction,
            after rendering (residual misalignment; the first shot and the layers stay put).
        noise: sensor noise level (`NOISE_GAINS`).
        phi_perp_offset_deg: φ⊥ − φ0, the s-direction relative to the first shot's nominal
            angle; None: drawn per patch from U[−45°, 45°] as the synthesizer does.
        angles_deg: nominal polarizer angles relative to the first shot.
        calibrated: the methods get the true angles (a perfect calibration) instead of the nominal ones.
    """

    angle_error_deg: float = 0.0
    misalign_px: float = 0.0
    noise: Noise = Noise.MEDIUM
    phi_perp_offset_deg: float | None = None
    angles_deg: tuple[float, ...] = optics.PAPER_ANGLES_DEG
    calibrated: bool = False

    def __post_init__(self):
        object.__setattr__(self, "noise", Noise(self.noise))
        object.__setattr__(self, "angles_deg", tuple(float(a) for a in self.angles_deg))
        if not 3 <= len(self.angles_deg) <= MAX_SHOTS:
            raise ValueError(f"expected 3 to {MAX_SHOTS} angles, got {list(self.angles_deg)}")
        if self.angle_error_deg < 0 or self.misalign_px < 0:
            raise ValueError(f"expected angle error and misalignment ≥ 0, got {self.angle_error_deg} deg and {self.misalign_px} px")


@dataclasses.dataclass(frozen=True, eq=False)
class Draws:
    """A patch's random draws, shared by every condition (common random numbers).

    Attributes:
        phi_perp_offset_deg: φ⊥ − φ0 when the condition leaves it open, in [−45, 45].
        angle_units: (MAX_SHOTS,) in [−1, 1]: shot k's angle error is e·angle_units[k].
        shift_directions: (MAX_SHOTS,) rad: shot k ≥ 1 moves along this direction.
        noise: (MAX_SHOTS, P, P, C) float32 standard normal values.
    """

    phi_perp_offset_deg: float
    angle_units: np.ndarray
    shift_directions: np.ndarray
    noise: np.ndarray


def draw_nuisances(index: int, shape: tuple[int, int, int], seed: int = ROBUST_SEED) -> Draws:
    """The draws of robustness patch ``index`` with layers of ``shape`` (P, P, C); deterministic."""
    rng = np.random.default_rng([seed, index])
    return Draws(float(rng.uniform(-45.0, 45.0)), rng.uniform(-1.0, 1.0, MAX_SHOTS),
                 rng.uniform(0.0, 2 * np.pi, MAX_SHOTS), rng.standard_normal((MAX_SHOTS, *shape), dtype=np.float32))


def shift_image(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``image`` (H, W[, C]) float32 with its content moved by (dx, dy) px (x: columns, y: rows).

    Band-limited (Fourier) interpolation of the image padded by reflection: an integer shift
    moves pixels exactly, a sub-pixel one neither blurs nor quantizes the shift (OpenCV's
    remap rounds it to 1/32 px, and bilinear weights blur); a zero shift returns a copy.
    """
    if dx == 0 and dy == 0:
        return image.copy()
    pad = 8 + int(math.ceil(max(abs(dx), abs(dy))))
    widths = ((pad, pad), (pad, pad)) + ((0, 0),) * (image.ndim - 2)
    padded = np.pad(image.astype(np.float64), widths, mode="reflect")
    h, w = padded.shape[:2]
    ramp = np.exp(-2j * np.pi * (np.fft.fftfreq(h)[:, None] * dy + np.fft.rfftfreq(w)[None, :] * dx))
    ramp = ramp.reshape(ramp.shape + (1,) * (image.ndim - 2))
    moved = np.fft.irfft2(np.fft.rfft2(padded, axes=(0, 1)) * ramp, s=(h, w), axes=(0, 1))
    return moved[pad : pad + image.shape[0], pad : pad + image.shape[1]].astype(np.float32)


def render_condition(layers: dict[str, np.ndarray], condition: Condition, draws: Draws,
                     n: float = optics.N_GLASS) -> tuple[np.ndarray, list[float], list[float]]:
    """Shoot a patch's scene under ``condition``.

    Args:
        layers: a synthesizer sample's ``r``, ``t`` (P, P, C) observable layers, ``theta`` and
            ``phi_perp`` (P, P) rad; the radiances are recovered as R/ρ and T/(1−ρ).
        condition: what to vary (`Condition`).
        draws: the patch's random draws (`draw_nuisances`).

    Returns:
        (shots, given_deg, true_deg): (N, P, P, C) float32 in [0, 1]; the angles the methods
        get (nominal, or the true ones when ``condition.calibrated``) and the true angles, both
        in degrees relative to the first shot's nominal angle φ0. The ground truth stays
        ``layers["r"]``, ``layers["t"]``.
    """
    r, t, theta, phi_perp = layers["r"], layers["t"], layers["theta"], layers["phi_perp"]
    if draws.noise.shape[1:] != r.shape:
        raise ValueError(f"expected draws for layers of shape {r.shape}, got {draws.noise.shape[1:]}")
    i_r, i_t = optics.radiances_from_layers(r, t, theta, n)
    offset = draws.phi_perp_offset_deg if condition.phi_perp_offset_deg is None else condition.phi_perp_offset_deg
    phi0_deg = float(np.degrees(phi_perp.flat[0])) - offset
    count = len(condition.angles_deg)
    nominal = np.asarray(condition.angles_deg)
    true = nominal + condition.angle_error_deg * draws.angle_units[:count]
    shots = []
    for k, angle in enumerate(true):
        shot = optics.render(i_r, i_t, theta, phi_perp, float(np.radians(phi0_deg + angle)), n).astype(np.float32)
        if k and condition.misalign_px:
            direction = draws.shift_directions[k]
            shot = shift_image(shot, condition.misalign_px * math.cos(direction), condition.misalign_px * math.sin(direction))
        shots.append(shot)
    shots = np.stack(shots)
    gain, read = NOISE_GAINS[condition.noise]
    shots = shots + draws.noise[:count] * noise_std(shots, gain, read)
    given = true if condition.calibrated else nominal
    return np.clip(shots, 0.0, 1.0).astype(np.float32), [float(a) for a in given], [float(a) for a in true]


@dataclasses.dataclass(frozen=True)
class Axis:
    """One robustness factor: its levels (plot label, condition), the quick run's subset, titles."""

    letter: str
    name: str
    title: str
    x_title: str
    levels: tuple[tuple[str, Condition], ...]
    quick: tuple[str, ...]

    def conditions(self, quick: bool) -> tuple[tuple[str, Condition], ...]:
        return tuple(level for level in self.levels if not quick or level[0] in self.quick)


AXES = (
    Axis("a", "angle-error", "(a) polarizer angle error: each shot off by up to ±e (U[−e, e]), nominal angles given",
         "angle error e (deg)", tuple((f"{e:g}", Condition(angle_error_deg=e)) for e in (0.0, 2.0, 4.0, 8.0)), ("0", "8")),
    Axis("b", "misalignment", "(b) residual misalignment: shots 2.. shifted by m px in random directions after rendering",
         "shift m (px)", tuple((f"{m:g}", Condition(misalign_px=m)) for m in (0.0, 0.5, 1.0, 2.0)), ("0", "2")),
    Axis("c", "noise", "(c) sensor noise: shot-noise gain and read-noise variance (1e-4, 1e-7), (10^-3.25, 1e-6), (10^-2.5, 1e-5)",
         "noise level", tuple((level.value, Condition(noise=level)) for level in Noise), ("low", "high")),
    Axis("d", "reference", "(d) s-direction relative to the first shot, φ⊥ − φ0",
         "phi_perp - phi_0 (deg)", tuple((f"{d:g}", Condition(phi_perp_offset_deg=d)) for d in range(0, 91, 15)), ("0", "90")),
    Axis("e", "angles", "(e) number of polarizer angles: 0/45/90, 0/45/90/135, 0/30/…/150",
         "angles", (("3", Condition()), ("4", Condition(angles_deg=(0, 45, 90, 135))),
                    ("6", Condition(angles_deg=(0, 30, 60, 90, 120, 150)))), ("3", "6")),
    Axis("f", "calibration", "(f) nominal vs calibrated angles (the true ones) given, shots off by up to ±e",
         "angles given, e (deg)", tuple((f"{'calibrated' if c else 'nominal'} {e:g}", Condition(angle_error_deg=e, calibrated=c))
                                       for e in (4.0, 8.0) for c in (False, True)), ("nominal 4", "calibrated 4")),
)


# ----------------------------------------------------------------------------- scoring


def make_method(name: str) -> tuple[Callable, dict]:
    """``(run, info)`` of a method of `separate.methods` or "direct" (the network with the direct
    variant's weights); every method with its default ("auto") reference."""
    from separate.methods import get_method

    if name == "direct":
        return get_method("network", weights=DIRECT_WEIGHTS)
    return get_method(name)


SCORES = ("rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r", "ssim_r")


def score(r_hat: np.ndarray, t_hat: np.ndarray, r: np.ndarray, t: np.ndarray, with_ssim: bool = True) -> dict[str, float]:
    """RMSE, PSNR (and SSIM, on values clipped to [0, 1]) of R̂ and T̂ against the truth, as
    `separate.bench` scores them."""
    out = {}
    for layer, est, ref in (("r", r_hat, r), ("t", t_hat, t)):
        out[f"rmse_{layer}"] = float(metrics.rmse(est, ref))
        out[f"psnr_{layer}"] = float(metrics.psnr(est, ref))
        if with_ssim:
            out[f"ssim_{layer}"] = metrics.ssim(np.clip(est, 0, 1), np.clip(ref, 0, 1))
    return out


def attempt(run: Callable, shots: np.ndarray, angles_deg: Sequence[float], truth: tuple[np.ndarray, np.ndarray],
            with_ssim: bool = True) -> tuple[dict[str, float], str | None]:
    """``score`` of one call of a method, or NaN figures and the message when the method
    refuses the input (ValueError: e.g. calibrated angles spanning less than it accepts)."""
    try:
        r_hat, t_hat = run(shots, list(angles_deg))
    except ValueError as exc:
        keys = SCORES if with_ssim else ("rmse_t", "psnr_t", "rmse_r", "psnr_r")
        return dict.fromkeys(keys, float("nan")), str(exc)
    return score(r_hat, t_hat, *truth, with_ssim=with_ssim), None


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def cross_validate(data: dict[str, np.ndarray], methods: dict[str, Callable], angles_deg: Sequence[float] = optics.PAPER_ANGLES_DEG,
                   progress: Progress | None = None, label: str = "cross-validation") -> list[dict]:
    """Score each method on a synthetic set; rows as `separate.bench.run_benchmark` gives them
    (means of RMSE/PSNR/SSIM of R̂ and T̂, ``seconds_per_patch``, ``psnr_t_per_patch``) plus
    ``psnr_r_per_patch``, ``failed`` (patches the method refused, NaN per patch, left out of
    the means) and ``failure`` (the first refusal's message)."""
    rows, count = [], len(data["obs"])
    done, total = 0, count * len(methods)
    for name, run in methods.items():
        scores: dict[str, list[float]] = {k: [] for k in SCORES}
        failures = []
        started = time.perf_counter()
        for obs, r, t in zip(data["obs"], data["r"], data["t"]):
            figures, failure = attempt(run, obs, angles_deg, (r, t))
            for key, value in figures.items():
                scores[key].append(value)
            failures += [failure] if failure else []
            done += 1
            if progress:
                progress(done, total, label)
        rows.append({"method": name, **{k: _mean(v) for k, v in scores.items()},
                     "seconds_per_patch": (time.perf_counter() - started) / count,
                     "psnr_t_per_patch": scores["psnr_t"], "psnr_r_per_patch": scores["psnr_r"],
                     "failed": len(failures), "failure": failures[0] if failures else None})
    return rows


def robustness(layers: dict[str, np.ndarray], axes: Sequence[Axis], methods: dict[str, Callable], quick: bool,
               progress: Progress | None = None) -> list[dict]:
    """T̂ and R̂ PSNR of each method under each condition of each axis, on the same patches.

    Args:
        layers: a synthetic set (``r``, ``t``, ``theta``, ``phi_perp`` stacked over patches).
        axes: the factors (`AXES`); a condition shared by several axes is run once.
        methods: name → run.
        quick: only each axis's quick levels.

    Returns:
        One row per (axis, level, method): ``axis``, ``condition`` (its label), ``method``,
        ``psnr_t``, ``psnr_r`` (means over the patches the method accepted),
        ``psnr_t_per_patch``, ``psnr_r_per_patch`` (NaN where refused), ``failed`` (patches
        refused) and ``failure`` (the first refusal's message).
    """
    count = len(layers["r"])
    unique = list(dict.fromkeys(cond for axis in axes for _, cond in axis.conditions(quick)))
    results = {c: {m: {"psnr_t": [], "psnr_r": [], "failures": []} for m in methods} for c in unique}
    done, total = 0, len(unique) * count
    for i in range(count):
        sample = {k: layers[k][i] for k in ("r", "t", "theta", "phi_perp")}
        draws = draw_nuisances(i, sample["r"].shape)
        for cond in unique:
            shots, given, _ = render_condition(sample, cond, draws)
            for name, run in methods.items():
                figures, failure = attempt(run, shots, given, (sample["r"], sample["t"]), with_ssim=False)
                cell = results[cond][name]
                cell["psnr_t"].append(figures["psnr_t"])
                cell["psnr_r"].append(figures["psnr_r"])
                cell["failures"] += [failure] if failure else []
            done += 1
            if progress:
                progress(done, total, "robustness")
    rows = []
    for axis in axes:
        for label, cond in axis.conditions(quick):
            for name in methods:
                cell = results[cond][name]
                rows.append({"axis": axis.name, "condition": label, "method": name,
                             "psnr_t": _mean(cell["psnr_t"]), "psnr_r": _mean(cell["psnr_r"]),
                             "psnr_t_per_patch": cell["psnr_t"], "psnr_r_per_patch": cell["psnr_r"],
                             "failed": len(cell["failures"]), "failure": cell["failures"][0] if cell["failures"] else None})
    return rows


def gap(rows: list[dict], a: str = "network", b: str = "direct") -> dict | None:
    """`separate.bench.paired_gain` of T̂ PSNR, ``a`` − ``b``, over the patches of one set or
    condition that both methods accepted; None unless both methods are there and share one."""
    by_name = {r["method"]: np.asarray(r["psnr_t_per_patch"], np.float64) for r in rows}
    if a not in by_name or b not in by_name:
        return None
    both = np.isfinite(by_name[a]) & np.isfinite(by_name[b])
    if not both.any():
        return None
    return {"a": a, "b": b, **paired_gain([{"method": m, "psnr_t_per_patch": by_name[m][both]} for m in (a, b)], a, b)}


# ----------------------------------------------------------------------------- speed


def speed_stack(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A (3, H, W, 3) float32 stack at 0/45/90° of two bundled photos behind glass (θ = 55°,
    φ⊥ along the first shot), exposure mean(S0) ≈ 0.2, medium noise; deterministic."""
    import skimage.data

    if height < 64 or width < 64:
        raise ValueError(f"expected at least 64 × 64 px, got {width} × {height}")
    refl, trans = (optics.photo_to_linear(cv2.resize(getattr(skimage.data, name)(), (width, height), interpolation=cv2.INTER_CUBIC))
                   for name in ("astronaut", "coffee"))
    theta = np.radians(55.0)
    rng = np.random.default_rng(seed)
    gain, read = NOISE_GAINS[Noise.MEDIUM]
    stack = np.empty((3, height, width, 3), np.float32)
    for k, angle in enumerate(np.radians(optics.PAPER_ANGLES_DEG)):
        stack[k] = optics.render(refl, trans, theta, 0.0, float(angle)) * 0.8
    exposure = 0.2 / float(stack.mean(dtype=np.float64) * 2)
    for k in range(3):
        shot = stack[k]
        shot *= exposure
        shot += rng.standard_normal(shot.shape, dtype=np.float32) * noise_std(shot, gain, read)
        np.clip(shot, 0.0, 1.0, out=shot)
    return stack


def _status_mb(field: str) -> float:
    """A memory field of /proc/self/status (VmRSS, VmHWM) in MB; NaN where not available."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak() -> bool:
    """Reset this process's peak resident memory (Linux ≥ 4.0); False where that is not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def time_method(name: str, height: int, width: int) -> dict:
    """Seconds and memory of one call of method ``name`` on `speed_stack` (run it in a fresh
    process, `run_isolated`): the peak resident memory counts from just before the call
    (input stack, loaded weights, interpreter included; 'rss_before_mb' is that baseline)."""
    stack = speed_stack(height, width)
    run, _ = make_method(name)
    exact = _reset_peak()
    before = _status_mb("VmRSS")
    started = time.perf_counter()
    run(stack, list(optics.PAPER_ANGLES_DEG))
    seconds = time.perf_counter() - started
    import resource

    peak = _status_mb("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"seconds": seconds, "peak_rss_mb": peak, "rss_before_mb": before}


def time_training(steps: int) -> dict:
    """Steps/s of `separate.train` on a tiny config (64² patches, batch 16, one thread, the
    CPU setting's shape; run it in a fresh process): steps 2 to N−1 are timed (the first warms
    up, the last validates and saves)."""
    import tempfile

    from separate.precision import resolve
    from separate.train import TrainConfig, train

    if steps < 3:
        raise ValueError(f"expected at least 3 training steps, got {steps}")
    cfg = TrainConfig(patch=64, batch=16, micro_batch=16, steps=steps, val_samples=4, val_every=10**9,
                      ckpt_every=10**9, threads=1)
    stamps: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        train(cfg, Path(tmp) / "run", progress=lambda record: stamps.append(time.perf_counter()))
    seconds = (stamps[-2] - stamps[0]) / (len(stamps) - 2)
    return {"steps_per_s": 1.0 / seconds, "patches_per_s": cfg.batch / seconds, "steps_timed": len(stamps) - 2,
            "patch": cfg.patch, "batch": cfg.batch, "threads": cfg.threads, "precision": resolve(cfg.precision).value}


def synthesis_throughput(count: int, size: int = 128) -> list[dict]:
    """Patches/s of the training-data synthesizer (full pipeline, training photos; loading the
    photos not timed), for each angle mode."""
    from separate.synthesis import default_pool

    pool = default_pool("train")
    rows = []
    for mode in AngleMode:
        synth = Synthesizer(pool, SynthesisConfig(patch=size, angles=mode), seed=0)
        started = time.perf_counter()
        synth.batch(count)
        seconds = time.perf_counter() - started
        rows.append({"mode": mode.value, "patches": count, "size": size, "patches_per_s": count / seconds,
                     "rejected": synth.rejected})
    return rows


def _isolated_entry(connection, function: Callable, args: tuple) -> None:
    try:
        connection.send(("ok", function(*args)))
    except BaseException:  # noqa: BLE001 - the parent reports whatever failed
        connection.send(("error", traceback.format_exc()))
    finally:
        connection.close()


def run_isolated(function: Callable, args: tuple, timeout_s: float = ISOLATED_TIMEOUT_S) -> dict:
    """``function(*args)`` in a fresh (spawned) process, so that its memory peak and thread
    settings are its own; TimeoutError after ``timeout_s`` (the process is terminated),
    RuntimeError with the child's traceback if it fails."""
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(target=_isolated_entry, args=(sender, function, args), daemon=True)
    process.start()
    sender.close()
    try:
        if not receiver.poll(timeout_s):
            raise TimeoutError(f"{function.__name__}{args} did not finish within {timeout_s:.0f} s")
        status, value = receiver.recv()
    except EOFError:
        raise RuntimeError(f"{function.__name__}{args} ended without a result (exit code {process.exitcode})") from None
    finally:
        if process.is_alive():
            process.join(5)
        if process.is_alive():
            process.terminate()
            process.join(5)
        receiver.close()
    if status != "ok":
        raise RuntimeError(f"{function.__name__}{args} failed:\n{value}")
    return value


# ----------------------------------------------------------------------------- environment


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else what platform reports."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def git_commit() -> str:
    """HEAD's commit, with " (working tree modified)" when tracked files differ; "unknown" without git."""
    try:
        head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    if head.returncode:
        return "unknown"
    return head.stdout.strip() + (" (working tree modified)" if dirty.stdout.strip() else "")


def _command_line() -> str:
    """This process's command as typed: ``python tools/x.py ARGS`` or ``urd ARGS``."""
    program = sys.argv[0]
    if program.endswith(".py"):
        return shlex.join(["python", os.path.relpath(program) if os.path.isabs(program) else program, *sys.argv[1:]])
    return shlex.join([Path(program).name, *sys.argv[1:]])


def environment(command: str | None = None) -> dict:
    """What a result depends on: command, commit, date, CPU, torch and its capability flags, precision."""
    import torch

    from separate.precision import describe, resolve

    caps = torch.cpu.get_capabilities() if hasattr(torch.cpu, "get_capabilities") else {}
    flags = [k for k in ("avx2", "avx512_f", "avx512_bf16", "avx512_vnni", "amx_bf16", "amx_tile") if caps.get(k)]
    precision = resolve("auto")
    return {
        "command": command or _command_line(),
        "commit": git_commit(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "flags": flags,
        "precision": precision.value,
        "precision_note": describe(precision),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
    }


# ----------------------------------------------------------------------------- settings


@dataclasses.dataclass(frozen=True)
class Settings:
    """What a run measures (quick or full; `settings_for`)."""

    quick: bool
    crossval_methods: tuple[str, ...]
    crossval_count: int
    crossval_size: int
    robust_methods: tuple[str, ...]
    robust_count: int
    robust_size: int
    speed_methods: tuple[str, ...]
    speed_shape: tuple[int, int]
    large: bool
    synthesis_count: int
    train_steps: int

    def fingerprint(self) -> dict:
        """Everything that determines the figures (not the speed measurements), for the expected file."""
        axes = {axis.name: [label for label, _ in axis.conditions(self.quick)] for axis in AXES}
        return {"crossval_methods": list(self.crossval_methods), "crossval_count": self.crossval_count,
                "crossval_size": self.crossval_size, "robust_methods": list(self.robust_methods),
                "robust_count": self.robust_count, "robust_size": self.robust_size, "seed": SEED,
                "robust_seed": ROBUST_SEED, "axes": axes}


def settings_for(quick: bool, large: bool = False) -> Settings:
    """The quick run or the full one.

    Quick: none/network/direct/schechner, 12 + 12 cross-validation patches of 256², 10
    robustness patches of 128² at two levels per axis, 1 MP timings; about 4 CPU-minutes
    (6.5-8.5 min wall on 2 shared cores). Full: every method on 64 + 64 cross-validation
    patches (the bsds500-test set is `tools/bench_synthetic.py`'s), 48 robustness patches at
    every level for the polarization methods (none/network/direct/schechner/kong/farid),
    every method timed at 1 MP, and the network and Schechner at 24 MP with ``large``; about half
    an hour on 2 cores (1804 s measured; Kong ~1.1 s per 256² patch, Schechner ~1.2 s, the rest less).
    """
    if quick and large:
        raise ValueError("expected large (24 MP) timings only in the full run, got quick=True, large=True")
    if quick:
        return Settings(True, QUICK_METHODS, 12, 256, QUICK_METHODS, 10, 128, QUICK_METHODS, (816, 1224), False, 24, 6)
    return Settings(False, ALL_METHODS, 64, 256, ("none", "network", "direct", "schechner", "kong", "farid"), 48, 128,
                    ALL_METHODS, (816, 1224), large, 96, 12)


# ----------------------------------------------------------------------------- figures and checks


#: Tolerances of the quick check by figure kind: ("abs", dB or units) or ("rel", fraction).
TOLERANCES = {"psnr": ("abs", 0.3), "gap": ("abs", 0.3), "ssim": ("abs", 0.01), "rmse": ("rel", 0.05), "failed": ("abs", 0)}


def flatten_figures(crossval: dict[str, list[dict]], robust: list[dict], robust_gaps: list[dict]) -> dict[str, float]:
    """The checkable figures by key: ``crossval/SET/METHOD/{rmse,psnr,ssim}_{t,r}``,
    ``crossval/SET/gap_t`` (network − direct), ``robustness/AXIS/LEVEL/METHOD/psnr_{t,r}``,
    ``robustness/AXIS/LEVEL/gap_t``, and ``.../METHOD/failed`` (patches refused) where a method
    refused any; figures that are not finite (every patch refused) are left out."""
    out = {}
    for name, rows in crossval.items():
        for row in rows:
            for key in SCORES:
                out[f"crossval/{name}/{row['method']}/{key}"] = row[key]
            if row.get("failed"):
                out[f"crossval/{name}/{row['method']}/failed"] = row["failed"]
        g = gap(rows)
        if g:
            out[f"crossval/{name}/gap_t"] = g["mean"]
    for row in robust:
        prefix = f"robustness/{row['axis']}/{row['condition']}/{row['method']}"
        for key in ("psnr_t", "psnr_r"):
            out[f"{prefix}/{key}"] = row[key]
        if row.get("failed"):
            out[f"{prefix}/failed"] = row["failed"]
    for g in robust_gaps:
        out[f"robustness/{g['axis']}/{g['condition']}/gap_t"] = g["mean"]
    return {k: float(v) for k, v in out.items() if math.isfinite(v)}


def tolerance_for(key: str, tolerances: dict = TOLERANCES) -> tuple[str, float]:
    """The (kind, value) tolerance of a figure key, by the kind its last part names."""
    last = key.rsplit("/", 1)[-1]
    for kind, tol in tolerances.items():
        if last.startswith(kind):
            return tol
    raise ValueError(f"expected a figure key ending in one of {sorted(tolerances)}_*, got {key!r}")


def check_figures(measured: dict[str, float], expected: dict[str, float], tolerances: dict = TOLERANCES,
                  absent_prefixes: Sequence[str] = ()) -> list[str]:
    """One line per expected figure that is out of tolerance or not measured (unless its key
    starts with one of ``absent_prefixes``: sets whose photos are not on this machine), and
    per refusal count (``.../failed``) that is not expected; empty when every figure agrees.
    A missing refusal count is 0; other figures measured but not expected are not checked."""
    problems = []
    for key, want in sorted(expected.items()):
        got = measured.get(key, 0.0 if key.endswith("/failed") else None)
        if got is None:
            if not any(key.startswith(p) for p in absent_prefixes):
                problems.append(f"{key}: expected {want:.4g}, not measured")
            continue
        kind, tol = tolerance_for(key, tolerances)
        allowed = tol if kind == "abs" else tol * abs(want)
        if not (abs(got - want) <= allowed):
            problems.append(f"{key}: measured {got:.4g}, expected {want:.4g} ± {allowed:.3g}"
                            + (f" ({tol:.0%})" if kind == "rel" else ""))
    for key, got in sorted(measured.items()):
        if key.endswith("/failed") and key not in expected:
            problems.append(f"{key}: the method refused {got:.0f} patch(es), expected none")
    return problems


def expected_document(figures: dict[str, float], settings: Settings, env: dict, weights: dict,
                      robust_source: str = "bsds500-test") -> dict:
    """The contents of ``expected-quick.json`` for a quick run's figures (values to 6
    significant digits), with the photo set its robustness patches came from."""
    return {"schema": EXPECTED_SCHEMA, "version": 1, "made_by": UPDATE_COMMAND, "robust_source": robust_source,
            "made": {"commit": env["commit"], "date": env["date"], "cpu": env["cpu"], "precision": env["precision"]},
            "weights": weights, "settings": settings.fingerprint(),
            "tolerances": {k: list(v) for k, v in TOLERANCES.items()},
            "figures": {k: float(f"{v:.6g}") for k, v in figures.items()}}


def verify_expected(figures: dict[str, float], document: dict, settings: Settings, weights: dict,
                    absent_prefixes: Sequence[str] = (), source: str = "expected-quick.json",
                    robust_source: str = "bsds500-test") -> list[str]:
    """Check a quick run against an expected document; returns notes (the weights differ, or
    the robustness figures were not checked because their patches came from another photo
    set than the document's) when every checked figure agrees; raises `BenchmarkMismatch`
    naming every figure out of tolerance (and the weights that changed), or when the quick
    settings changed."""
    if document.get("schema") != EXPECTED_SCHEMA:
        raise BenchmarkMismatch(f"{source}: expected schema {EXPECTED_SCHEMA!r}, got {document.get('schema')!r}")
    if document.get("settings") != settings.fingerprint():
        raise BenchmarkMismatch(f"{source} was made with other quick settings than this urd's; regenerate it: {UPDATE_COMMAND}")
    tolerances = {k: tuple(v) for k, v in document.get("tolerances", {}).items()} or TOLERANCES
    notes = []
    if document.get("weights") != weights:
        notes.append(f"the weights differ from those {source} was made with ({_weights_line(document.get('weights', {}))})")
    made = document.get("made", {})
    if document.get("robust_source", robust_source) != robust_source:
        notes.append(f"robustness figures not checked: {source} has them on {document['robust_source']} patches, "
                     f"this run on {robust_source} patches (its photos are not on this machine)")
        figures = {k: v for k, v in figures.items() if not k.startswith("robustness/")}
        absent_prefixes = [*absent_prefixes, "robustness/"]
    problems = check_figures(figures, document["figures"], tolerances, absent_prefixes)
    if problems:
        hint = [f"made at commit {made.get('commit', '?')} on {made.get('cpu', '?')}, precision {made.get('precision', '?')}"]
        raise BenchmarkMismatch(f"{len(problems)} figure(s) of the quick evaluation differ from {source}:\n  "
                                + "\n  ".join(problems + notes + hint)
                                + f"\nIf the change is intended (new weights, new methods), regenerate: {UPDATE_COMMAND}")
    return notes


def _weights_line(weights: dict) -> str:
    return ", ".join(f"{name} {info.get('file', '?')} sha256 {info.get('sha256', '?')[:12]}" for name, info in weights.items())


# ----------------------------------------------------------------------------- plots


#: Colours (BGR) of the series, matplotlib's "tab10".
PALETTE = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23))
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def nice_ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    """Round tick values (steps 1, 2, 2.5 or 5 × 10^k) from at or below ``lo`` to at or above
    ``hi``, about ``count`` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"expected finite limits, got {lo}, {hi}")
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / max(count - 1, 1)
    magnitude = 10 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw * (1 - 1e-9))
    start, stop = math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9)
    return [round(k * step, 10) for k in range(start, stop + 1)]


def _text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.45, align: str = "left",
          colour: tuple[int, int, int] = (0, 0, 0)) -> None:
    (w, h), _ = cv2.getTextSize(text, _FONT, scale, 1)
    x = x - w // 2 if align == "center" else x - w if align == "right" else x
    cv2.putText(canvas, text, (int(x), int(y + h // 2)), _FONT, scale, colour, 1, cv2.LINE_AA)


def _tick_label(value: float, step: float) -> str:
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step < 1 else 0
    decimals += 1 if step * 10 ** decimals % 1 else 0
    return f"{value:.{decimals}f}"


def _frame(size: tuple[int, int], title: str, x_labels: Sequence[str], x_title: str, y_title: str,
           ticks: list[float], series: Sequence[str]) -> tuple[np.ndarray, Callable[[float], int], Callable[[float], float], tuple]:
    """A white canvas with title, grid, axes, categorical x labels, y ticks and a legend; returns
    (canvas, y → row, slot index → column centre, plot box (x0, y0, x1, y1))."""
    width, height = size
    canvas = np.full((height, width, 3), 255, np.uint8)
    legend_w = 20 + max([cv2.getTextSize(s, _FONT, 0.45, 1)[0][0] for s in series] + [0]) + 30 if series else 0
    x0, y0, x1, y1 = 78, 46, width - 16 - legend_w, height - 62
    if x1 - x0 < 100 or y1 - y0 < 100:
        raise ValueError(f"expected a plot of at least {x0 + 116 + legend_w} × {y0 + 162} px, got {width} × {height}")
    lo, hi = ticks[0], ticks[-1]

    def row(y: float) -> int:
        return int(round(y1 - (y - lo) / (hi - lo) * (y1 - y0)))

    slot = (x1 - x0) / max(len(x_labels), 1)

    def column(i: float) -> float:
        return x0 + (i + 0.5) * slot

    step = ticks[1] - ticks[0] if len(ticks) > 1 else 1.0
    for value in ticks:
        cv2.line(canvas, (x0, row(value)), (x1, row(value)), (225, 225, 225), 1)
        cv2.line(canvas, (x0 - 5, row(value)), (x0, row(value)), (0, 0, 0), 1)
        _text(canvas, _tick_label(value, step), x0 - 8, row(value), align="right")
    for i, label in enumerate(x_labels):
        cx = int(round(column(i)))
        cv2.line(canvas, (cx, y1), (cx, y1 + 5), (0, 0, 0), 1)
        _text(canvas, label, cx, y1 + 16, scale=0.42 if len(x_labels) < 10 else 0.36, align="center")
    cv2.rectangle(canvas, (x0, y0), (x1, y1), (0, 0, 0), 1)
    _text(canvas, title, (x0 + x1) // 2, 22, scale=0.55, align="center")
    _text(canvas, x_title, (x0 + x1) // 2, height - 18, align="center")
    (tw, th), _ = cv2.getTextSize(y_title, _FONT, 0.45, 1)
    label = np.full((th + 10, tw + 4, 3), 255, np.uint8)
    _text(label, y_title, 2, (th + 10) // 2)
    label = cv2.rotate(label, cv2.ROTATE_90_COUNTERCLOCKWISE)
    top = max(0, (y0 + y1) // 2 - label.shape[0] // 2)
    label = label[: height - top]
    canvas[top : top + label.shape[0], 8 : 8 + label.shape[1]] = np.minimum(canvas[top : top + label.shape[0], 8 : 8 + label.shape[1]], label)
    lx = x1 + 16
    for i, name in enumerate(series):
        ly = y0 + 10 + 20 * i
        cv2.line(canvas, (lx, ly), (lx + 22, ly), PALETTE[i % len(PALETTE)], 3, cv2.LINE_AA)
        _text(canvas, name, lx + 30, ly)
    return canvas, row, column, (x0, y0, x1, y1)


def _limits(values: list[float], floor: float | None = None) -> list[float]:
    finite = [v for v in values if math.isfinite(v)] or [0.0, 1.0]
    lo, hi = min(finite), max(finite)
    pad = 0.05 * (hi - lo) if hi > lo else 0.5
    return nice_ticks(lo - pad if floor is None else min(floor, lo - pad), hi + pad)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an 8-bit BGR image as PNG, atomically."""
    path = Path(path)
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"cannot encode a PNG of shape {image.shape} for {path}")
    with atomic_path(path, overwrite=True) as tmp:
        tmp.write_bytes(data.tobytes())


def plot_lines(path: Path | None, x_labels: Sequence[str], series: dict[str, Sequence[float]], title: str, x_title: str,
               y_title: str, intervals: dict[str, Sequence[tuple[float, float]]] | None = None,
               size: tuple[int, int] = (900, 540), zero_line: bool = False, connect: bool = True) -> np.ndarray:
    """A line plot over categorical x (one marker per level, NaN leaves a gap; ``connect``
    False: markers only), with optional error bars (``intervals``: name → (lo, hi) per level)
    and a line at 0 (``zero_line``), written as PNG to ``path`` unless None.

    Returns the (size[1], size[0], 3) uint8 BGR image. Labels must be ASCII (OpenCV's font).
    """
    for name, values in series.items():
        if len(values) != len(x_labels):
            raise ValueError(f"expected {len(x_labels)} values for series {name!r}, got {len(values)}")
    values = [v for vs in series.values() for v in vs] + [v for iv in (intervals or {}).values() for pair in iv for v in pair]
    ticks = _limits(values + ([0.0] if zero_line else []))
    canvas, row, column, (x0, _, x1, _) = _frame(size, title, x_labels, x_title, y_title, ticks, list(series))
    if zero_line:
        cv2.line(canvas, (x0, row(0.0)), (x1, row(0.0)), (90, 90, 90), 1, cv2.LINE_AA)
    count = max(len(series), 1)
    for k, (name, ys) in enumerate(series.items()):
        colour = PALETTE[k % len(PALETTE)]
        nudge = (k - (count - 1) / 2) * 3 if intervals else 0
        points = [(int(round(column(i) + nudge)), row(y)) if math.isfinite(y) else None for i, y in enumerate(ys)]
        for a, b in zip(points, points[1:]):
            if connect and a and b:
                cv2.line(canvas, a, b, colour, 2, cv2.LINE_AA)
        for i, p in enumerate(points):
            if p is None:
                continue
            if intervals and name in intervals:
                lo, hi = intervals[name][i]
                if math.isfinite(lo) and math.isfinite(hi):
                    cv2.line(canvas, (p[0], row(lo)), (p[0], row(hi)), colour, 1, cv2.LINE_AA)
                    for v in (lo, hi):
                        cv2.line(canvas, (p[0] - 4, row(v)), (p[0] + 4, row(v)), colour, 1, cv2.LINE_AA)
            cv2.circle(canvas, p, 4, colour, -1, cv2.LINE_AA)
    if path is not None:
        write_png(path, canvas)
    return canvas


def plot_bars(path: Path | None, groups: Sequence[str], series: dict[str, Sequence[float]], title: str, y_title: str,
              x_title: str = "", size: tuple[int, int] = (900, 540)) -> np.ndarray:
    """Grouped bars (a group per x label, a bar per series; NaN: no bar) from the lowest tick
    up, written as PNG to ``path`` unless None; returns the image as `plot_lines` does."""
    for name, values in series.items():
        if len(values) != len(groups):
            raise ValueError(f"expected {len(groups)} values for series {name!r}, got {len(values)}")
    values = [v for vs in series.values() for v in vs]
    ticks = _limits(values)
    canvas, row, column, (x0, _, x1, _) = _frame(size, title, groups, x_title, y_title, ticks, list(series))
    slot = (x1 - x0) / max(len(groups), 1)
    bar = 0.8 * slot / max(len(series), 1)
    for k, (_, ys) in enumerate(series.items()):
        for i, y in enumerate(ys):
            if not math.isfinite(y):
                continue
            left = column(i) - 0.4 * slot + k * bar
            cv2.rectangle(canvas, (int(round(left)), row(y)), (int(round(left + bar)) - 1, row(ticks[0]) - 1),
                          PALETTE[k % len(PALETTE)], -1)
    if path is not None:
        write_png(path, canvas)
    return canvas


# ----------------------------------------------------------------------------- writing


def write_text(path: Path, text: str) -> None:
    """Write a text file atomically."""
    with atomic_path(Path(path), overwrite=True) as tmp:
        tmp.write_text(text)


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence]) -> None:
    """Write a CSV file (floats with 6 significant digits) atomically."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in row])
    write_text(path, buffer.getvalue())


def _robust_cell(row: dict | None) -> str:
    if row is None:
        return "–"
    cell = f"{row['psnr_t']:.2f} / {row['psnr_r']:.2f}"
    return cell + (f" ({row['failed']} of {len(row['psnr_t_per_patch'])} refused)" if row["failed"] else "")


def _gap_cell(g: dict | None) -> str:
    if g is None:
        return "–"
    return f"{g['mean']:+.2f} ({g['ci95'][0]:+.2f} to {g['ci95'][1]:+.2f}), {g['wins']}/{g['count']}"


def format_report(result: dict) -> str:
    """The Markdown report (``tables.md``) of a `run_evaluation` result."""
    env, settings = result["environment"], result["settings"]
    mode = "quick" if settings.quick else "full"
    lines = [f"# urd evaluation ({mode})", "",
             f"* command: `{env['command']}`",
             f"* commit: {env['commit']}",
             f"* date: {env['date']}",
             f"* CPU: {env['cpu']}, {env['cores']} cores; torch {env['torch']}, {env['torch_threads']} threads; "
             f"capability flags: {' '.join(env['flags']) or 'none reported'}",
             f"* precision (auto): {env['precision_note']}",
             f"* weights: {_weights_line(result['weights'])}",
             "* runtime: " + ", ".join(f"{k} {v:.0f} s" for k, v in result["seconds"].items()),
             "", "Linear values, peak 1, PSNR floored at 60 dB per patch; means over patches. Every method picks its "
             "reference itself (\"auto\"). Gaps are paired per patch: mean, 95% bootstrap interval, patches where the "
             "first method scores higher.", ""]
    lines += ["## 1. Cross-validation on held-out synthetic sets (paper Table 1)", "",
              f"{settings.crossval_count} patches of {settings.crossval_size}² per set (seed {SEED}), the full synthesis "
              "pipeline (DR + NRD + LCG, the paper's angles with ±4° errors, sensor noise); the methods get the nominal "
              "angles 0/45/90. No shipped model saw these photos (training: bsds500/train + sunhays80; validation: "
              "bsds500/val).", ""]
    for name, description, rows in result["crossval_sets"]:
        lines += [f"### {name}: {description}", ""]
        if rows is None:
            lines += ["Not measured: the photos are not on this machine.", ""]
            continue
        lines += [format_table(rows), ""]
        lines += [f"* {r['method']} refused {r['failed']} of {len(r['psnr_t_per_patch'])} patches (left out of its means): "
                  f"{r['failure']}" for r in rows if r["failed"]]
        for g in result["crossval_gaps"].get(name, []):
            lines.append(f"* T PSNR {g['a']} − {g['b']}: {_gap_cell(g)} patches")
        lines.append("")
    lines += ["## 2. Robustness", "",
              f"{settings.robust_count} patches of {settings.robust_size}² ({result['robust_source']}, seed {SEED + 1}): "
              "the synthesizer's layers rendered again with `separate.optics`, one factor varied at a time from the "
              "base condition (exact angles 0/45/90, no misalignment, medium noise, φ⊥ − φ0 ~ U[−45°, 45°] per patch, "
              "no non-rigid deformation); every condition of a patch shares its random draws. Cells: T̂ / R̂ PSNR (dB).", ""]
    methods = list(settings.robust_methods)
    for axis in AXES:
        levels = axis.conditions(settings.quick)
        refusals: dict[str, str] = {}
        lines += [f"### {axis.title}", "",
                  "| " + axis.x_title + " | " + " | ".join(methods) + " | T network − direct (interval), wins |",
                  "|---|" + "---|" * (len(methods) + 1)]
        for label, _ in levels:
            cells = []
            for m in methods:
                row = result["robust_index"].get((axis.name, label, m))
                if row and row["failed"]:
                    refusals.setdefault(m, row["failure"])
                cells.append(_robust_cell(row))
            lines.append(f"| {label} | " + " | ".join(cells) + f" | {_gap_cell(result['robust_gap_index'].get((axis.name, label)))} |")
        lines += [""] + [f"* {m} refused some patches (means over the rest; gaps over patches both accepted): {msg}"
                         for m, msg in refusals.items()] + ([""] if refusals else [])
    lines += ["## 3. Speed and memory", "",
              f"One call per method on a {settings.speed_shape[1]}×{settings.speed_shape[0]} scene (three shots), each "
              "in a fresh process, first call (setup included); peak resident memory from just before the call (input "
              "stack, weights and interpreter included; the baseline in brackets). Other load on the machine slows them.", "",
              "| method | size | seconds | peak RSS (MB) |", "|---|---|---|---|"]
    for row in result["speed"]:
        size = f"{row['width']}×{row['height']}"
        if "error" in row:
            lines.append(f"| {row['method']} | {size} | failed: {row['error']} | |")
        else:
            lines.append(f"| {row['method']} | {size} | {row['seconds']:.2f} | {row['peak_rss_mb']:.0f} ({row['rss_before_mb']:.0f}) |")
    lines += ["", "| throughput | figure |", "|---|---|"]
    for row in result["synthesis"]:
        lines.append(f"| synthesis, {row['size']}² patches, full pipeline, angles {row['mode']} | "
                     f"{row['patches_per_s']:.1f} patches/s ({row['rejected']} rejected draws) |")
    t = result["training"]
    if "error" in t:
        lines.append(f"| training | failed: {t['error']} |")
    else:
        lines.append(f"| training, {t['patch']}² × {t['batch']} patches, {t['threads']} thread, {t['precision']} "
                     f"({t['steps_timed']} steps timed) | {t['steps_per_s']:.2f} steps/s ({t['patches_per_s']:.1f} patches/s) |")
    lines += ["", "## Check", "", result["check"]["line"], ""]
    lines += ["## Files", "", ", ".join(f"`{f}`" for f in result["files"]), ""]
    return "\n".join(lines)


def _write_outputs(result: dict, folder: Path) -> list[str]:
    settings = result["settings"]
    files = []

    def name(file: str) -> Path:
        files.append(file)
        return folder / file

    crossval_rows, patch_rows, gap_rows = [], [], []
    for set_name, _, rows in result["crossval_sets"]:
        for row in rows or []:
            crossval_rows.append([set_name, row["method"], settings.crossval_count, settings.crossval_size, row["failed"],
                                  *(row[k] for k in ("rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r", "ssim_r", "seconds_per_patch"))])
            patch_rows += [[set_name, row["method"], i, t, r] for i, (t, r) in enumerate(zip(row["psnr_t_per_patch"], row["psnr_r_per_patch"]))]
        for g in result["crossval_gaps"].get(set_name, []):
            gap_rows.append([set_name, g["a"], g["b"], g["mean"], g["ci95"][0], g["ci95"][1], g["wins"], g["count"]])
    write_csv(name("crossval.csv"), ["set", "method", "patches", "size", "refused", "rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r",
                                     "ssim_r", "seconds_per_patch"], crossval_rows)
    write_csv(name("crossval_patches.csv"), ["set", "method", "patch", "psnr_t", "psnr_r"], patch_rows)
    write_csv(name("crossval_gaps.csv"), ["set", "a", "b", "mean_db", "ci95_lo", "ci95_hi", "wins", "patches"], gap_rows)
    write_csv(name("robustness.csv"), ["axis", "condition", "method", "patches", "refused", "psnr_t", "psnr_r"],
              [[r["axis"], r["condition"], r["method"], len(r["psnr_t_per_patch"]), r["failed"], r["psnr_t"], r["psnr_r"]]
               for r in result["robustness"]])
    write_csv(name("robustness_gaps.csv"), ["axis", "condition", "a", "b", "mean_db", "ci95_lo", "ci95_hi", "wins", "patches"],
              [[g["axis"], g["condition"], g["a"], g["b"], g["mean"], g["ci95"][0], g["ci95"][1], g["wins"], g["count"]]
               for g in result["robust_gaps"]])
    write_csv(name("speed.csv"), ["method", "width", "height", "seconds", "peak_rss_mb", "rss_before_mb"],
              [[r["method"], r["width"], r["height"], r.get("seconds", float("nan")), r.get("peak_rss_mb", float("nan")),
                r.get("rss_before_mb", float("nan"))] for r in result["speed"]])
    t = result["training"]
    write_csv(name("throughput.csv"), ["what", "figure", "unit"],
              [[f"synthesis {r['mode']} {r['size']}px", r["patches_per_s"], "patches/s"] for r in result["synthesis"]]
              + ([["training 64px x16", t["steps_per_s"], "steps/s"]] if "steps_per_s" in t else []))

    measured = [(n, d, rows) for n, d, rows in result["crossval_sets"] if rows]
    if measured:
        methods = [r["method"] for r in measured[0][2]]
        for layer, title in (("t", "T"), ("r", "R")):
            by_set = {n: {r["method"]: r[f"psnr_{layer}"] for r in rows} for n, _, rows in measured}
            plot_bars(name(f"crossval_psnr_{layer}.png"), methods,
                      {n: [by_set[n].get(m, float("nan")) for m in methods] for n in by_set},
                      f"Cross-validation: {title} PSNR per method and held-out set", f"{title} PSNR (dB)", "method")
    for axis in AXES:
        labels = [label for label, _ in axis.conditions(settings.quick)]
        series = {m: [result["robust_index"][(axis.name, lb, m)]["psnr_t"] for lb in labels] for m in settings.robust_methods}
        plot_lines(name(f"robustness_{axis.name}.png"), labels, series, f"Robustness ({axis.name}): T PSNR",
                   axis.x_title, "T PSNR (dB)")
    gaps = result["robust_gaps"]
    if gaps:
        letters = {axis.name: axis.letter for axis in AXES}
        labels = [f"{letters[g['axis']]}: {g['condition']}" for g in gaps]
        plot_lines(name("robustness_gap.png"), labels, {"network - direct": [g["mean"] for g in gaps]},
                   "T PSNR network - direct per condition, 95% bootstrap interval", "axis (a-f, see tables.md): condition",
                   "gap (dB)",
                   intervals={"network - direct": [g["ci95"] for g in gaps]}, size=(max(900, 75 * len(gaps) + 300), 540),
                   zero_line=True, connect=False)
    files.append("tables.md")
    return files


# ----------------------------------------------------------------------------- driver


def run_evaluation(out_dir: Path, quick: bool, images_dir: Path | None = None, progress: Progress | None = None, *,
                   large: bool = False, update_expected: bool = False, expected_path: Path = EXPECTED_QUICK,
                   command: str | None = None) -> dict:
    """Run the evaluation and write ``tables.md``, CSV files and PNG plots into
    ``out_dir/quick`` or ``out_dir/full``.

    Args:
        out_dir: the output folder (`DEFAULT_OUT`: docs/bench); created when missing.
        quick: the quick run (`settings_for`), checked against ``expected_path``.
        images_dir: a folder of photos (JPEG, PNG, TIFF, 8 or 16 bit) to cross-validate on as
            well; its figures are reported, never checked.
        progress: called with (done, total, label) per patch, label naming the part.
        large: the full run also times `LARGE_METHODS` at 24 MP (6000×4000).
        update_expected: (quick only) write the figures as the new expected values instead of
            checking them.
        expected_path: the expected values of the quick run.
        command: the command line printed in the report (default: this process's).

    Returns:
        A dict: ``environment``, ``settings``, ``figures`` (flat, `flatten_figures`),
        ``crossval_sets`` [(name, description, rows or None)], ``crossval_gaps``,
        ``robustness`` rows, ``robust_gaps``, ``speed``, ``synthesis``, ``training``,
        ``seconds`` per part, ``check`` ({"status", "line", "notes"}), ``files``, ``folder``.

    Raises:
        BenchmarkMismatch: (quick) a figure is out of tolerance or the expected file is
            missing or stale; the outputs are written first.
    """
    if update_expected and not quick:
        raise ValueError("expected update_expected only with quick=True (the expected values are the quick run's)")
    if images_dir is not None and not Path(images_dir).is_dir():
        raise ValueError(f"expected a folder of photos for images_dir, got {images_dir}")
    settings = settings_for(quick, large)
    folder = Path(out_dir) / ("quick" if quick else "full")
    folder.mkdir(parents=True, exist_ok=True)
    env = environment(command)
    seconds: dict[str, float] = {}
    started = time.perf_counter()

    names = list(dict.fromkeys(settings.crossval_methods + settings.robust_methods))
    loaded = {name: make_method(name) for name in names}
    weights = {name: {"file": info["weights"]["file"], "sha256": info["weights"]["sha256"]}
               for name, (_, info) in loaded.items() if name in ("network", "direct")}
    runs = {name: run for name, (run, _) in loaded.items()}

    crossval_sets, crossval_gaps = [], {}
    robust_pool, robust_source = None, ""
    for name, description, pool in photo_pools(images_dir):
        if pool is None:
            crossval_sets.append((name, description, None))
            continue
        if robust_pool is None and name in ("bsds500-test", "skimage-bundled"):
            robust_pool, robust_source = pool, name
        data = synthetic_set(pool, settings.crossval_count, settings.crossval_size)
        rows = cross_validate(data, {m: runs[m] for m in settings.crossval_methods}, progress=progress,
                              label=f"cross-validation {name}")
        crossval_sets.append((name, description, rows))
        baselines = [r for r in rows if r["method"] not in ("none", "network", "direct")]
        pairs = [gap(rows, "network", "direct")]
        if baselines:
            pairs.append(gap(rows, "network", max(baselines, key=lambda r: r["psnr_t"])["method"]))
        crossval_gaps[name] = [g for g in pairs if g]
    seconds["cross-validation"] = time.perf_counter() - started

    mark = time.perf_counter()
    layers = synthetic_set(robust_pool, settings.robust_count, settings.robust_size, seed=ROBUST_SEED)
    robust = robustness(layers, AXES, {m: runs[m] for m in settings.robust_methods}, quick, progress)
    robust_index = {(r["axis"], r["condition"], r["method"]): r for r in robust}
    robust_gaps = []
    for axis in AXES:
        for label, _ in axis.conditions(quick):
            g = gap([r for r in robust if r["axis"] == axis.name and r["condition"] == label])
            if g:
                robust_gaps.append({"axis": axis.name, "condition": label, **g})
    seconds["robustness"] = time.perf_counter() - mark

    mark = time.perf_counter()
    del runs, loaded
    jobs = [(m, *settings.speed_shape) for m in settings.speed_methods]
    if settings.large:
        jobs += [(m, 4000, 6000) for m in LARGE_METHODS]
    speed = []
    for k, (method, height, width) in enumerate(jobs):
        row = {"method": method, "height": height, "width": width}
        try:
            row.update(run_isolated(time_method, (method, height, width)))
        except (RuntimeError, TimeoutError) as exc:
            row["error"] = str(exc).splitlines()[-1]
        speed.append(row)
        if progress:
            progress(k + 1, len(jobs) + 2, "speed")
    synthesis = synthesis_throughput(settings.synthesis_count)
    if progress:
        progress(len(jobs) + 1, len(jobs) + 2, "speed")
    try:
        training = run_isolated(time_training, (settings.train_steps,))
    except (RuntimeError, TimeoutError) as exc:
        training = {"error": str(exc).splitlines()[-1]}
    if progress:
        progress(len(jobs) + 2, len(jobs) + 2, "speed")
    seconds["speed"] = time.perf_counter() - mark
    seconds["total"] = time.perf_counter() - started

    figures = flatten_figures({n: rows for n, _, rows in crossval_sets if rows and not n.startswith("images-")},
                              robust, robust_gaps)
    result = {"environment": env, "settings": settings, "weights": weights, "figures": figures,
              "crossval_sets": crossval_sets, "crossval_gaps": crossval_gaps, "robustness": robust,
              "robust_index": robust_index, "robust_gaps": robust_gaps, "robust_gap_index": {(g["axis"], g["condition"]): g for g in robust_gaps},
              "robust_source": robust_source, "speed": speed, "synthesis": synthesis, "training": training,
              "seconds": seconds, "folder": folder}

    failure = None
    if not quick:
        result["check"] = {"status": "not checked", "line": "Full run: not checked against expected values.", "notes": []}
    elif update_expected:
        write_text(Path(expected_path), json.dumps(expected_document(figures, settings, env, weights, robust_source), indent=1, sort_keys=True) + "\n")
        result["check"] = {"status": "updated", "line": f"Expected values written to `{_display(expected_path)}` ({len(figures)} figures).",
                           "notes": []}
    else:
        absent = [f"crossval/{n}/" for n, _, rows in crossval_sets if rows is None]
        try:
            if not Path(expected_path).is_file():
                raise BenchmarkMismatch(f"no expected values at {expected_path}; make them with: {UPDATE_COMMAND}")
            notes = verify_expected(figures, json.loads(Path(expected_path).read_text()), settings, weights, absent,
                                    source=_display(expected_path), robust_source=robust_source)
            line = f"All figures agree with `{_display(expected_path)}` within the tolerances ({_tolerance_text()})."
            result["check"] = {"status": "passed", "line": " ".join([line] + notes), "notes": notes}
        except BenchmarkMismatch as exc:
            failure = exc
            result["check"] = {"status": "failed", "line": "FAILED:\n\n```\n" + str(exc) + "\n```", "notes": []}
    result["files"] = _write_outputs(result, folder)
    write_text(folder / "tables.md", format_report(result))
    if failure is not None:
        raise failure
    return result


def _tolerance_text() -> str:
    return ", ".join(f"{kind} ±{value:g}" + (" relative" if how == "rel" else "") for kind, (how, value) in TOLERANCES.items())


def _display(path: Path) -> str:
    path = Path(path).resolve()
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)
