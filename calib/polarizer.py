"""Polarizer calibration.

Mounting offset
    The polarizer's axis at stage zero. A sweep photographs a target whose light is linearly
    polarized at a known angle ψ_t (a sheet polarizer on a light box, an LCD) at stage angles
    a_k. Malus's law, I(a) = c0 + c1·cos 2a + c2·sin 2a, peaks at a = ψ_t − offset, so
    offset = ψ_t − ½·atan2(c2, c1). The fit is linear least squares; its covariance gives
    the uncertainty.

Sense of rotation
    urd takes a positive stage move to turn the polarizer counter-clockwise as the camera sees
    it; a mount turned round turns it the other way, which one sweep cannot tell (it fits either
    sense with another offset). Two sweeps with the target's axis turned between them tell it
    (`check_direction`): counter-clockwise, both give the same offset.

Per-shot angle error
    The actual angle of each shot of a scene, from the images alone. Each pixel's N shots
    must be explained by 3 Stokes parameters; the angles φ_k that make that possible are
    found by Levenberg–Marquardt on the residual of the per-pixel Stokes fit (variable
    projection), from the nominal angles, on the stack averaged down to a few thousand pixels
    (noise in the per-pixel Stokes nuisance parameters otherwise biases the angles). It needs shots registered much better than the ECC alignment
    of hand-held shots gives: on weakly polarized scenes 0.05 px of misregistration disturbs
    the pixels as much as a 2° angle error, so calibrate from a tripod. One common rotation of all angles never
    shows in the images (the mounting offset fixes it), so errors are reported with zero
    mean. With N ≥ 5 angles every other combination is determined. With N = 4 one more is
    not: any affine map of the points (cos 2φ_k, sin 2φ_k) that keeps them on the unit
    circle (a conic of the pencil through 4 points) explains the images equally well, so
    the result is the smallest correction consistent with the images. The uncertainty is
    the spread over a bootstrap of image tiles.

Angles here are degrees at the interface, radians inside.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from separate import optics
from urd.core.errors import CalibrationError


@dataclasses.dataclass
class OffsetFit:
    """Result of a Malus-law sweep fit: the mounting offset and its 1σ uncertainty (degrees),
    the target's degree of linear polarization (``modulation``, unitless) and the fit's RMS
    residual (intensity units)."""

    offset_deg: float
    uncertainty_deg: float
    modulation: float
    residual_rms: float

    def record(self) -> dict:
        return {k: round(float(v), 5) for k, v in dataclasses.asdict(self).items()}


def malus_fit(stage_angles_deg: np.ndarray, intensities: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares Malus-law fit of a sweep, I(a) = A(a)·S with A = `separate.optics.stokes_matrix`:
    the target's Stokes vector S (3,) as seen by the stage, the RMS residual (intensity units,
    N − 3 degrees of freedom) and S's covariance (3, 3). CalibrationError unless there are at
    least 4 angles (deg) with one intensity each."""
    a = np.radians(np.asarray(stage_angles_deg, np.float64))
    y = np.asarray(intensities, np.float64)
    if a.size < 4 or a.size != y.size:
        raise CalibrationError(f"expected at least 4 sweep angles with one intensity each, got {a.size} and {y.size}")
    design = optics.stokes_matrix(a)
    stokes, *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = y - design @ stokes
    rms = float(np.sqrt(residual @ residual / (a.size - 3)))
    return stokes, rms, rms**2 * np.linalg.inv(design.T @ design)


#: The least degree of linear polarization a sweep's Malus fit must show for an offset.
MIN_MODULATION = 0.05
#: The least unsaturated pixels (of the reduced shots) an angle-error estimate needs.
MIN_PIXELS = 20


def fit_offset(stage_angles_deg: np.ndarray, intensities: np.ndarray, target_angle_deg: float = 0.0) -> OffsetFit:
    """Mounting offset from a sweep: mean intensities of the target at each stage angle (deg);
    the target's polarization axis is at ``target_angle_deg``."""
    stokes, rms, cov = malus_fit(stage_angles_deg, intensities)
    modulation = float(optics.dolp(stokes, eps=0.0)) if stokes[0] > 0 else 0.0
    if modulation < MIN_MODULATION:
        raise CalibrationError(f"the sweep shows almost no Malus modulation: expected a DoLP of at least {MIN_MODULATION:g}, "
                               f"got {modulation:.3f}; is the target polarized?")
    s1, s2 = stokes[1], stokes[2]
    grad = np.array([0.0, -0.5 * s2, 0.5 * s1]) / (s1**2 + s2**2)      # of AoLP = ½·atan2(S2, S1)
    offset = (target_angle_deg - np.degrees(optics.aolp(stokes))) % 180.0
    return OffsetFit(float(offset), float(np.degrees(np.sqrt(grad @ cov @ grad))), modulation, rms)


#: The least turn (deg) of the target between the two sweeps of a direction check, away from 0°
#: and 90° (mod 180°): at those the two senses of rotation predict the same offsets.
MIN_TARGET_TURN_DEG = 20.0
#: How far (deg) the second sweep's offset may lie from the nearer of the two predictions.
DIRECTION_TOLERANCE_DEG = 5.0


def wrapped_deg(angle: float) -> float:
    """An axis difference (deg, mod 180) as the nearest value in (−90, 90]."""
    return 90.0 - (90.0 - angle) % 180.0


def check_target_turn(first_target_deg: float, second_target_deg: float) -> float:
    """The target's turn between the two sweeps of a direction check (deg, wrapped to ±90°);
    CalibrationError unless it lies `MIN_TARGET_TURN_DEG` or more away from 0° and 90°."""
    turn = wrapped_deg(second_target_deg - first_target_deg)
    if not MIN_TARGET_TURN_DEG <= abs(turn) <= 90.0 - MIN_TARGET_TURN_DEG:
        raise CalibrationError(f"the target turns by {turn:.1f} deg between the sweeps (mod 180): too near 0 or 90 deg, "
                               f"where the two senses of rotation give offsets too alike to tell apart; turn it by "
                               f"{MIN_TARGET_TURN_DEG:g} to {90 - MIN_TARGET_TURN_DEG:g} deg (45 is best)")
    return turn


def check_direction(first: OffsetFit, first_target_deg: float, second: OffsetFit, second_target_deg: float) -> float:
    """Whether the stage turns the polarizer counter-clockwise as the camera sees it, as urd takes
    stage angles, from two sweeps with the target's axis at two angles: the offset is
    ψ − a_peak for each. Counter-clockwise, ψ = offset + a, so both give the offset; clockwise,
    ψ = offset − a, so they differ by twice the target's turn. Returns their difference (deg,
    wrapped to ±90°); CalibrationError when the stage turns the polarizer clockwise, when the target
    was turned too little (or by about 90°) to tell, or when neither sense explains the two sweeps."""
    turn = check_target_turn(first_target_deg, second_target_deg)
    difference = wrapped_deg(second.offset_deg - first.offset_deg)
    clockwise = wrapped_deg(difference - 2.0 * turn)
    slack = DIRECTION_TOLERANCE_DEG + 3.0 * math.hypot(first.uncertainty_deg, second.uncertainty_deg)
    if abs(difference) <= slack:
        return difference
    if abs(clockwise) <= slack:
        raise CalibrationError(f"the stage turns the polarizer clockwise as the camera sees it: the offsets at target "
                               f"angles {first_target_deg:g} and {second_target_deg:g} deg differ by {difference:.2f} deg, "
                               f"twice the target's turn (or the target was turned clockwise: check that first); urd "
                               "takes stage angles counter-clockwise, so turn the rotation mount round (its other face "
                               "towards the camera) and calibrate again")
    raise CalibrationError(f"the two sweeps' offsets differ by {difference:.2f} deg, which neither sense of rotation "
                           f"explains (0, or {wrapped_deg(2 * turn):.2f} deg for a target turned by {turn:g} deg); was the "
                           "target turned counter-clockwise as the camera sees it, by exactly that?")


@dataclasses.dataclass
class ShotErrors:
    """Per-shot angle errors of a scene (degrees, zero mean) and their bootstrap spread.

    With exactly 4 angles one combination of the errors besides the common rotation is not
    observable (``unobservable`` gives its unit direction); the reported errors are then the
    smallest correction that explains the images.
    """

    errors_deg: list[float]
    uncertainty_deg: list[float]
    pixels: int
    iterations: int
    unobservable: list[float] | None

    def record(self) -> dict:
        return {"errors_deg": [round(e, 4) for e in self.errors_deg],
                "uncertainty_deg": [round(u, 4) for u in self.uncertainty_deg],
                "unobservable_direction": None if self.unobservable is None else [round(u, 4) for u in self.unobservable],
                "pixels": self.pixels, "iterations": self.iterations, "method": "stokes self-consistency, Levenberg-Marquardt (minimum-norm steps)"}


def _residual(phi: np.ndarray, data: np.ndarray) -> np.ndarray:
    """What a Stokes fit at angles ``phi`` (rad) leaves unexplained of ``data`` (N, P), flattened."""
    return (data - optics.stokes_matrix(phi) @ (optics.stokes_fit(phi) @ data)).ravel()


def _solve_angles(data: np.ndarray, nominal: np.ndarray, iterations: int = 100,
                  tol: float = 1e-9) -> tuple[np.ndarray, int, np.ndarray | None]:
    """Levenberg–Marquardt on the variable-projection residual, from the nominal angles.

    The damped (ridge) steps never move along the residual's null space (the common rotation
    and, for N = 4, the unobservable direction), so the result is the solution nearest the
    nominal angles. Returns the angles (rad), the iterations, and the unobservable direction
    (None when N ≥ 5).
    """
    phi, n = nominal.copy(), nominal.size
    r = _residual(phi, data)
    cost, lam, step = r @ r, None, 1e-6
    for it in range(1, iterations + 1):  # noqa: B007 - the count of iterations is returned
        jac = np.stack([(_residual(phi + step * np.eye(n)[k], data) - r) / step for k in range(n)], axis=1)
        lam = lam if lam is not None else 1e-6 * float(np.sum(jac**2))
        normal, gradient = jac.T @ jac, jac.T @ r          # the ridge step's normal equations (n × n)
        for _ in range(20):
            delta = -np.linalg.solve(normal + lam * np.eye(n), gradient)
            trial = phi + delta
            r_trial = _residual(trial, data)
            if r_trial @ r_trial < cost:
                phi, r, cost, lam = trial, r_trial, r_trial @ r_trial, lam / 3
                break
            lam *= 10
        else:
            break
        if np.max(np.abs(delta)) < tol:
            break
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    gauge = np.ones(n) / np.sqrt(n)
    extra = [v - (v @ gauge) * gauge for v in vt[sv < 1e-3 * sv[0]]]
    extra = [v / np.linalg.norm(v) for v in extra if np.linalg.norm(v) > 0.5]
    return phi - np.mean(phi - nominal), it, (extra[0] if extra else None)


#: Largest per-shot angle error (deg) `estimate_shot_errors` reports: a stage's encoder puts the
#: polarizer within a fraction of a degree and the paper allows ±4°. Larger errors mean the images
#: do not determine the angles (little polarized light against the noise, or misaligned shots):
#: the fit then slides towards angles that all coincide, where any stack is explained.
MAX_SHOT_ERROR_DEG = 10.0


def estimate_shot_errors(stack: np.ndarray, nominal_deg: list[float], short_side: int = 32,
                         bootstrap: int = 20, seed: int = 0) -> ShotErrors:
    """Per-shot polarizer angle errors from an aligned stack.

    Args:
        stack: (N, H, W, C) aligned linear shots, N ≥ 4 (N ≥ 5 determines every error).
        nominal_deg: the N angles the shots were taken at (deg).
        short_side: size the stack is averaged down to (px) before fitting.
        bootstrap: resamples of 8×8 image tiles for the uncertainty.
    """
    nominal = optics.check_angles(np.radians(nominal_deg))
    if stack.shape[0] != nominal.size:
        raise CalibrationError(f"expected {nominal.size} shots, got {stack.shape[0]}")
    if nominal.size < 4:
        raise CalibrationError(f"per-shot angle errors need at least 4 angles (the fit is exact with 3), got {nominal.size}")
    # average down to a short side of `short_side` px: the model is linear, so block averages obey
    # it exactly, and averaging cuts the noise that biases the angles (the per-pixel Stokes
    # parameters are nuisance parameters estimated from the same noisy data: Neyman–Scott)
    n, height, width = stack.shape[:3]
    scale = min(1.0, short_side / min(height, width))
    size = (max(4, round(width * scale)), max(4, round(height * scale)))
    margin = (height // 20, width // 20)                           # aligned shots are padded at the border
    inner = stack.reshape(n, height, width, -1)[:, margin[0]:height - margin[0], margin[1]:width - margin[1]]

    def reduce(image: np.ndarray) -> np.ndarray:
        return cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], -1)

    flat = np.stack([reduce(img) for img in inner])
    h, w = flat.shape[1:3]
    clipped = np.zeros(inner.shape[1:], bool)                      # a pixel clipped in any shot, at full resolution:
    for img in inner:                                              # a block holding one is off the model
        clipped |= (img >= 0.98) | (img <= 0.0)
    chosen = reduce(clipped.astype(np.float32)) == 0.0
    if chosen.sum() < MIN_PIXELS:
        raise CalibrationError(f"too few unsaturated pixels to estimate angle errors: expected at least {MIN_PIXELS}, "
                               f"got {int(chosen.sum())}")
    data = flat[:, chosen].astype(np.float64)
    phi, iterations, unobservable = _solve_angles(data, nominal)
    errors = np.degrees(phi - nominal)
    remedy = ("the scene has too little polarized light against the noise, or its shots are not aligned. "
              "Calibrate on a scene with glare from glass or a polarizer target, from a tripod")
    if np.abs(errors).max() > MAX_SHOT_ERROR_DEG:
        raise CalibrationError(f"the images do not determine the shots' angles: the fit moves them by up to "
                               f"{np.abs(errors).max():.1f} deg (at most {MAX_SHOT_ERROR_DEG:.1f} is plausible); {remedy}")
    if n >= 5 and unobservable is not None:
        raise CalibrationError("the images do not determine every shot's angle: one combination of the errors does "
                               f"not show in them; {remedy}")
    tiles = np.arange(h)[:, None] * 8 // h * 8 + np.arange(w)[None, :] * 8 // w          # the fit is plausible: its spread
    tile_of = np.broadcast_to(tiles[..., None], chosen.shape)[chosen]
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(bootstrap):
        idx = np.concatenate([np.flatnonzero(tile_of == t) for t in rng.choice(64, 64)])
        if idx.size >= 100:
            draws.append(_solve_angles(data[:, idx], nominal)[0])
    spread = np.degrees(np.std(draws, axis=0)) if draws else np.full(n, np.nan)
    return ShotErrors(errors.tolist(), spread.tolist(), int(chosen.sum()), iterations,
                      None if unobservable is None else unobservable.tolist())
