"""Polarization maps of a stack, for export: Stokes S0, S1, S2, DoLP, AoLP, the reference φ⊥ and
the angle of incidence θ.

Every map is H×W float32 on the luminance (the mean of the colour channels) except S0, S1 and S2,
which keep the colour channels (H×W×C). Angles are degrees in urd's image-plane convention
(`separate.optics`: from the +x axis, counter-clockwise as the viewer sees the image): AoLP in
[0, 180), φ⊥ the reference field (`separate.reference.estimate_reference_field`, continuous, so
it may leave [0, 180)), θ the per-pixel estimate of `separate.incidence.estimate_incidence` (NaN where it is not trusted)
(a plane fitted to block estimates: it turns across a wide view of a flat pane). DoLP keeps to
[0, 1]; where S0 is within the sensor's noise (luminance below `DARK_S0`) DoLP and AoLP have no
meaning and are NaN. `MAPS` gives each map's unit and meaning; the exporter writes them into the
files' metadata.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from separate import optics
from separate.incidence import estimate_incidence
from separate.presentation import check_rows, check_stack, field_at

#: S0 of the luminance (linear, 1.0 = a shot's white level) below which a pixel is dark: its
#: polarization is within the noise (1 % of white: at the 1-2 codes of noise of an 8-bit reading a
#: DoLP error of ±0.5), and DoLP and AoLP are NaN there.
DARK_S0 = 0.01

#: name → (unit, meaning) of each map `polarization_maps` returns.
MAPS = {
    "S0": ("linear (1.0 = sensor white)", "Stokes S0: total intensity, the image without a polarizer"),
    "S1": ("linear (1.0 = sensor white)", "Stokes S1: linear polarization along 0 deg minus along 90 deg"),
    "S2": ("linear (1.0 = sensor white)", "Stokes S2: linear polarization along 45 deg minus along 135 deg"),
    "DoLP": ("1 (0 = unpolarized, 1 = fully polarized)",
             f"degree of linear polarization of the luminance, in [0, 1]; NaN where S0 < {DARK_S0} (dark: within the noise)"),
    "AoLP": ("deg in [0, 180), from +x, counter-clockwise",
             f"angle of linear polarization of the luminance; NaN where S0 < {DARK_S0} (dark: within the noise)"),
    "phi_perp": ("deg, from +x, counter-clockwise", "reference s-direction of the glass used for separation"),
    "theta": ("deg", "estimated angle of incidence on the glass, per pixel (a plane fitted over the frame); NaN "
                     "everywhere when the shots do not tell it (fewer than 3 blocks of the frame give an angle)"),
}


def polarization_maps(images: np.ndarray, angles_deg: Sequence[float], reference_deg: float | np.ndarray,
                      rows: int = 256) -> dict[str, np.ndarray]:
    """The maps of `MAPS` for a stack.

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        reference_deg: φ⊥ (deg), one angle or a field (any h×w, resized to H×W).
        rows: image rows processed at a time.

    Returns:
        name → float32 array: S0, S1, S2 H×W×C; the others H×W; DoLP in [0, 1] and AoLP in
        [0, 180), both NaN where the luminance's S0 < `DARK_S0`.

    Raises TypeError or ValueError for a stack `check_stack` refuses, a ``reference_deg`` that is
    not a number or an h×w array of numbers, or one that is not finite.
    """
    phi = check_stack(images, angles_deg)
    check_rows(rows)
    reference = check_reference(reference_deg)
    n, h, w, c = images.shape
    pinv = optics.stokes_fit(phi).astype(np.float32)
    stokes = np.empty((3, h, w, c), np.float32)
    for y in range(0, h, rows):
        stokes[:, y : y + rows] = np.tensordot(pinv, optics.to_float(images[:, y : y + rows]), axes=1)
    lum = stokes.mean(axis=-1)
    field = field_at(reference, (h, w)) if reference.ndim == 2 else np.full((h, w), float(reference), np.float32)
    incidence = estimate_incidence(images, angles_deg, reference_deg)
    theta = field_at(incidence.field_deg, (h, w))
    if incidence.clarity == 0.0:                              # too few blocks tell an angle: no estimate to show
        theta = np.full((h, w), np.nan, np.float32)
    aolp = np.mod(np.degrees(optics.aolp(lum.astype(np.float64))), 180.0).astype(np.float32)
    aolp[aolp >= 180.0] = 0.0                                 # float32 rounding of values just below 180
    dark = lum[0] < DARK_S0
    dolp = np.clip(optics.dolp(lum), 0.0, 1.0).astype(np.float32)
    dolp[dark] = np.nan
    aolp[dark] = np.nan
    return {
        "S0": stokes[0], "S1": stokes[1], "S2": stokes[2],
        "DoLP": dolp,
        "AoLP": aolp,
        "phi_perp": field,
        "theta": theta,
    }


def check_reference(reference_deg: float | np.ndarray) -> np.ndarray:
    """φ⊥ (deg) as float32: one angle, or an h×w field. TypeError unless it is a real number or an
    array of them, ValueError unless it has 0 or 2 dimensions (none of them empty) and finite values."""
    reference = np.asarray(reference_deg)
    if reference.dtype.kind not in "iuf":
        raise TypeError(f"expected reference_deg a number or an array of numbers (deg), got {reference.dtype}")
    if reference.ndim not in (0, 2) or 0 in reference.shape:
        raise ValueError(f"expected reference_deg one angle or an h×w field (deg), got shape {reference.shape}")
    if not np.isfinite(reference).all():
        raise ValueError("expected reference_deg finite (deg), got NaN or infinite values")
    return reference.astype(np.float32)
