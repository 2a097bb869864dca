"""The angle of incidence on the glass, estimated from the shots: the Fresnel inversion
(`separate.optics.mixture_inverse`) that leaves the recovered layers the least mutual
information (Schechner et al. 2000), as one number for the view (`estimate_incidence_deg`) or
per pixel, a plane across the frame fitted to blocks (`estimate_incidence`), with how far the
estimate can be trusted (`Incidence.clear`). The reference φ⊥ it reads the shots at comes from
`separate.reference`; the angles searched are `separate.reference.INCIDENCE_RANGE_DEG`.

Functions take stacks (N, H, W, C) float32 linear (1.0 = sensor white), or their codes
(uint16, 65535 = 1.0; `separate.optics.code_scale`), and the N polarizer angles in degrees,
urd's image-plane convention (`separate.optics`).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import cv2
import numpy as np

from separate import metrics, optics
from separate.presentation import check_stack, field_at
from separate.reference import INCIDENCE_RANGE_DEG, INCIDENCE_STEP_DEG, MAX_SIDE, reduce_luminance


def estimate_incidence_deg(images: np.ndarray, angles_deg: Sequence[float], reference: float | np.ndarray,
                           grid_deg: np.ndarray | None = None) -> float:
    """The angle of incidence (deg) whose Fresnel inversion (`separate.optics.mixture_inverse`)
    leaves the least mutual information between the recovered layers (Schechner et al. 2000),
    on the luminance reduced to at most `MAX_SIDE` px; Brewster's angle when the minimum lies on
    the grid's first or last point (a degenerate mixture, `separate.baselines.schechner`).

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        reference: φ⊥ (deg), a number or an H×W field.
        grid_deg: the angles searched (deg, ascending, ≥ 3); default `INCIDENCE_RANGE_DEG` in
            steps of `INCIDENCE_STEP_DEG`.
    """
    if grid_deg is None:
        grid_deg = np.arange(INCIDENCE_RANGE_DEG[0], INCIDENCE_RANGE_DEG[1] + INCIDENCE_STEP_DEG / 2, INCIDENCE_STEP_DEG)
    i_perp, i_par = _canonical_luminances(images, angles_deg, reference, MAX_SIDE)
    return float(np.degrees(incidence_by_information(i_perp, i_par, grid_deg)))


def _canonical_luminances(images: np.ndarray, angles_deg: Sequence[float], reference: float | np.ndarray,
                          side: int) -> tuple[np.ndarray, np.ndarray]:
    """I⊥, I∥ (h×w float64) of the stack's luminance at the reference (deg, a number or an H×W
    field), area-averaged to at most ``side`` px on the long side (≤ `MAX_SIDE`)."""
    phi = check_stack(images, angles_deg)
    lum = reduce_luminance(images)
    scale = min(1.0, side / max(lum.shape[1:]))
    if scale < 1:
        size = (max(1, round(lum.shape[2] * scale)), max(1, round(lum.shape[1] * scale)))
        lum = np.stack([cv2.resize(shot, size, interpolation=cv2.INTER_AREA) for shot in lum])
    reference = field_at(reference, lum.shape[1:]) if np.ndim(reference) == 2 else np.float64(reference)
    stokes = optics.rotate_stokes(optics.stokes_from_images(lum, phi), np.radians(reference))
    return optics.canonical_intensities(stokes, 0.0)


#: Long side (px) of the reduced image on which `estimate_incidence_field` runs, and its blocks per side.
INCIDENCE_FIELD_SIDE = 256
INCIDENCE_BLOCKS = 4
#: Residual scale (deg) of the robust plane fit of the blocks' angles of incidence.
INCIDENCE_FIT_SCALE_DEG = 6.0


#: Median block clarity below which an angle-of-incidence estimate is not trusted (`Incidence`):
#: chosen on 64 bsds500/val patches of 256² (the synthetic benchmark's pipeline), where the
#: estimates at or above it were off by a median 3.1° and those below by 25°.
INCIDENCE_CLARITY_MIN = 0.3
#: Median block sharpness below which it is not trusted either, and how far (deg) on either side
#: of a block's least mutual information sharpness looks. Where the Fresnel model holds (one
#: flat pane, registered shots) the mutual information dips sharply at the true angle, as the
#: inversion cancels one layer from the other exactly; a broad bowl instead (misregistration, a
#: pane curved within the block, a layer without texture) has its least value pulled towards
#: Brewster's angle, by 10–20° on panes seen at 70–80°. Chosen on 300 bsds500/val patches of 256²
#: at the true φ⊥: with both thresholds the shipped network's T̂ gained 0.14 ± 0.09 dB over the
#: clarity threshold alone, half of what the true θ field gains.
INCIDENCE_SHARPNESS_MIN = 0.05
INCIDENCE_SHARPNESS_SPAN_DEG = 6.0


@dataclasses.dataclass
class Incidence:
    """An angle-of-incidence estimate (`estimate_incidence`): ``field_deg`` h×w float32 (deg,
    at most `INCIDENCE_FIELD_SIDE` px on the long side; `separate.presentation.field_at` brings
    it to full size), ``clarity``, the median over the blocks of how far the least mutual
    information stands below the median over the angles (0: no angle stands out), and
    ``sharpness``, the median over the blocks of how far it stands below the mean of its values
    `INCIDENCE_SHARPNESS_SPAN_DEG` to either side, both relative to the median over the angles."""

    field_deg: np.ndarray
    clarity: float
    sharpness: float

    @property
    def clear(self) -> bool:
        """Whether the estimate can be trusted (clarity ≥ `INCIDENCE_CLARITY_MIN` and sharpness ≥
        `INCIDENCE_SHARPNESS_MIN`)."""
        return self.clarity >= INCIDENCE_CLARITY_MIN and self.sharpness >= INCIDENCE_SHARPNESS_MIN

    def record(self) -> dict:
        """The estimate for a manifest: the field's median and range (deg), clarity, sharpness
        and whether a physics-anchored network uses it (its Fresnel gate on)."""
        return {"median_deg": round(float(np.median(self.field_deg)), 1),
                "range_deg": [round(float(self.field_deg.min()), 1), round(float(self.field_deg.max()), 1)],
                "clarity": round(self.clarity, 3), "sharpness": round(self.sharpness, 3), "gate": self.clear}


def estimate_incidence_field(images: np.ndarray, angles_deg: Sequence[float], reference: float | np.ndarray) -> np.ndarray:
    """The angle of incidence per pixel (deg, h×w float32): `estimate_incidence`'s field."""
    return estimate_incidence(images, angles_deg, reference).field_deg


def estimate_incidence(images: np.ndarray, angles_deg: Sequence[float], reference: float | np.ndarray) -> Incidence:
    """The angle of incidence per pixel and how clear the estimate is (`Incidence`).

    The frame's canonical luminances at the reference are cut into `INCIDENCE_BLOCKS`² blocks; in
    each, the angle whose Fresnel inversion leaves the layers the least mutual information
    (`information_by_incidence`), weighted by how clearly it stands out; then a plane
    θ = a + b·x + c·y fitted to them with Tukey's biweight from two starts
    (`robust_plane`), held in `INCIDENCE_RANGE_DEG`. A flat pane seen through a lens has θ
    turning smoothly across the frame (by ~30° for a 60° field of view); a plane is the lowest
    order that says so, and a single block's poor estimate (little texture, one layer dark) does
    not bend it.

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        reference: φ⊥ (deg), a number or an H×W field.
    """
    i_perp, i_par = _canonical_luminances(images, angles_deg, reference, INCIDENCE_FIELD_SIDE)
    h, w = i_perp.shape
    grid_deg = np.arange(INCIDENCE_RANGE_DEG[0], INCIDENCE_RANGE_DEG[1] + INCIDENCE_STEP_DEG / 2, INCIDENCE_STEP_DEG)
    span = max(1, round(INCIDENCE_SHARPNESS_SPAN_DEG / INCIDENCE_STEP_DEG))
    points, clarities, sharpnesses = [], [], []
    for by in range(INCIDENCE_BLOCKS):
        for bx in range(INCIDENCE_BLOCKS):
            rows = slice(by * h // INCIDENCE_BLOCKS, (by + 1) * h // INCIDENCE_BLOCKS)
            cols = slice(bx * w // INCIDENCE_BLOCKS, (bx + 1) * w // INCIDENCE_BLOCKS)
            if min(i_perp[rows, cols].shape) < 8:
                continue
            scores = information_by_incidence(i_perp[rows, cols], i_par[rows, cols], grid_deg)
            best = int(np.argmin(scores))
            median = float(np.median(scores))
            clarity = (median - float(scores[best])) / max(median, 1e-9)
            sides = (scores[max(best - span, 0)] + scores[min(best + span, grid_deg.size - 1)]) / 2
            clarities.append(clarity)
            sharpnesses.append(float(sides - scores[best]) / max(median, 1e-9))
            if 0 < best < grid_deg.size - 1 and clarity > 0:
                points.append(((bx + 0.5) / INCIDENCE_BLOCKS - 0.5, (by + 0.5) / INCIDENCE_BLOCKS - 0.5, grid_deg[best], clarity))
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    xs, ys = (xs + 0.5) / w - 0.5, (ys + 0.5) / h - 0.5
    if len(points) < 3:                      # too few blocks tell an angle: one number, not trusted
        flat = np.degrees(incidence_by_information(i_perp, i_par, grid_deg))
        return Incidence(np.full((h, w), flat, np.float32), 0.0, 0.0)
    coef = robust_plane(*np.array(points).T)
    plane = _plane(coef, xs, ys)
    return Incidence(np.clip(plane, *INCIDENCE_RANGE_DEG).astype(np.float32), float(np.median(clarities)),
                     float(np.median(sharpnesses)))


def robust_plane(x: np.ndarray, y: np.ndarray, theta: np.ndarray, clarity: np.ndarray) -> np.ndarray:
    """The plane θ = a + b·x + c·y through block estimates, by Tukey's biweight
    (`INCIDENCE_FIT_SCALE_DEG`). The biweight has local minima, so it starts twice: from the
    clarity-weighted least-squares plane, which follows a steep slope (θ turns by ~30° across a
    wide view of a pane) but is pulled by clear outliers (blocks where the texture fakes a
    minimum), and from the clarity-weighted (lower) median, flat, which they do not pull; the fit
    with the lower biweight loss wins. A start whose iterations ever keep fewer than 3 blocks
    within the scale is dropped; where both are, the median, flat.

    Args:
        x, y: (n,) block centres, fractions of the frame from its centre (in [−0.5, 0.5]), n ≥ 1.
        theta: (n,) the blocks' angles of incidence (deg).
        clarity: (n,) their weights (> 0).

    Returns:
        (3,) the coefficients (a, b, c) (deg, deg per frame width / height).
    """
    order = np.argsort(theta)
    cumulative = np.cumsum(clarity[order])
    median = np.array([float(theta[order][np.searchsorted(cumulative, cumulative[-1] / 2)]), 0.0, 0.0])
    fits = [fit for fit in (_biweight(x, y, theta, clarity, start) for start in (_plane_fit(x, y, theta, clarity), median))
            if fit is not None]
    return min(fits, key=lambda fit: fit[1])[0] if fits else median


def _biweight(x: np.ndarray, y: np.ndarray, theta: np.ndarray, clarity: np.ndarray,
              start: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Tukey's biweight plane (`robust_plane`) iterated from ``start`` and its loss
    Σ clarity·ρ(residual / `INCIDENCE_FIT_SCALE_DEG`); None where fewer than 3 blocks keep a weight."""
    coef = start
    for _ in range(10):
        u = (theta - _plane(coef, x, y)) / INCIDENCE_FIT_SCALE_DEG
        weights = clarity * np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        if np.count_nonzero(weights) < 3:
            return None
        coef = _plane_fit(x, y, theta, weights)
    u = (theta - _plane(coef, x, y)) / INCIDENCE_FIT_SCALE_DEG
    return coef, float(np.sum(clarity * np.where(np.abs(u) < 1, 1 - (1 - u**2) ** 3, 1.0)))


def _plane(coef: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """θ = a + b·x + c·y (deg) of the coefficients (a, b, c) at positions x, y (frame fractions)."""
    return coef[0] + coef[1] * x + coef[2] * y


def _plane_fit(x: np.ndarray, y: np.ndarray, theta: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted least-squares (a, b, c) of θ = a + b·x + c·y; a slope the weighted points do not
    pin down (all in one column, or one row) is 0 rather than the minimum-norm answer's guess."""
    used = weights > 0
    columns = [np.ones_like(x)] + [v if np.ptp(v[used]) > 0 else np.zeros_like(v) for v in (x, y)] if used.any() \
        else [np.ones_like(x), np.zeros_like(x), np.zeros_like(y)]
    keep = [k for k, col in enumerate(columns) if col.any()]
    design = np.stack([columns[k] for k in keep], axis=1) * np.sqrt(weights)[:, None]
    coef = np.zeros(3)
    coef[keep] = np.linalg.lstsq(design, theta * np.sqrt(weights), rcond=None)[0]
    return coef


def information_by_incidence(i_perp: np.ndarray, i_par: np.ndarray, grid_deg: np.ndarray, chunk: int = 16) -> np.ndarray:
    """The mutual information (nats) of the layers that canonical luminances I⊥, I∥ (h×w) invert
    to at each angle of incidence of ``grid_deg`` (deg); at most ~256 px per side are used, and
    ``chunk`` angles are scored at a time (`separate.metrics.mutual_information_rows`)."""
    small = (slice(None, None, max(1, i_perp.shape[0] // 256)), slice(None, None, max(1, i_perp.shape[1] // 256)))
    i_perp, i_par = np.asarray(i_perp[small], np.float64).ravel(), np.asarray(i_par[small], np.float64).ravel()
    thetas = np.radians(np.asarray(grid_deg, np.float64))
    s0 = i_perp + i_par
    scores = []
    for start in range(0, thetas.size, chunk):
        r_s, r_p = optics.fresnel_reflectance(thetas[start : start + chunk, None])
        r_obs, _ = optics.mixture_inverse(i_perp, i_par, r_s, r_p)            # (chunk, n): R_obs at each angle
        scores.extend(metrics.mutual_information_rows(r_obs, s0 - r_obs))     # T_obs = S0 − R_obs, as mixture_inverse has it
    return np.array(scores)


def incidence_by_information(i_perp: np.ndarray, i_par: np.ndarray, grid_deg: np.ndarray) -> float:
    """The angle of incidence (rad) over ``grid_deg`` (deg, ascending, ≥ 3) minimizing the mutual
    information of the layers that canonical luminances I⊥, I∥ (h×w) invert to
    (`information_by_incidence`); Brewster's angle if the minimum is on the grid's first or last point."""
    grid_deg = np.asarray(grid_deg, dtype=np.float64)
    if grid_deg.ndim != 1 or grid_deg.size < 3:
        raise ValueError(f"expected a grid of at least 3 angles (deg), got {grid_deg.tolist()}")
    best = int(np.argmin(information_by_incidence(i_perp, i_par, grid_deg)))
    if best in (0, grid_deg.size - 1):
        return optics.brewster_angle()
    return float(np.radians(grid_deg[best]))
