"""The robustness study: the methods under controlled shooting conditions, one factor at a time.

The layers of seeded synthetic patches are rendered again with `separate.optics` under a
`Condition` varied one factor at a time from a base condition (exact angles 0/45/90, no
misalignment, medium noise, φ⊥ within ±45° of the first shot, as the synthesizer draws it):
polarizer angle error, residual misalignment, noise, φ⊥ relative to the first shot, number of
angles, nominal versus calibrated angles (`AXES`). Every condition of a patch uses the same
random draws (`Draws`, `draw_nuisances`), so conditions and methods are compared on paired
data. A method that refuses an input (ValueError, e.g. calibrated angles spanning less than
90°) scores NaN on that patch: its means leave the patch out and the rows count refusals
(`robustness`).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Callable, Sequence

import numpy as np

from separate import optics
from separate.bench import SEED
from separate.scoring import attempt, finite_mean
from separate.synthesis import noise_std
from urd.core.progress import Progress

ROBUST_SEED = SEED + 1
MAX_SHOTS = 6


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

    def __post_init__(self) -> None:
        """Normalize ``noise`` to `Noise` and the angles to floats; check counts and signs."""
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
        """The (label, condition) levels a run measures: all of them, or the quick subset."""
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
                             "psnr_t": finite_mean(cell["psnr_t"]), "psnr_r": finite_mean(cell["psnr_r"]),
                             "psnr_t_per_patch": cell["psnr_t"], "psnr_r_per_patch": cell["psnr_r"],
                             "failed": len(cell["failures"]), "failure": cell["failures"][0] if cell["failures"] else None})
    return rows
