"""Training data synthesis (paper §3.3): polarization triplets with known layers.

From two natural photos, in linear light (inverse gamma 2.2):

1. dynamic-range manipulation: reflection ×β, transmission ÷β with β ~ U[1, K];
2. abrupt reflections (random subset): the reflection zeroed below mean(R̃ + T̃);
3. non-rigid deformation, NRD (random subset): a coarse grid of anchors moved by Gaussian
   offsets with a per-patch σ, interpolated to a smooth warp, drawn anew for each shot;
4. surface geometry: uniform angle of incidence (LCG off), or (LCG on) a flat or parabolic
   pane seen from a camera at a finite distance, the angle of incidence in closed form;
5. polarizer angles with ±4° error per shot, rendered with the optics core:
   ``AngleMode.CLASSIC`` (the paper's, and the benchmark's): φ0 + i·45°, i = 0, 1, 2, with φ⊥
   within ±45° of φ0, the three shots as rendered;
   ``AngleMode.ANY``: an angle set drawn from `ANGLE_SETS_DEG` at φ0 ~ U[0°, 180°), and the
   network's input made exactly as at inference: φ⊥ estimated from the noisy shots with the
   nominal angles (`separate.reference.estimate_reference_deg`) and the shots re-rendered at
   it + 0/45/90° from their Stokes fit (`separate.presentation.present`), clipped below at 0 as
   `separate.infer` does;
   ``AngleMode.ANY_TRUE_SIDE``: as ANY, but an estimate on the wrong side of φ⊥ (more than 45°
   away) is turned by 90°, so the network is taught only the canonical mapping and deciding
   the side is left to the reference estimator (ANY teaches it to hedge against a wrong side);
6. exposure, shot and read noise, and rejection of flat, dark or saturated patches.

Further switches, off by default (the paper's pipeline and the benchmark's data stay as
they were), on in training the physics-anchored network's gate (``configs/cpu-gate.toml``):

* ``phi_field_prob``: φ⊥ turning linearly across the patch by up to ``phi_field_max_deg`` (a
  wide view through a flat pane, or a curved one);
* ``no_glass_prob``: no glass at all: the photo seen directly, with a polarization of its own
  (a smooth DoLP up to ``no_glass_dolp_max`` at a smoothly varying angle: sheen, varnish,
  glossy surfaces); the target is R = 0, T = S0;
* ``t_polarized_prob``: the transmitted photo given a polarization of its own, as real scenes
  have (`own_polarization`: sky-like smooth strong polarization, glossy highlights, diffuse
  polarization across object contours, up to ``t_dolp_max``), rendered through the pane's
  Fresnel transmission (`separate.optics.pane_stokes`); the target T is the S0 of what the
  pane transmits;
* ``real_prob``: the transmitted layer (or, without glass, the whole view) a crop of a real
  capture without glass from the training side of the split (`urd.core.samples.no_glass_captures`,
  its Stokes fit; scaled, flipped and turned with its polarization turned alike), where
  ../shared/data is present (else the photo);
* ``mono_prob``: both layers grey (a mono polarization camera; a mono capture's crop from
  ``real_prob`` makes its sample grey too); ``defocus_prob``: the reflection
  out of focus (a Gaussian blur of σ 1–4 px per 128 px);
* ``mosaic_prob`` (ANY modes): the shots taken by a polarization-mosaic sensor, as most
  polarization cameras take them (`through_mosaic`): the sample drawn at twice the patch size
  with the sensor's four angles 0/45/90/135° (from a random first angle, which is the same as a
  random φ⊥), noise per sensor pixel, one angle per pixel (IMX250MZR for a grey sample, the
  colour IMX250MYR otherwise), demosaiced at half size as `urd ingest` does (Newton: each 2×2
  cell's mean), its layers and θ averaged over the same cells;
* ``strength``: (lo, hi) > 0: the reflection scaled so that the observed layers' mean ratio
  R_obs/T_obs is log-uniform in [lo, hi] (as `separate.semireal` draws it), instead of what the
  photos, DR and the pane's reflectance give (a median near 0.2, a quarter of samples above 0.5,
  up to about 5);
* ``reference_field``: the ANY modes present the shots at the estimated per-pixel reference
  field (`separate.reference.estimate_reference_field`, turned to φ⊥'s side in
  ANY_TRUE_SIDE), as `urd separate` does, instead of at one global reference; ``angles`` are
  then 0/45/90° in each pixel's own frame;
* ``incidence_estimate``: each sample carries ``theta_est``, a P×P angle-of-incidence map as
  an estimator reads it (`perturbed_incidence`), the physics-anchored network's input. It is
  drawn around the truth rather than estimated from the patch: `urd separate` estimates θ on
  the whole frame (`separate.incidence.estimate_incidence_field`), where it is far better
  determined than on a 128² patch, and an estimate per patch would cost 100× the synthesis.

Every step has a switch in `SynthesisConfig`; a generator seeded with the same seed yields
the same patches.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from separate import optics
from separate.optics import parabola_aoi, photo_to_linear
from separate.reference import INCIDENCE_RANGE_DEG, inspect_stack
from separate.presentation import field_at, present, present_field
from urd.core import samples
from urd.core.mosaic import ANGLES_DEG as MOSAIC_ANGLES_DEG, Demosaic, MosaicLayout, build_mosaic, cell_means, demosaic

SHARED_NATURAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "natural"
#: scikit-image photos that ship with the package (no download): the fallback image pool.
BUNDLED_PHOTOS = ("astronaut", "chelsea", "coffee", "rocket", "camera", "coins", "moon", "page", "text", "brick", "grass", "gravel")


#: Angle sets (deg from the first shot) that ``AngleMode.ANY`` draws from, equally often:
#: the rotating polarizer's three and four angles, 60° steps, and six angles (30° steps).
ANGLE_SETS_DEG = ((0.0, 45.0, 90.0), (0.0, 60.0, 120.0), (0.0, 45.0, 90.0, 135.0),
                  (0.0, 30.0, 60.0, 90.0, 120.0, 150.0))
#: log10 ranges of the sensor noise levels drawn per sample: shot gain and read variance
#: (linear units, white = 1).
SHOT_GAIN_LOG10 = (-4.0, -2.5)
READ_VAR_LOG10 = (-7.0, -5.0)


def draw_noise_levels(rng: np.random.Generator, shot_gain_log10: tuple[float, float] = SHOT_GAIN_LOG10,
                      read_var_log10: tuple[float, float] = READ_VAR_LOG10) -> tuple[float, float]:
    """A sample's sensor noise levels (shot gain, read variance), log-uniform in the given log10
    ranges (default: the module's)."""
    return 10 ** rng.uniform(*shot_gain_log10), 10 ** rng.uniform(*read_var_log10)


def noise_std(x: np.ndarray, shot_gain: float, read_var: float) -> np.ndarray:
    """Standard deviation of the sensor noise at linear values ``x`` (Poisson–Gaussian model:
    variance shot_gain·x + read_var; negative values count as 0)."""
    return np.sqrt(shot_gain * np.clip(x, 0.0, None) + read_var)


class AngleMode(enum.Enum):
    """How the polarizer angles are drawn and the shots handed to the network (step 5)."""

    CLASSIC = "classic"
    ANY = "any"
    ANY_TRUE_SIDE = "any-true-side"


@dataclasses.dataclass
class SynthesisConfig:
    """Switches and ranges of the synthesis pipeline (defaults: the paper's full pipeline,
    with the paper's angles, ``AngleMode.CLASSIC``)."""

    patch: int = 128
    dynamic_range: bool = True
    k_max: float = 2.8
    abrupt_prob: float = 0.2
    nrd_prob: float = 0.5
    nrd_grid: int = 5
    nrd_sigma_max_px: float = 1.5
    curvature: bool = True
    curved_prob: float = 0.5
    aoi_deg: tuple[float, float] = (10.0, 80.0)
    angle_noise_deg: float = 4.0
    noise: bool = True
    shot_gain_log10: tuple[float, float] = SHOT_GAIN_LOG10
    read_var_log10: tuple[float, float] = READ_VAR_LOG10
    n: float = optics.N_GLASS
    angles: AngleMode = AngleMode.CLASSIC
    angle_sets_deg: tuple[tuple[float, ...], ...] = ANGLE_SETS_DEG
    phi_field_prob: float = 0.0
    phi_field_max_deg: float = 20.0
    no_glass_prob: float = 0.0
    no_glass_dolp_max: float = 0.4
    t_polarized_prob: float = 0.0
    t_dolp_max: float = 0.6
    real_prob: float = 0.0
    mono_prob: float = 0.0
    mosaic_prob: float = 0.0
    defocus_prob: float = 0.0
    strength: tuple[float, float] = (0.0, 0.0)
    incidence_estimate: bool = False
    incidence_error_deg: tuple[float, float] = (3.0, 1.5)
    incidence_failure: tuple[float, float] = (0.05, 0.3)
    reference_field: bool = False

    def __post_init__(self):
        self.angles = AngleMode(self.angles)
        self.shot_gain_log10, self.read_var_log10 = tuple(self.shot_gain_log10), tuple(self.read_var_log10)
        self.strength = tuple(self.strength)
        if len(self.strength) != 2 or self.strength != (0.0, 0.0) and not 0 < self.strength[0] <= self.strength[1]:
            raise ValueError(f"expected strength (0, 0) (as drawn) or (lo, hi) with 0 < lo <= hi, got {self.strength}")
        if any(len(r) != 2 or r[0] > r[1] for r in (self.shot_gain_log10, self.read_var_log10)):
            raise ValueError(f"expected noise ranges (lo, hi) with lo <= hi, got {self.shot_gain_log10} and {self.read_var_log10}")
        if self.mosaic_prob > 0 and (self.angles is AngleMode.CLASSIC or self.patch % 2):
            raise ValueError(f"expected mosaic samples in an ANY angle mode with an even patch, got angles "
                             f"{self.angles.value!r} and patch {self.patch}")
        if not self.angle_sets_deg or any(len(a) < 3 for a in self.angle_sets_deg):
            raise ValueError(f"expected angle sets of at least 3 angles each, got {self.angle_sets_deg}")

    @classmethod
    def ablation(cls, name: str, patch: int = 128, angles: AngleMode | str = AngleMode.CLASSIC) -> "SynthesisConfig":
        """The paper's ablation settings: 'DR', 'DR+NRD' or 'DR+NRD+LCG' (the full pipeline),
        with the given angle mode; and 'DR+LCG', the full pipeline without non-rigid deformation
        (shots registered as `urd ingest` registers them: the Fresnel gate's last stage)."""
        settings = {
            "DR": dict(nrd_prob=0.0, curvature=False),
            "DR+NRD": dict(curvature=False),
            "DR+NRD+LCG": {},
            "DR+LCG": dict(nrd_prob=0.0),
        }
        if name not in settings:
            raise ValueError(f"expected one of {sorted(settings)}, got {name!r}")
        return cls(patch=patch, angles=AngleMode(angles), **settings[name])


#: The long side (px) to which photos and real captures are reduced when read for synthesis.
POOL_MAX_SIDE = 512


def load_image_pool(folders: list[Path] | None = None, max_side: int = POOL_MAX_SIDE) -> list[np.ndarray]:
    """Natural photos as uint8 RGB arrays, at most ``max_side`` pixels on the long side.

    With no folders, scikit-image's bundled photos are used (no download needed).
    """
    images = []
    if folders:
        files = sorted(f for d in folders for f in Path(d).iterdir() if f.suffix.lower() in (".jpg", ".jpeg", ".png"))
        if not files:
            raise FileNotFoundError(f"no JPEG or PNG photos in {[str(d) for d in folders]}")
        for f in files:
            bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"cannot read image {f}")
            images.append(_shrink(bgr[..., ::-1], max_side))
    else:
        import skimage.data

        for name in BUNDLED_PHOTOS:
            img = getattr(skimage.data, name)()
            if img.ndim == 2:
                img = np.repeat(img[..., None], 3, axis=2)
            images.append(_shrink(np.ascontiguousarray(img[..., :3]), max_side))
    return images


@functools.cache
def default_pool(split: str) -> tuple[np.ndarray, ...]:
    """The image pool for a split: shared BSDS500 (+ Sun–Hays for train) or bundled photos.
    Read once per process and kept, read-only, for its life (0.2–1.3 s to read, 46–138 MB held):
    every training run, benchmark and semi-real scene set of a process shares it."""
    bsds = SHARED_NATURAL / "bsds500" / split
    folders = None
    if bsds.is_dir():
        folders = [bsds] + ([SHARED_NATURAL / "sunhays80"] if split == "train" else [])
    return _read_only(load_image_pool(folders))


def _shrink(img: np.ndarray, max_side: int) -> np.ndarray:
    scale = max_side / max(img.shape[:2])
    if scale >= 1:
        return img
    return cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def random_crop(rng: np.random.Generator, img: np.ndarray, size: int) -> np.ndarray:
    """A random crop of ``size``² at a random scale in [1, 2], randomly flipped; uint8 in, uint8 out."""
    h, w = img.shape[:2]
    side = int(min(h, w, size * rng.uniform(1.0, 2.0)))
    y, x = rng.integers(0, h - side + 1), rng.integers(0, w - side + 1)
    crop = cv2.resize(img[y : y + side, x : x + side], (size, size), interpolation=cv2.INTER_AREA)
    return crop[:, ::-1] if rng.random() < 0.5 else crop


def smooth_warp_field(rng: np.random.Generator, size: int, grid: int, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random warp: grid×grid anchor offsets ~ N(0, σ²), bicubic to size², as remap maps."""
    offsets = rng.normal(0.0, sigma_px, (2, grid, grid)).astype(np.float32)
    dx = cv2.resize(offsets[0], (size, size), interpolation=cv2.INTER_CUBIC)
    dy = cv2.resize(offsets[1], (size, size), interpolation=cv2.INTER_CUBIC)
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    return xs + dx, ys + dy


def phi_perp_map(rng: np.random.Generator, cfg: SynthesisConfig, center: float) -> np.ndarray:
    """φ⊥ (rad, P×P float32) around ``center``: constant, or (with probability
    ``cfg.phi_field_prob``) turning linearly by up to ``cfg.phi_field_max_deg`` across the patch
    in a random direction."""
    p = cfg.patch
    if cfg.phi_field_prob <= 0 or rng.random() >= cfg.phi_field_prob:
        return np.full((p, p), center, np.float32)
    turn = np.radians(rng.uniform(-cfg.phi_field_max_deg, cfg.phi_field_max_deg))
    direction = rng.uniform(0, 2 * np.pi)
    ys, xs = np.mgrid[0:p, 0:p].astype(np.float32) / (p - 1) - 0.5
    return (center + turn * (xs * np.cos(direction) + ys * np.sin(direction))).astype(np.float32)


def smooth_field(rng: np.random.Generator, size: int, grid: int = 4) -> np.ndarray:
    """A smooth random field in [0, 1] (size² float32): grid² uniform anchors, bicubic."""
    anchors = rng.uniform(0.0, 1.0, (grid, grid)).astype(np.float32)
    return np.clip(cv2.resize(anchors, (size, size), interpolation=cv2.INTER_CUBIC), 0.0, 1.0)


def surface_maps(rng: np.random.Generator, cfg: SynthesisConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel angle of incidence θ and s-direction φ⊥ (rad), each P×P float32."""
    p = cfg.patch
    theta_c = np.radians(rng.uniform(*cfg.aoi_deg))
    omega = rng.uniform(0, np.pi)  # image direction along which the plane of incidence runs
    phi_perp = phi_perp_map(rng, cfg, omega + np.pi / 2)
    if not cfg.curvature:
        return np.full((p, p), theta_c, np.float32), phi_perp
    distance = rng.uniform(1.0, 5.0)
    length = distance * rng.uniform(0.05, 0.8)
    curved = rng.random() < cfg.curved_prob
    sagitta = length * rng.uniform(0.0, 0.05) if curved else 0.0
    convexity = 1 if rng.random() < 0.5 else -1
    ys, xs = np.mgrid[0:p, 0:p].astype(np.float32) / (p - 1) - 0.5
    t = xs * np.cos(omega) - ys * np.sin(omega)  # rows grow downwards, angles count upwards
    theta = parabola_aoi(theta_c, distance, length, sagitta, convexity, t.ravel()).reshape(p, p)
    return np.minimum(theta, np.radians(85.0)).astype(np.float32), phi_perp


#: Within this angle of incidence (deg) of head-on, or without glass, an estimate fails more often.
HEAD_ON_DEG = 30.0


def perturbed_incidence(rng: np.random.Generator, theta: np.ndarray, error_deg: tuple[float, float] = (3.0, 1.5),
                        failure: tuple[float, float] = (0.05, 0.3)) -> np.ndarray:
    """The angle of incidence (rad, P×P float32) as an estimate of the true map ``theta`` reads:
    off by a global error ~ N(0, σ²), σ ~ U[0, ``error_deg[0]``], and a smooth error within
    ±``error_deg[1]`` (deg), held in `separate.reference.INCIDENCE_RANGE_DEG`; or a failed estimate,
    one angle drawn over that range, with probability ``failure[0]`` (``failure[1]`` within
    `HEAD_ON_DEG` of head-on, where three shots barely tell θ, and without glass, θ = 0). `separate.incidence.estimate_incidence_field` is off by a median
    1–2° from θ = 35° up on the virtual camera's panes, 4–6° at 20° (`urd bench --virtual`)."""
    lo, hi = INCIDENCE_RANGE_DEG
    theta_deg = np.degrees(theta.astype(np.float32))
    if rng.random() < (failure[1] if theta_deg.mean() < HEAD_ON_DEG else failure[0]):
        return np.full(theta.shape, np.radians(rng.uniform(lo, hi)), np.float32)
    offset = rng.normal(0.0, rng.uniform(0.0, error_deg[0]))
    local = error_deg[1] * (2 * smooth_field(rng, theta.shape[0]) - 1)
    return np.radians(np.clip(theta_deg + offset + local, lo, hi)).astype(np.float32)


def true_side_deg(reference_deg: float, phi_perp_deg: float) -> float:
    """``reference_deg``, or it + 90° if it lies more than 45° from ``phi_perp_deg`` modulo
    180° (deg)."""
    return reference_deg + 90.0 if abs(optics.axis_gap_deg(reference_deg, phi_perp_deg)) > 45.0 else reference_deg


def capture_stokes(capture: samples.Capture, max_side: int = POOL_MAX_SIDE) -> tuple[np.ndarray, np.ndarray]:
    """A real capture's Stokes stack (3, H, W, 3) from the least-squares fit of its shots, scaled
    to a mean S0 of 1, and its clipped pixels (H×W bool: ≥ `CLIPPED` in any shot, where any
    pixel of the full-resolution capture under it is), at most ``max_side`` px long."""
    full, angles = samples.load(capture)
    stack = np.stack([samples.area_reduce(shot, max_side) for shot in full])     # as load(capture, max_side)
    clipped = samples.area_reduce((full >= CLIPPED).any(axis=(0, 3)).astype(np.float32), max_side) > 0
    stokes = optics.stokes_from_images(stack, np.radians(angles)).astype(np.float32)
    return stokes / max(float(stokes[0].mean()), 1e-6), clipped


#: A real capture's pixel counts as clipped from this linear value in any of its shots.
CLIPPED = 0.98


@functools.cache
def real_pool(split: str = "train") -> tuple[tuple[np.ndarray, np.ndarray, bool], ...]:
    """The real no-glass captures of one side of the split as (Stokes, clipped, mono)
    (`capture_stokes`); empty without ../shared/data. Read once per process and kept, read-only,
    for its life (2–4 s to read, ~130 MB held)."""
    return tuple((*_read_only(capture_stokes(c)), c.mono) for c in samples.no_glass_captures(split=split))


def training_data(real_prob: float) -> tuple[str, list[str]]:
    """What training samples are synthesized from, as a model card states it, and what of urd's
    training data is missing here (``../shared/data``'s photos; with ``real_prob`` > 0 its real
    no-glass captures), for a warning: the pool falls back to scikit-image's bundled photos."""
    missing = []
    if (SHARED_NATURAL / "bsds500" / "train").is_dir():
        text = "synthesized from bsds500/train + sunhays80 (../shared/data/natural)"
    else:
        text, missing = "synthesized from scikit-image's bundled photos", ["../shared/data/natural (bsds500, sunhays80)"]
    if real_prob > 0:
        real = len(samples.no_glass_captures(split="train"))
        text += f" and {real} real no-glass captures (../shared/data/polarization, training side)" if real else ""
        missing += [] if real else ["../shared/data/polarization (real no-glass captures for real_prob)"]
    return text, missing


def _read_only(arrays: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
    """The arrays, marked read-only: a cached pool is shared, so nothing may write into it."""
    for array in arrays:
        array.setflags(write=False)
    return tuple(arrays)


def grey(image: np.ndarray) -> np.ndarray:
    """An image (…, C) with every channel set to the channels' mean, float32."""
    return np.repeat(image.mean(axis=-1, keepdims=True), image.shape[-1], axis=-1).astype(np.float32)


def turn_stokes(stokes: np.ndarray, flip: bool, quarter_turns: int) -> np.ndarray:
    """A Stokes stack (3, H, W, C) mirrored left–right (``flip``) and then turned by
    ``quarter_turns`` × 90° counter-clockwise, its polarization turned alike: a mirror maps an
    axis φ to −φ (S2 → −S2), a quarter turn to φ + 90° (S1, S2 → −S1, −S2)."""
    out = stokes[:, :, ::-1] * np.array([1, 1, -1], np.float32)[:, None, None, None] if flip else stokes
    out = np.rot90(out, quarter_turns, axes=(1, 2))
    if quarter_turns % 2:
        out = out * np.array([1, -1, -1], np.float32)[:, None, None, None]
    return np.ascontiguousarray(out, dtype=np.float32)


def real_crop(rng: np.random.Generator, stokes: np.ndarray, clipped: np.ndarray, size: int) -> np.ndarray | None:
    """A random ``size``² crop of a real Stokes stack at a scale in [1, 2], mirrored and turned
    at random (`turn_stokes`); None where it holds clipped pixels."""
    h, w = stokes.shape[1:3]
    side = int(min(h, w, size * rng.uniform(1.0, 2.0)))
    y, x = rng.integers(0, h - side + 1), rng.integers(0, w - side + 1)
    if clipped[y:y + side, x:x + side].mean() > 0.001:
        return None
    crop = np.stack([cv2.resize(np.ascontiguousarray(plane), (size, size), interpolation=cv2.INTER_AREA)
                     for plane in stokes[:, y:y + side, x:x + side]])
    return turn_stokes(crop, bool(rng.random() < 0.5), int(rng.integers(4)))


def own_polarization(rng: np.random.Generator, photo: np.ndarray, dolp_max: float) -> tuple[np.ndarray, np.ndarray]:
    """A polarization of the photo's own (DoLP, AoLP (rad)), each P×P float32: the sum of one to
    three of the kinds real scenes show (the no-glass captures of ../shared/data: DoLP medians
    0.02–0.12, 95th percentiles 0.07–0.5):

    * sky: smooth and strong, DoLP up to ``dolp_max``, its angle turning slowly;
    * gloss: the photo's highlights (its brightest 5–20 %, softened), DoLP up to ``dolp_max``;
    * contours: diffuse polarization across object edges, DoLP up to 0.25, along the luminance
      gradient (the surface normal's direction in the image).
    """
    p = photo.shape[0]
    lum = photo.mean(axis=2)
    stokes = np.zeros((3, p, p), np.float32)
    stokes[0] = 1.0
    for kind in rng.choice(3, int(rng.integers(1, 4)), replace=False):
        if kind == 0:
            dolp = rng.uniform(0.1, dolp_max) * smooth_field(rng, p, 3)
            aolp = rng.uniform(0.0, np.pi) + np.radians(40.0) * (smooth_field(rng, p) - 0.5)
        elif kind == 1:
            bright = (lum >= np.quantile(lum, 1.0 - rng.uniform(0.05, 0.2))).astype(np.float32)
            dolp = rng.uniform(0.2, dolp_max) * cv2.GaussianBlur(bright, (0, 0), 1.5)
            aolp = rng.uniform(0.0, np.pi) + np.radians(60.0) * (smooth_field(rng, p) - 0.5)
        else:
            gx = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3)
            gy = cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)
            magnitude = cv2.GaussianBlur(np.hypot(gx, gy), (0, 0), 1.0)
            dolp = rng.uniform(0.05, 0.25) * np.clip(magnitude / (np.quantile(magnitude, 0.95) + 1e-6), 0.0, 1.0)
            aolp = np.arctan2(-gy, gx)                     # rows grow downwards, angles count upwards
        stokes[1:] += optics.stokes_from_polarization(np.ones((p, p), np.float32), dolp, aolp)[1:].astype(np.float32)
    return np.minimum(optics.dolp(stokes, eps=0.0), 0.95).astype(np.float32), optics.aolp(stokes).astype(np.float32)


def _warp(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """An H×W×C image (or a (3, H, W, C) Stokes stack, plane by plane) through remap maps; as is for None."""
    if maps is None:
        return image
    if image.ndim == 4:
        return np.stack([_warp(plane, maps) for plane in image])
    return cv2.remap(image, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


class Synthesizer:
    """Draws training samples from an image pool; deterministic for a seed.

    A sample is a dict of float32 arrays: ``obs`` 3×P×P×3 (the network's input: CLASSIC, the
    shots at φ0, φ0+45°, φ0+90°; ANY and ANY_TRUE_SIDE, the shots presented at the estimated
    reference), ``r`` and ``t`` P×P×3 (the observable layers R_obs, T_obs), ``theta`` and
    ``phi_perp`` P×P, ``angles`` (3,) the angles of ``obs`` (rad; CLASSIC: the true polarizer
    angles; ANY modes: reference + 0/45/90° in the nominal angles' frame, which is φ⊥'s frame),
    and ``shots`` () the number of shots taken (3 in CLASSIC). ``real``: the real captures'
    (Stokes, clipped, mono) for ``cfg.real_prob`` (default: `real_pool`'s training side).
    """

    def __init__(self, pool: Sequence[np.ndarray], cfg: SynthesisConfig, seed: int,
                 real: Sequence[tuple[np.ndarray, np.ndarray, bool]] | None = None):
        if len(pool) < 2:
            raise ValueError(f"expected at least 2 images in the pool, got {len(pool)}")
        self.pool = [img for img in pool if min(img.shape[:2]) >= cfg.patch]
        if len(self.pool) < 2:
            raise ValueError(f"expected at least 2 images of at least {cfg.patch} px, got {len(self.pool)}")
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        self.rejected = 0
        if real is None and cfg.real_prob > 0:
            real = real_pool("train")
        self.real = [entry for entry in (real or []) if min(entry[0].shape[1:3]) >= cfg.patch]
        self.mosaic = None                       # the twin that draws mosaic samples at twice the size
        if cfg.mosaic_prob > 0:
            twin = dataclasses.replace(cfg, patch=2 * cfg.patch, mosaic_prob=0.0, angle_sets_deg=(MOSAIC_ANGLES_DEG,))
            self.mosaic = Synthesizer(pool, twin, seed, real=real or [])
            self.mosaic.rng = self.rng

    def sample(self) -> dict[str, np.ndarray]:
        """One accepted sample (rejected draws are counted in ``self.rejected``)."""
        while True:
            mosaic = self.mosaic is not None and self.rng.random() < self.cfg.mosaic_prob
            parts = self.mosaic._draw() if mosaic else self._draw()
            if parts is not None:
                return self._finish(*(through_mosaic(*parts) if mosaic else parts))
            self.rejected += 1

    def batch(self, size: int) -> dict[str, np.ndarray]:
        """``size`` samples stacked on a new leading axis."""
        samples = [self.sample() for _ in range(size)]
        return {k: np.stack([s[k] for s in samples]) for k in samples[0]}

    def _draw(self) -> tuple[np.ndarray, ...] | None:
        """A sample's parts before `_finish` (shots, R_obs, T_obs, nominal and true angles, θ, φ⊥),
        or None for a rejected draw."""
        cfg, rng, p = self.cfg, self.rng, self.cfg.patch
        if cfg.no_glass_prob > 0 and rng.random() < cfg.no_glass_prob:
            return self._draw_no_glass()
        i, j = rng.choice(len(self.pool), 2, replace=False)
        refl = photo_to_linear(random_crop(rng, self.pool[i], p))
        trans = photo_to_linear(random_crop(rng, self.pool[j], p))
        stokes_t, grey_capture = self._transmitted(trans)
        mono = cfg.mono_prob > 0 and rng.random() < cfg.mono_prob
        if mono or grey_capture:                      # a mono capture's view: the reflection grey too
            refl, trans = grey(refl), grey(trans)
            stokes_t = None if stokes_t is None else grey(stokes_t)
        if cfg.defocus_prob > 0 and rng.random() < cfg.defocus_prob:
            refl = cv2.GaussianBlur(refl, (0, 0), rng.uniform(1.0, 4.0) * p / 128)
        if cfg.dynamic_range:
            beta = rng.uniform(1.0, cfg.k_max)
            refl, trans = refl * beta, trans / beta
            stokes_t = None if stokes_t is None else stokes_t / beta
        if rng.random() < cfg.abrupt_prob:
            level = (refl + (trans if stokes_t is None else stokes_t[0])).mean()
            refl = np.where(refl.mean(axis=2, keepdims=True) < level, 0.0, refl).astype(np.float32)
        theta, phi_perp = surface_maps(rng, cfg)
        if cfg.angles is AngleMode.CLASSIC:
            phi0 = phi_perp[0, 0] - rng.uniform(-np.pi / 4, np.pi / 4)
            nominal = phi0 + np.radians(optics.PAPER_ANGLES_DEG)
        else:
            offsets = cfg.angle_sets_deg[int(rng.integers(len(cfg.angle_sets_deg)))]
            nominal = rng.uniform(0.0, np.pi) + np.radians(offsets)
        noise = np.radians(rng.uniform(-cfg.angle_noise_deg, cfg.angle_noise_deg, len(nominal)))
        angles = (nominal + noise).astype(np.float32)
        deform = rng.random() < cfg.nrd_prob
        sigma = rng.uniform(0.0, cfg.nrd_sigma_max_px) * p / 128
        zeros = np.zeros_like(refl)
        if stokes_t is None:
            r_obs, t_obs = optics.observable_layers(refl, trans, theta, cfg.n)
        else:
            parts = optics.pane_stokes(np.stack([refl, zeros, zeros]), stokes_t, theta, phi_perp, cfg.n)
            r_obs, t_obs = parts[0][0], parts[1][0]
        if cfg.strength[1] > 0 and r_obs.mean() > 0:
            scale = np.float32(np.exp(rng.uniform(*np.log(cfg.strength))) * t_obs.mean() / r_obs.mean())
            refl, r_obs = refl * scale, r_obs * scale
            parts = None if stokes_t is None else (parts[0] * scale, parts[1])
        shots = []
        for phi in angles:
            maps = smooth_warp_field(rng, p, cfg.nrd_grid, sigma) if deform else None
            if stokes_t is None:
                shots.append(optics.render(_warp(refl, maps), _warp(trans, maps), theta, phi_perp, float(phi), cfg.n))
                continue
            if maps is not None:
                parts = optics.pane_stokes(np.stack([_warp(refl, maps), zeros, zeros]), _warp(stokes_t, maps),
                                           theta, phi_perp, cfg.n)
            shots.append(optics.intensity_from_stokes(parts[0] + parts[1], float(phi)))
        obs = np.stack(shots).astype(np.float32)
        exposed = self._expose(obs, r_obs, t_obs)
        return None if exposed is None else (*exposed, nominal, angles, theta, phi_perp)

    def _transmitted(self, photo: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """The transmitted light's Stokes stack (3, P, P, 3) where the sample's transmitted layer
        is polarized: a real capture's crop (``real_prob``, scaled to the photo's mean) or the
        photo with a polarization of its own (``t_polarized_prob``); None for the unpolarized photo;
        and whether it is a mono capture's (grey: the sample's reflection must be grey too)."""
        cfg, rng = self.cfg, self.rng
        if self.real and cfg.real_prob > 0 and rng.random() < cfg.real_prob:
            crop, mono = self._real_crop()
            if crop is not None:
                return crop * float(photo.mean()), mono
        if cfg.t_polarized_prob > 0 and rng.random() < cfg.t_polarized_prob:
            dolp, aolp = own_polarization(rng, photo, cfg.t_dolp_max)
            return optics.stokes_from_polarization(photo, dolp[..., None], aolp[..., None]).astype(np.float32), False
        return None, False

    def _real_crop(self) -> tuple[np.ndarray | None, bool]:
        """A crop of a random real capture (`real_crop`), grey for a mono capture (None where
        clipped), and whether the capture is mono."""
        stokes, clipped, mono = self.real[int(self.rng.integers(len(self.real)))]
        crop = real_crop(self.rng, stokes, clipped, self.cfg.patch)
        return (crop if crop is None or not mono else grey(crop)), mono

    def _expose(self, obs: np.ndarray, r_obs: np.ndarray, t_obs: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Step 6: a random exposure, sensor noise, and the shots clipped to [0, 1]; None for a
        patch that is saturated, dark or flat."""
        cfg, rng = self.cfg, self.rng
        exposure = rng.uniform(0.1, 0.35) / max(float((r_obs + t_obs).mean()), 1e-6)
        obs, r_obs, t_obs = obs * exposure, r_obs * exposure, t_obs * exposure
        if cfg.noise:
            shot_gain, read_var = draw_noise_levels(rng, cfg.shot_gain_log10, cfg.read_var_log10)
            obs = obs + rng.normal(0.0, 1.0, obs.shape).astype(np.float32) * noise_std(obs, shot_gain, read_var)
        if (obs > 1.0).mean() > 0.01 or (r_obs + t_obs).mean() < 0.02 or t_obs.std() < 0.01:
            return None
        return np.clip(obs, 0.0, 1.0).astype(np.float32), r_obs, t_obs

    def _draw_no_glass(self) -> tuple[np.ndarray, ...] | None:
        """A view with no glass: one photo with a smooth polarization of its own, or a real capture's
        crop (``real_prob``) (module docstring)."""
        cfg, rng, p = self.cfg, self.rng, self.cfg.patch
        stokes = self._real_crop()[0] if self.real and cfg.real_prob > 0 and rng.random() < cfg.real_prob else None
        if stokes is None:
            photo = photo_to_linear(random_crop(rng, self.pool[int(rng.integers(len(self.pool)))], p))
            dolp = rng.uniform(0.0, cfg.no_glass_dolp_max) * smooth_field(rng, p)
            aolp = rng.uniform(0.0, np.pi) + np.radians(60.0) * (smooth_field(rng, p) - 0.5)
            stokes = optics.stokes_from_polarization(photo, optics.expand_map(dolp, photo), optics.expand_map(aolp, photo))
        if cfg.mono_prob > 0 and rng.random() < cfg.mono_prob:
            stokes = grey(stokes)
        photo = stokes[0].astype(np.float32)
        offsets = optics.PAPER_ANGLES_DEG if cfg.angles is AngleMode.CLASSIC else \
            cfg.angle_sets_deg[int(rng.integers(len(cfg.angle_sets_deg)))]
        nominal = rng.uniform(0.0, np.pi) + np.radians(offsets)
        angles = (nominal + np.radians(rng.uniform(-cfg.angle_noise_deg, cfg.angle_noise_deg, len(nominal)))).astype(np.float32)
        obs = np.stack([optics.intensity_from_stokes(stokes, float(phi)) for phi in angles]).astype(np.float32)
        exposed = self._expose(obs, np.zeros_like(photo), photo)
        zeros = np.zeros((p, p), np.float32)
        return None if exposed is None else (*exposed, nominal, angles, zeros, zeros)

    def _finish(self, obs: np.ndarray, r_obs: np.ndarray, t_obs: np.ndarray, nominal: np.ndarray, angles: np.ndarray,
                theta: np.ndarray, phi_perp: np.ndarray) -> dict[str, np.ndarray]:
        """A sample from its shots: in the ANY modes presented at the estimated reference (or
        reference field), turned to φ⊥'s side in ANY_TRUE_SIDE where the view has glass (θ > 0),
        with an estimate of the angle of incidence where asked."""
        cfg = self.cfg
        if cfg.angles is not AngleMode.CLASSIC:
            nominal_deg = np.degrees(nominal)
            inspection = inspect_stack(obs, nominal_deg)
            turn = 0.0
            if cfg.angles is AngleMode.ANY_TRUE_SIDE and theta.any():
                turn = true_side_deg(inspection.reference_deg, circular_mean_deg(phi_perp)) - inspection.reference_deg
            if cfg.reference_field:
                obs, presented_deg = present_field(obs, nominal_deg, field_at(inspection.field, obs.shape[1:3]) + turn)
            else:
                obs, presented_deg = present(obs, nominal_deg, inspection.reference_deg + turn)
            obs, angles = np.maximum(obs, 0.0), np.radians(presented_deg).astype(np.float32)
        sample = {
            "obs": obs.astype(np.float32),
            "r": r_obs.astype(np.float32),
            "t": t_obs.astype(np.float32),
            "theta": theta,
            "phi_perp": phi_perp,
            "angles": angles,
            "shots": np.float32(len(nominal)),
        }
        if cfg.incidence_estimate:
            sample["theta_est"] = perturbed_incidence(self.rng, theta, cfg.incidence_error_deg, cfg.incidence_failure)
        return sample


def through_mosaic(obs: np.ndarray, r_obs: np.ndarray, t_obs: np.ndarray, nominal: np.ndarray, angles: np.ndarray,
                   theta: np.ndarray, phi_perp: np.ndarray) -> tuple[np.ndarray, ...]:
    """A sample's parts drawn at 2P with four shots at a mosaic sensor's 0/45/90/135° (from any
    first angle) as the sensor and `urd ingest` give them: one angle per pixel (and, for a
    colour sample, one colour; `urd.core.mosaic.build_mosaic`: IMX250MZR where the layers are
    grey, else IMX250MYR), demosaiced at half size (Newton, each 2×2 cell's mean); the layers
    and θ averaged over the same cells, φ⊥ as an axis. Returns the parts at P."""
    mono = all(np.array_equal(x[..., 0], x[..., k]) for x in (r_obs, t_obs) for k in (1, 2))   # noise differs per channel
    layout = MosaicLayout.IMX250MZR if mono else MosaicLayout.IMX250MYR
    stack, _ = demosaic(build_mosaic(obs[..., :1] if mono else obs, layout), layout, Demosaic.NEWTON)
    stack = np.repeat(stack, 3, axis=-1) if mono else stack
    phi = np.angle(cell_means(np.exp(2j * phi_perp.astype(np.float64)))) / 2 % np.pi
    return (stack, *(cell_means(x).astype(np.float32) for x in (r_obs, t_obs)), nominal, angles,
            cell_means(theta).astype(np.float32), phi.astype(np.float32))


def circular_mean_deg(axis_rad: np.ndarray) -> float:
    """The mean direction (deg) of an axis map (rad; axes repeat every 180°)."""
    return float(np.degrees(np.angle(np.exp(2j * axis_rad.astype(np.float64)).mean())) / 2)
