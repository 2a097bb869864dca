"""The reference angle: the glass's s-direction φ⊥, estimated from the shots themselves.

Every polarization method (the network, Schechner, Kong, Farid) reads the shots at the
canonical angles φ⊥ and φ⊥ + 90°. The Stokes fit gives φ⊥ only up to 90°, so urd used to take
it within ±45° of the first shot's angle, which only works when the photographer starts near
φ⊥ (a mosaic camera always starts at 0°). This module finds φ⊥ from the images instead, and
`separate.presentation` re-renders any N ≥ 3 shots at it + 0/45/90°, the input every method then sees.

Physics (unpolarized layers, one pane): with ρ = (R_s+R_p)/2 and Δ = (R_s−R_p)/2,

    I_φ = [ρ·I_R + (1−ρ)·I_T]/2 + Δ·(I_R − I_T)·cos 2(φ−φ⊥)/2,

so a pixel is polarized along φ⊥ where the reflected radiance exceeds the transmitted one
(I_R > I_T) and along φ⊥ + 90° elsewhere. Its DoLP is at most Δ/ρ on the first side and at
most Δ/(1−ρ) on the second (`separate.optics.dolp_limits`): 1.0 and 0.073 at Brewster's angle,
0.38 and 0.235 at 80°. Both sides share the axis, which `estimate_reference` takes from the
DoLP-weighted axial mean of 4·AoLP (no 90° ambiguity on the axis); the side is chosen by the
bound:

* both orientations occur (``Basis.TAILS``): the one reaching the higher DoLP is the
  reflection's (Δ/ρ > Δ/(1−ρ) below ~83°). A scene's own polarization (a wooden wall's sheen,
  foliage) can reach higher still along the other orientation, so where a method is at hand
  `decide_side` checks this side as it checks an assumed one;
* one orientation, more polarized than transmitted light can be (DoLP above
  `TRANSMISSION_DOLP_MAX`; ``Basis.STRONG``): the reflection's;
* one orientation, weakly polarized (``Basis.TRANSMISSION``): ambiguous in principle (a
  transmission-dominated view at a steep angle, or a reflection-dominated one nearly head-on
  look the same). urd assumes the transmission dominates, so φ⊥ is the other orientation.
  The network, given the wrong side, ruins a clean transmission-dominated photo (T̂ 34 → 12 dB
  on synthetic scenes at 60°) but leaves a reflection-dominated one about as it was (T̂ ≈ S0).
  `polarization_warnings` says so. Where a method is at hand, `decide_side` settles the
  assumption by separating both sides (``Basis.TRIAL`` when it turns the side);
* no usable polarization (``Basis.NONE``): the first shot's angle (nothing to separate).

All statistics use the luminance reduced to at most `MAX_SIDE` px (area averaging, which
commutes with the linear Stokes fit) and box-filtered over `BLUR` px (sensor noise otherwise
gives dark pixels a random, strong polarization); pixels near saturation (any shot ≥
`SATURATION` × white), on the strongest edges (where misregistration between the shots fakes a
polarization) and with DoLP > 1 (impossible for light) are ignored.

Measured on synthetic patches (200 bsds500/val and 200 bsds500/test patches of 128², the
benchmark's pipeline, each shot at 0/45/90, 0/60/120 and 0/45/90/135° from a random first
angle): the side is right on 83% (val) and 84% (test) of the 600 stacks each, and the network's
T̂ PSNR is 0.89 / 0.94 dB below what the true φ⊥ gives. Nearly all misses (87 of 103, 86 of
98) are ``Basis.TRANSMISSION`` on reflection-dominated patches at low incidence (θ ≤ 35°),
where a visible reflection already means I_R > I_T. Lowering `TRANSMISSION_DOLP_MAX` to 0.1
would recover 0.3–0.4 dB of that on synthetic data (0.6 dB if, besides, a lighter orientation
whose tail reaches a higher DoLP were read as the reflection), but real glass polarizes
transmitted light more than the single interface of `separate.optics.dolp_limits` (a pane has
two surfaces, double glazing four): on the Lapray wine glass (one orientation, DoLP up to
0.27, transmission dominated) it turns T̂ ≈ S0 into a blotchy split with half the light in R̂.
urd keeps the conservative side; the synthetic benchmark pays for it.

Functions take stacks (N, H, W, C) float32 linear (1.0 = sensor white), or their codes
(uint16, 65535 = 1.0; `separate.optics.code_scale`), and the N polarizer angles in degrees,
urd's image-plane convention (`separate.optics`).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import enum
from typing import Callable, Sequence

import cv2
import numpy as np

from separate import metrics, optics
from separate.presentation import check_stack, field_at

#: Long side (px) of the reduced luminance used for the statistics.
MAX_SIDE = 512
#: Box filter (px, on the reduced image) against noise and misregistration.
BLUR = 5
#: Percentile (and 100 − it) taken as the robust extremes of the signed DoLP.
TAIL_PERCENT = 0.5
#: Percentage of the usable pixels kept by flatness: the rest, with the strongest edges relative to
#: S0, are where misregistration between the shots fakes a polarization.
FLAT_PERCENT = 75
#: A shot value at or above this fraction of white counts as saturated.
SATURATION = 0.98
#: DoLP that transmission-dominated light does not exceed for θ ≤ 80° at one interface (0.235), with
#: a margin for a pane's second surface up to ~70° (module docstring: why it is not lower).
TRANSMISSION_DOLP_MAX = 0.3
#: Below this ratio of the lighter to the heavier orientation's polarized mass, one orientation.
ONE_SIDED = 0.1
#: A scene whose 98th-percentile DoLP is below this shows too little polarization to separate.
WEAK_DOLP = 0.02
#: Shots whose mean absolute difference is below this fraction of their mean are "identical".
IDENTICAL = 0.002
#: Share of clipped pixels (`clipped_mask`) above which the scene is warned about.
CLIPPED_WARN = 0.01
#: Ridge weight (relative to the total evidence) pulling the reference field's polynomial
#: towards the global φ⊥: where few pixels are polarized the field stays the global estimate.
FIELD_PRIOR = 0.02
#: Pixels whose axis is further than this (deg) from the field are left out of its next fit.
FIELD_OUTLIER_DEG = 15.0
#: Fits of the reference field (each keeps the pixels within `FIELD_OUTLIER_DEG` of the previous
#: fit; the first, of the global φ⊥).
FIELD_ITERATIONS = 3
#: Long side (px) of the stack `decide_side` separates at both sides.
TRIAL_SIDE = 256
#: A ``Basis.TAILS`` side is turned to one whose trial puts more light into R̂ only where the
#: layers' mutual information falls below this fraction of the kept side's (`decide_side`).
TAILS_TURN_MI_RATIO = 0.5
#: The angles of incidence (deg) searched by `separate.incidence` and its step.
INCIDENCE_RANGE_DEG = (10.0, 80.0)
INCIDENCE_STEP_DEG = 2.0
#: The least S0 (linear) a DoLP divides by here: dark pixels give a finite ratio.
DARK = 1e-12


class Basis(enum.Enum):
    """How the side of φ⊥ (versus φ⊥ + 90°) was decided (module docstring)."""

    TAILS = "tails"
    STRONG = "strong"
    TRANSMISSION = "transmission"
    TRIAL = "trial"
    NONE = "none"


@dataclasses.dataclass(frozen=True)
class ReferenceEstimate:
    """The estimated s-direction and the evidence behind it.

    Attributes:
        reference_deg: φ⊥ (deg) in [0, 180), in the frame of the given angles.
        axis_strength: resultant length in [0, 1] of the DoLP-weighted mean of 4·AoLP; near 1
            when every polarized pixel agrees on the axis, near 0 for noise.
        basis: how the side was chosen.
        dolp_range: robust (1st, 99th percentile) signed DoLP along φ⊥ of the well-exposed
            pixels: negative where the transmission dominates, positive where the reflection does.
    """

    reference_deg: float
    axis_strength: float
    basis: Basis
    dolp_range: tuple[float, float]


def clipped_mask(images: np.ndarray, white: float = 1.0, rows: int = 512) -> np.ndarray:
    """Pixels (H×W bool) where any shot reaches `SATURATION` × white in any channel: their
    polarization is lost (a clipped shot does not follow Malus's law), so no method can separate
    them; ``rows`` rows at a time."""
    limit = SATURATION * white / optics.code_scale(images)
    out = np.zeros(images.shape[1:3], bool)

    def mark(y: int) -> None:
        block = out[y : y + rows]
        for shot in images[:, y : y + rows]:
            for k in range(shot.shape[-1]):               # per channel: 5× faster than any() over small axes
                block |= shot[..., k] >= limit

    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:     # numpy releases the GIL: 24 MP 0.2 → 0.1 s
        list(pool.map(mark, range(0, images.shape[1], rows)))
    return out


def reduce_luminance(images: np.ndarray) -> np.ndarray:
    """The stack's luminance area-averaged to at most `MAX_SIDE` px on the long side, (N, h, w)
    float64 (averaging commutes with the Stokes fit)."""
    n, h, w = images.shape[:3]
    scale = min(1.0, MAX_SIDE / max(h, w))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    lum = np.empty((n, size[1], size[0]))
    unit = optics.code_scale(images)
    for k, shot in enumerate(images):
        small = shot if shot.dtype == np.uint16 else shot.astype(np.float32, copy=False)    # cv2 takes both
        if scale < 1:
            small = cv2.resize(small, size, interpolation=cv2.INTER_AREA)
        lum[k] = small.reshape(size[1], size[0], -1).mean(axis=-1) * unit
    return lum


def _reduce_stack(images: np.ndarray, clipped: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`reduce_luminance`, and where a reduced pixel covers a clipped pixel (`clipped_mask`),
    h×w bool."""
    lum = reduce_luminance(images)
    saturated = clipped.view(np.uint8) * np.uint8(255)               # 255 keeps one pixel in 500 visible
    if lum.shape[1:] != clipped.shape:
        saturated = cv2.resize(saturated, (lum.shape[2], lum.shape[1]), interpolation=cv2.INTER_AREA)
    return lum, saturated > 0


def _statistics(images: np.ndarray, phi: np.ndarray, white: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The reduced luminance (N, h, w), its filtered Stokes images (3, h, w) float64, their
    usable pixels (h×w bool: no saturated shot nearby, S0 > 0, not among the strongest edges,
    DoLP ≤ 1) and the full-size clipped pixels (`clipped_mask`)."""
    clipped = clipped_mask(images, white)
    lum, saturated = _reduce_stack(images, clipped)
    stokes = optics.stokes_from_images(lum, phi)
    edge = np.hypot(*np.gradient(stokes[0])) / np.maximum(stokes[0], DARK)
    stokes = np.stack([cv2.blur(s, (BLUR, BLUR)) for s in stokes])
    usable = (cv2.blur(saturated.astype(np.float32), (BLUR, BLUR)) == 0) & (stokes[0] > 0)
    if usable.any():
        edge = cv2.blur(edge, (BLUR, BLUR))
        usable &= edge <= np.percentile(edge[usable], FLAT_PERCENT)
    usable &= np.hypot(stokes[1], stokes[2]) <= stokes[0]                 # DoLP > 1: not light, an artefact
    return lum, stokes, usable, clipped


def _signed_dolp(stokes: np.ndarray, phi_perp: float) -> np.ndarray:
    """Signed DoLP along ``phi_perp`` (rad): (S1 cos 2φ⊥ + S2 sin 2φ⊥)/S0."""
    return optics.rotate_stokes(stokes, phi_perp)[1] / np.maximum(stokes[0], DARK)


def estimate_reference(images: np.ndarray, angles_deg: Sequence[float], white: float = 1.0) -> ReferenceEstimate:
    """Estimate the glass's s-direction φ⊥ from a stack (module docstring).

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        white: the sensor's white level in linear units (1.0 = full scale, also for codes; for saturation).

    Returns:
        A `ReferenceEstimate`; ``reference_deg`` is in [0, 180).
    """
    phi = check_stack(images, angles_deg)
    _, stokes, usable, _ = _statistics(images, phi, white)
    return _estimate(stokes, usable, float(np.mod(np.degrees(phi[0]), 180.0)))


def _estimate(stokes: np.ndarray, usable: np.ndarray, fallback_deg: float) -> ReferenceEstimate:
    """`estimate_reference` on reduced Stokes images (3, h, w) and their usable pixels."""
    s0, s1, s2 = picked = stokes[:, usable]
    dolp = np.clip(optics.dolp(picked, floor=DARK), 0.0, 1.0)
    weight = dolp**2 * s0
    total = weight.sum()
    if s0.size == 0 or total <= 0:
        return ReferenceEstimate(fallback_deg, 0.0, Basis.NONE, (0.0, 0.0))
    unit4 = ((s1**2 - s2**2) + 2j * s1 * s2) / np.maximum(np.hypot(s1, s2), 1e-30) ** 2       # exp(4i·AoLP)
    resultant = (weight * unit4).sum() / total
    axis = float(np.angle(resultant)) / 4
    signed = _signed_dolp(picked, axis)
    lo, hi = (float(q) for q in np.percentile(signed, [TAIL_PERCENT, 100 - TAIL_PERCENT]))
    mass_pos = float((s0 * np.maximum(signed, 0) ** 2).sum())
    mass_neg = float((s0 * np.maximum(-signed, 0) ** 2).sum())
    if max(mass_pos, mass_neg) <= 0 or max(hi, -lo) < WEAK_DOLP / 2:
        return ReferenceEstimate(fallback_deg, float(abs(resultant)), Basis.NONE, (lo, hi))
    if min(mass_pos, mass_neg) >= ONE_SIDED * max(mass_pos, mass_neg):
        basis, positive = Basis.TAILS, hi >= -lo
    elif (hi if mass_pos > mass_neg else -lo) > TRANSMISSION_DOLP_MAX:
        basis, positive = Basis.STRONG, mass_pos > mass_neg
    else:
        basis, positive = Basis.TRANSMISSION, mass_pos < mass_neg
    phi_perp = axis if positive else axis + np.pi / 2
    dolp_range = (lo, hi) if positive else (-hi, -lo)
    return ReferenceEstimate(float(np.mod(np.degrees(phi_perp), 180.0)), float(abs(resultant)), basis, dolp_range)


def estimate_reference_deg(images: np.ndarray, angles_deg: Sequence[float], white: float = 1.0) -> float:
    """The estimated s-direction φ⊥ (deg, in [0, 180)) of a stack (N, H, W, C) float32 linear
    shot at ``angles_deg``; see `estimate_reference`."""
    return estimate_reference(images, angles_deg, white).reference_deg


def presence_map(images: np.ndarray, angles_deg: Sequence[float], reference_deg: float | None = None,
                 white: float = 1.0) -> np.ndarray:
    """Per-pixel share of reflected light, R_obs/S0, estimated from the polarization alone.

    With one angle of incidence θ, a pixel's signed DoLP along φ⊥, v = (I⊥ − I∥)/S0, is linear
    in its reflected share: R_obs/S0 = (v + c_T)/(c_R + c_T), c_T = Δ/(1−ρ), c_R = Δ/ρ
    (`separate.optics.dolp_limits`). θ is taken as the smallest angle whose limits cover the
    image's robust DoLP range (`feasible_theta_deg`), so the most transmission-like pixels read
    0. The map is computed on the reduced, filtered luminance (module docstring) and resized
    bilinearly, so it is smooth (and unreliable on saturated pixels). 1 means "this is all
    reflection", 0 "no reflection"; it is a confidence map, not a separation.

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        reference_deg: φ⊥ (deg); estimated when None.
        white: the sensor's white level.

    Returns:
        H×W float32 in [0, 1].
    """
    return inspect_stack(images, angles_deg, reference_deg, white).presence_at(images.shape[1:3])


def _presence(stokes: np.ndarray, usable: np.ndarray, reference_deg: float) -> np.ndarray:
    """`presence_map` on the reduced Stokes images (3, h, w): h×w float32 in [0, 1]."""
    signed = _signed_dolp(stokes, np.radians(reference_deg))
    lo, hi = (np.percentile(signed[usable], [TAIL_PERCENT, 100 - TAIL_PERCENT]) if usable.any() else (0.0, 0.0))
    theta_lo, _ = feasible_theta_deg(float(lo), float(hi))
    c_t, c_r = optics.dolp_limits(np.radians(theta_lo))
    return np.clip((signed + c_t) / (c_r + c_t), 0.0, 1.0).astype(np.float32)


def feasible_theta_deg(dolp_lo: float, dolp_hi: float, bounds_deg: tuple[float, float] = (10.0, 80.0),
                       step_deg: float = 0.25, n: float = optics.N_GLASS) -> tuple[float, float]:
    """The range of angles of incidence (deg) that explain an observed signed-DoLP range.

    Transmission-dominated pixels reach −Δ/(1−ρ) at most, reflection-dominated ones Δ/ρ
    (`separate.optics.dolp_limits`); θ is feasible when −``dolp_lo`` ≤ Δ/(1−ρ) and ``dolp_hi``
    ≤ Δ/ρ, searched within ``bounds_deg``. When no θ there is feasible (noise, misregistration
    or polarized light from the scene itself exceed the limits), the θ with the smallest
    violation is returned as a one-point range.

    Args:
        dolp_lo, dolp_hi: robust extremes of the signed DoLP along φ⊥ (negative: the
            transmission dominates).
        bounds_deg: the physically sensible search range (deg).

    Returns:
        (lo, hi) in degrees, lo ≤ hi.
    """
    if not bounds_deg[0] < bounds_deg[1]:
        raise ValueError(f"expected bounds (lo, hi) with lo < hi in degrees, got {bounds_deg}")
    grid = np.arange(bounds_deg[0], bounds_deg[1] + step_deg / 2, step_deg)
    c_t, c_r = optics.dolp_limits(np.radians(grid), n)
    violation = np.maximum(np.maximum(-dolp_lo - c_t, 0.0), np.maximum(dolp_hi - c_r, 0.0))
    feasible = violation <= 0
    if not feasible.any():
        best = float(grid[int(np.argmin(violation))])
        return best, best
    return float(grid[feasible].min()), float(grid[feasible].max())


def _field(stokes: np.ndarray, usable: np.ndarray, reference_deg: float) -> np.ndarray:
    """The reference field on reduced Stokes images (3, h, w): h×w float32 deg (docstring of
    `estimate_reference_field`)."""
    s0, s1, s2 = stokes
    h, w = s0.shape
    dolp = optics.dolp(stokes, floor=DARK)
    weight = np.where(usable, np.clip(dolp, 0.0, 1.0) ** 2 * np.maximum(s0, 0.0), 0.0).ravel()
    gap = np.mod(np.degrees(optics.aolp(stokes)) - reference_deg + 45.0, 90.0).ravel() - 45.0
    ys, xs = np.mgrid[-1.0 : 1.0 : h * 1j, -1.0 : 1.0 : w * 1j]
    terms = np.stack([np.ones(h * w), xs.ravel(), ys.ravel(), xs.ravel() ** 2, (xs * ys).ravel(), ys.ravel() ** 2], axis=1)
    total = weight.sum()
    if total <= 0:
        return np.full((h, w), reference_deg, np.float32)
    coef = np.zeros(terms.shape[1])
    for _ in range(FIELD_ITERATIONS):
        residual = np.abs(gap - terms @ coef)
        fit_weight = weight * (residual < FIELD_OUTLIER_DEG)
        normal = (terms * fit_weight[:, None]).T @ terms + FIELD_PRIOR * total * np.eye(terms.shape[1])
        coef = np.linalg.solve(normal, (terms * fit_weight[:, None]).T @ gap)
    field = reference_deg + np.clip(terms @ coef, -45.0, 45.0)
    return field.reshape(h, w).astype(np.float32)


def estimate_reference_field(images: np.ndarray, angles_deg: Sequence[float], white: float = 1.0) -> np.ndarray:
    """A smooth per-pixel s-direction φ⊥(x, y) (deg), for views in which it varies: a wide
    field of view through a flat pane (φ⊥ turns with the plane of incidence across the frame)
    or a curved pane.

    Each usable pixel's axis is taken on the branch within ±45° of the global φ⊥
    (`estimate_reference`: the side is decided once for the view), and its deviation from it is
    fitted by a quadratic in x and y (weights DoLP²·S0, a ridge of `FIELD_PRIOR` towards the
    global φ⊥, `FIELD_ITERATIONS` fits dropping pixels further than `FIELD_OUTLIER_DEG`): the
    field of a flat pane seen through a wide lens or of a gently curved one. A view with no
    usable polarization gets a constant field.

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        white: the sensor's white level (for saturation).

    Returns:
        h×w float32 φ⊥ (deg, continuous: the global φ⊥ ± 45°) on the reduced grid of at most
        `MAX_SIDE` px; `field_at` resizes it.
    """
    return inspect_stack(images, angles_deg, white=white).field


def polarization_warnings(images: np.ndarray, angles_deg: Sequence[float], white: float = 1.0) -> list[str]:
    """Scene-level warnings about a stack, each naming the likely cause.

    * two shots bitwise identical: the same file given twice;
    * all shots identical within `IDENTICAL` (mean absolute difference over mean, on the
      reduced, filtered luminance): the polarizer is not turning (or not in the light path);
    * otherwise, 98% of the pixels below DoLP `WEAK_DOLP`: too little polarization to separate
      anything (no glass in view, glass seen nearly head-on, or no polarizer);
    * a weak polarization with one orientation (`Basis.TRANSMISSION`): the side of φ⊥ is
      assumed, and the way to override it;
    * more than `CLIPPED_WARN` of the pixels clipped in some shot (`clipped_mask`).

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        white: the sensor's white level.

    Returns:
        Warnings as sentences; empty for a normal scene.
    """
    return inspect_stack(images, angles_deg, white=white).warnings


def _warnings(images: np.ndarray, angles_deg: Sequence[float], lum: np.ndarray, stokes: np.ndarray,
              usable: np.ndarray, estimate: ReferenceEstimate, clipped: np.ndarray, given: bool = False) -> list[str]:
    """`polarization_warnings` from the stack, its reduced statistics (`_statistics`) and its
    clipped pixels (`clipped_mask`); with a reference ``given``, none about the estimated one."""
    n = images.shape[0]
    warnings = []
    span = np.degrees(optics.angle_span(np.radians(angles_deg)))
    if span < optics.MIN_SPAN_DEG:
        warnings.append(f"the polarizer angles ({', '.join(f'{a:g}' for a in angles_deg)} deg) span only {span:.0f} deg: "
                        f"their Stokes fit has {optics.stokes_noise_gain(np.radians(angles_deg)):.1f}x the noise of "
                        f"0/45/90 deg; spread the shots over at least {optics.MIN_SPAN_DEG:g} deg (the network "
                        "refuses less)")
    share = float(clipped.mean())
    if share > CLIPPED_WARN:
        warnings.append(f"{100 * share:.1f}% of the pixels are clipped in at least one shot: their polarization is "
                        "lost and R and T there are guesses (marked in clipped.png); expose for the highlights")
    for i in range(n):
        for j in range(i + 1, n):
            if _identical(images[i], images[j]):
                warnings.append(f"shots {i} and {j} ({angles_deg[i]:g} and {angles_deg[j]:g} deg) are identical: "
                                "the same file given twice?")
    lum = np.stack([cv2.blur(shot, (BLUR, BLUR)) for shot in lum])
    mean = max(float(lum.mean()), 1e-12)
    spread = max(float(np.abs(lum[i] - lum[j]).mean()) / mean for i in range(n) for j in range(i + 1, n))
    if spread < IDENTICAL:
        warnings.append(f"the {n} shots are identical within {100 * spread:.2f}% although their angles differ: "
                        "the polarizer is not turning (or not in the light path); nothing can be separated")
        return warnings
    dolp = optics.dolp(stokes, floor=DARK)
    level = float(np.percentile(dolp[usable], 98)) if usable.any() else 0.0
    if level < WEAK_DOLP:
        warnings.append(f"the shots show too little polarization to separate anything (98% of pixels below DoLP "
                        f"{level:.3f}): no glass in view, glass seen nearly head-on, or no polarizer")
        return warnings
    if estimate.basis is Basis.TRANSMISSION and not given:
        other = np.mod(estimate.reference_deg + 90.0, 180.0)
        warnings.append(f"the polarization is weak and has one orientation: urd assumes the transmission dominates "
                        f"(reference {estimate.reference_deg:.1f} deg); if the reflection dominates the photo, as it "
                        f"usually does when the glass is seen within ~35 deg of head-on with a bright reflection, "
                        f"pass --reference {other:.1f}")
    return warnings


def _identical(a: np.ndarray, b: np.ndarray) -> bool:
    """True if two shots are equal, pixel for pixel (a coarse sample first, as shots of a
    turning polarizer differ: a 24 MP pair 0.08 s → well under 1 ms)."""
    return np.array_equal(a[::61, ::67], b[::61, ::67]) and np.array_equal(a, b)


@dataclasses.dataclass(frozen=True)
class Inspection:
    """What the shots say before any separation (`inspect_stack`).

    Attributes:
        estimate: the estimated s-direction (`estimate_reference`).
        reference_deg: the reference to use (deg): the given one, else the estimate's.
        warnings: `polarization_warnings`.
        presence: the reflection-presence map at the reduced size (h×w float32 in [0, 1]),
            along ``reference_deg``; `presence_at` gives it at full size.
        clipped: H×W bool, `clipped_mask`.
        field: the reference field at the reduced size (h×w float32 deg,
            `estimate_reference_field`), around ``reference_deg``; constant when a reference
            was given.
    """

    estimate: ReferenceEstimate
    reference_deg: float
    warnings: list[str]
    presence: np.ndarray
    clipped: np.ndarray
    field: np.ndarray

    def presence_at(self, shape: tuple[int, int]) -> np.ndarray:
        """The presence map resized bilinearly to ``shape`` (H, W): H×W float32 in [0, 1]."""
        h, w = shape
        return np.clip(cv2.resize(self.presence, (w, h), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)


def inspect_stack(images: np.ndarray, angles_deg: Sequence[float], reference_deg: float | None = None,
                  white: float = 1.0) -> Inspection:
    """The reference estimate, the warnings and the presence map of a stack in one pass over
    it (the three share the reduced statistics; a 24 MP stack is read once, not three times).

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        reference_deg: φ⊥ (deg) to use for the presence map; the estimate's when None.
        white: the sensor's white level.
    """
    phi = check_stack(images, angles_deg)
    if reference_deg is not None and not np.isfinite(reference_deg):
        raise ValueError(f"expected a finite reference angle (deg) or None, got {reference_deg}")
    lum, stokes, usable, clipped = _statistics(images, phi, white)
    estimate = _estimate(stokes, usable, float(np.mod(np.degrees(phi[0]), 180.0)))
    reference = estimate.reference_deg if reference_deg is None else float(reference_deg)
    if reference_deg is None and estimate.basis is not Basis.NONE:
        field = _field(stokes, usable, reference)
    else:
        field = np.full(stokes.shape[1:], reference, np.float32)
    return Inspection(estimate, reference, _warnings(images, list(angles_deg), lum, stokes, usable, estimate, clipped,
                                                     given=reference_deg is not None),
                      _presence(stokes, usable, reference), clipped, field)


def reduced_stack(images: np.ndarray, max_side: int = MAX_SIDE) -> np.ndarray:
    """The stack (N, H, W, C) area-averaged to at most ``max_side`` px on the long side, float32
    linear (averaging commutes with the Stokes fit, so the reduced shots are shots too)."""
    n, h, w, c = images.shape
    scale = min(1.0, max_side / max(h, w))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    out = np.empty((n, size[1], size[0], c), np.float32)
    for k, shot in enumerate(images):
        small = optics.to_float(shot)
        out[k] = (cv2.resize(small, size, interpolation=cv2.INTER_AREA) if scale < 1 else small).reshape(out.shape[1:])
    return out


Trial = Callable[[np.ndarray, list[float], "float | np.ndarray"], tuple[np.ndarray, np.ndarray]]


def decide_side(images: np.ndarray, angles_deg: Sequence[float], inspection: "Inspection", trial: Trial,
                use_field: bool = True) -> "Inspection":
    """Settle a side of φ⊥ that the polarization alone does not by separating both (Schechner's
    criterion, on a trial separation: a method's own, or for the network Schechner's inversion):
    where the side was only assumed (``Basis.TRANSMISSION``: weak polarization of one
    orientation) or read from the higher of two orientations' DoLP (``Basis.TAILS``), ``trial``
    separates the stack reduced to `TRIAL_SIDE` px at the reference (the field with
    ``use_field``, else the one angle) and at it + 90°, and the side whose layers share less
    mutual information wins. ``Basis.STRONG`` and ``Basis.NONE`` come back unchanged.

    Measured with the network's backbone as the trial on 48 synthetic scenes × 3 angle sets (the
    benchmark's patches): the network's T̂ was 0.78 dB below the true φ⊥ with the assumed side,
    0.40 dB with this decision; deciding every stack this way was worse (−1.1 dB), so the
    polarization's own evidence stays first where it is strong. Schechner's inversion as the
    trial decides better still (`separate.methods.network`). With it, trying ``Basis.TAILS``
    too turned 2 of the 3 wrong sides among the 10 TAILS stacks of the training-side semi-real
    scenes (3, 4 and 6 shots) and none of the 7 right ones (the shipped network's T̂ on those
    10: 26.20 → 28.39 dB); trying ``Basis.STRONG`` turned none of the 34 STRONG stacks there.
    A view without glass has no right side, and there a turn that puts more light into R̂ is
    the scene's own polarization read as a reflection (wen2019's scene61: the trial's R̂ 8% →
    27%, the mutual information 0.34 → 0.25 nats), so a TAILS side is turned towards more
    reflected light only where the mutual information falls below `TAILS_TURN_MI_RATIO` of the
    kept side's (the semi-real outdoor view turned right: 0.50 → 0.17 nats, R̂ 7% → 19%).

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes).
        angles_deg: the N polarizer angles (deg).
        inspection: the stack's `inspect_stack`.
        trial: a method's run (images, angles_deg, reference) → (R̂, T̂), reference a number or an
            h×w field (deg).

    Returns:
        ``inspection``, or one turned by 90° (estimate with ``Basis.TRIAL``, reference, field,
        presence map) with a note in its warnings.
    """
    if inspection.estimate.basis not in (Basis.TRANSMISSION, Basis.TAILS):
        return inspection
    small = reduced_stack(images, TRIAL_SIDE)
    field = field_at(inspection.field, small.shape[1:3]) if use_field else inspection.reference_deg
    scores, shares = [], []
    for turn in (0.0, 90.0):
        r_hat, t_hat = trial(small, list(angles_deg), field + turn)
        scores.append(metrics.mutual_information(t_hat.mean(axis=-1), r_hat.mean(axis=-1)))
        reflected = float(np.maximum(r_hat, 0.0).sum())
        shares.append(reflected / max(reflected + float(np.maximum(t_hat, 0.0).sum()), 1e-12))
    if scores[1] >= scores[0]:
        return inspection
    if (inspection.estimate.basis is Basis.TAILS and shares[1] > shares[0]
            and scores[1] > TAILS_TURN_MI_RATIO * scores[0]):
        return inspection
    reference = float(np.mod(inspection.reference_deg + 90.0, 180.0))
    assumed = inspection.estimate.basis is Basis.TRANSMISSION
    read = "the assumed" if assumed else "the more strongly polarized orientation's"
    note = (f"the side of the reference was decided by separating both: {reference:.1f} deg"
            f"{' (the reflection dominates)' if assumed else ''} gave layers sharing less information ({scores[1]:.3f} against {scores[0]:.3f} nats) than {read} "
            f"{inspection.reference_deg:.1f} deg; pass --reference {inspection.reference_deg:.1f} to use that side instead "
            "(one angle for the whole view)")
    warnings = [w for w in inspection.warnings if "urd assumes the transmission dominates" not in w] + [note]
    turned = inspect_stack(images, angles_deg, reference)                 # the presence map along the new side
    low, high = inspection.estimate.dolp_range
    estimate = ReferenceEstimate(reference, inspection.estimate.axis_strength, Basis.TRIAL, (-high, -low))
    return dataclasses.replace(turned, estimate=estimate, warnings=warnings,
                               field=inspection.field + np.float32(reference - inspection.reference_deg))


def resolve_reference(images: np.ndarray, angles_deg: Sequence[float], reference: str | float,
                      trial: Trial | None) -> tuple["Inspection", float | np.ndarray]:
    """The inspection of a stack and the reference to present it at, as every separation in urd
    chooses them: "auto", the estimated field (H×W deg), or the estimated angle where the stack's
    polarization is weak and of one orientation (`Basis.TRANSMISSION`: a field fitted to it
    follows the scene's own polarization, not a pane's); "global", the estimated angle; a number,
    that angle. An estimated side that was only assumed is settled by ``trial`` (`decide_side`;
    None: not settled, for methods that see S0 only).

    The one angle for `Basis.TRANSMISSION` stacks was chosen on the training-side semi-real
    scenes (`separate.semireal`, the network's T̂, field → one angle for those stacks): faint
    reflections 26.37 → 27.52 dB, every other condition within ±0.15 dB, the no-glass R̂ share
    14.3 → 14.2%; on the held-out scenes 3 shots 26.92 → 27.01, faint 27.01 → 27.07, the rest
    within ±0.02 dB.

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes).
        angles_deg: the N polarizer angles (deg).
        reference: "auto", "global" or degrees.
        trial: a method's silent run, (images, angles_deg, reference) → (R̂, T̂), or None.

    Returns:
        (inspection, reference): the `Inspection` and the reference (deg, a number or an H×W field).
    """
    estimated = reference in ("auto", "global")
    if isinstance(reference, str) and not estimated:
        raise ValueError(f"expected reference 'auto', 'global' or an angle in degrees, got {reference!r}")
    inspection = inspect_stack(images, angles_deg, None if estimated else float(reference))
    use_field = reference == "auto" and inspection.estimate.basis is not Basis.TRANSMISSION
    if estimated and trial is not None:
        inspection = decide_side(images, angles_deg, inspection, trial, use_field=use_field)
    if use_field:
        return inspection, field_at(inspection.field, images.shape[1:3])
    return inspection, inspection.reference_deg
