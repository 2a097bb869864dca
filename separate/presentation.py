"""Presenting shots to a separation method: a stack of N ≥ 3 polarizer shots re-rendered at a
reference φ⊥ + 0/45/90° from its least-squares Stokes fit (`present`), or at a per-pixel
reference field (`present_field`), the input every polarization method in urd sees; and the
check of a stack and its angles that every function on stacks starts with (`check_stack`).

Exact for the ideal linear-polarizer model I_φ = (S0 + S1 cos 2φ + S2 sin 2φ)/2 and it uses
every shot: with N > 3 the fit averages their noise. The reference itself is estimated by
`separate.reference`. Stacks are (N, H, W, C) float32 linear (1.0 = sensor white), or their
codes (uint16, 65535 = 1.0; `separate.optics.code_scale`); angles are degrees in urd's
image-plane convention (`separate.optics`).
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from separate import optics


def check_stack(images: np.ndarray, angles_deg: Sequence[float]) -> np.ndarray:
    """Validate a stack and its angles; return the angles in radians (float64).

    Raises TypeError unless ``images`` is a numpy array, ValueError unless it is (N, H, W, C)
    with N ≥ 3 and C 1 or 3, one angle per shot, angles that determine S0, S1, S2, and finite values.
    """
    if not isinstance(images, np.ndarray):
        raise TypeError(f"expected images as a numpy array, got {type(images).__name__}")
    optics.code_scale(images)
    if images.ndim != 4 or images.shape[0] < 3 or images.shape[3] not in (1, 3):
        raise ValueError(f"expected a stack of shape (N>=3, H, W, C) with C = 1 or 3 channels (grey or RGB, "
                         f"channels last), got {images.shape}")
    short, long = sorted(images.shape[1:3])
    if short < 2 or long > 128 * short:                # the side trial's frame, reduced to 256 px, keeps 2 px
        raise ValueError(f"expected images of at least 2 px on a side, at most 128 times as long as wide, "
                         f"got {images.shape[2]}×{images.shape[1]}")
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.ndim != 1 or angles.size != images.shape[0]:
        raise ValueError(f"expected {images.shape[0]} angles (one per shot), got {np.asarray(angles_deg).tolist()}")
    phi = optics.check_angles(np.radians(angles))
    if images.dtype.kind == "f" and not np.isfinite(images.sum(dtype=np.float64)):
        raise ValueError("expected finite pixel values, got NaN or infinite values")
    return phi


def check_rows(rows: int) -> None:
    """TypeError unless ``rows`` (the image rows processed at a time) is a whole number, ValueError
    unless it is at least 1."""
    if isinstance(rows, bool) or not isinstance(rows, (int, np.integer)):
        raise TypeError(f"expected rows a whole number of at least 1, got {rows!r}")
    if rows < 1:
        raise ValueError(f"expected rows a whole number of at least 1, got {rows!r}")


def presented_angles_deg(reference_deg: float) -> list[float]:
    """The angles (deg) `present` renders at: reference + 0/45/90°, reference taken mod 180."""
    ref = float(np.mod(reference_deg, 180.0))
    return [ref + offset for offset in optics.PAPER_ANGLES_DEG]


def presenting_matrix(angles_deg: Sequence[float], reference_deg: float) -> np.ndarray:
    """The 3×N float32 matrix that re-renders N shots at ``angles_deg`` (deg) as shots at
    reference + 0/45/90°: A(φ3) · pinv(A(φ)), the least-squares Stokes fit then the rendering
    (A = `separate.optics.stokes_matrix`). Applied to linear values by `present` and, a tile
    at a time, by `separate.infer.separate_stack`."""
    phi = np.radians(np.asarray(angles_deg, np.float64))
    phi3 = np.radians(presented_angles_deg(reference_deg))
    return (optics.stokes_matrix(phi3) @ optics.stokes_fit(phi)).astype(np.float32)


def present(images: np.ndarray, angles_deg: Sequence[float], reference_deg: float,
            rows: int = 256) -> tuple[np.ndarray, list[float]]:
    """Re-render a stack at reference + 0/45/90° from its least-squares Stokes fit.

    Exact for the ideal linear-polarizer model (I_φ = (S0 + S1 cos 2φ + S2 sin 2φ)/2) and it
    uses every shot: with N > 3 the fit averages their noise. The fit (as
    `separate.optics.stokes_from_images`) and the rendering are applied as one 3×N matrix. A stack already at those angles
    (three float32 shots, equal modulo 180°) is returned as it is, not copied.

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        reference_deg: the reference φ⊥ (deg), usually `estimate_reference_deg`.
        rows: image rows processed at a time (bounds the temporary memory).

    Returns:
        (images3, angles3_deg): (3, H, W, C) float32 shots and their angles, reference (mod
        180°) + 0/45/90°. Noisy input can give slightly negative values.
    """
    phi = check_stack(images, angles_deg)
    check_rows(rows)
    if not np.isfinite(reference_deg):
        raise ValueError(f"expected a finite reference angle (deg), got {reference_deg}")
    angles3 = presented_angles_deg(reference_deg)
    if images.shape[0] == 3 and images.dtype == np.float32:
        if np.all(np.abs(optics.axis_gap_deg(np.degrees(phi), angles3)) < 1e-9):
            return images, angles3
    mixing = presenting_matrix(angles_deg, reference_deg)
    out = np.empty((3,) + images.shape[1:], np.float32)
    for y in range(0, images.shape[1], rows):
        out[:, y : y + rows] = np.tensordot(mixing, optics.to_float(images[:, y : y + rows]), axes=1)
    return out, angles3


def field_at(field_deg: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A reference field (h×w deg, `estimate_reference_field`) resized bilinearly to ``shape``
    (H, W): H×W float32 deg. The field is continuous (no 180° wrap), so interpolating it is exact."""
    h, w = shape
    return cv2.resize(np.asarray(field_deg, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)


def present_field(images: np.ndarray, angles_deg: Sequence[float], field_deg: np.ndarray,
                  rows: int = 256) -> tuple[np.ndarray, list[float]]:
    """Re-render a stack at φ(x, y) + 0/45/90° for a per-pixel reference ``field_deg`` (H×W deg,
    `field_at`): `present` with a reference that varies over the image. The shots come back in
    each pixel's own frame, so their angles are 0/45/90° and every method reads φ⊥ there.

    Args:
        images: (N, H, W, C) linear shots (float, or uint16 codes), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        field_deg: H×W reference (deg).
        rows: image rows processed at a time.

    Returns:
        (images3, [0, 45, 90]): (3, H, W, C) float32.
    """
    phi = check_stack(images, angles_deg)
    check_rows(rows)
    field_deg = np.asarray(field_deg, np.float32)
    if field_deg.shape != images.shape[1:3]:
        raise ValueError(f"expected a reference field of shape {images.shape[1:3]}, got {field_deg.shape}")
    if not np.isfinite(field_deg).all():
        raise ValueError(f"expected a finite reference field, got {int((~np.isfinite(field_deg)).sum())} non-finite values")
    pinv = optics.stokes_fit(phi).astype(np.float32)
    out = np.empty((3,) + images.shape[1:], np.float32)
    for y in range(0, images.shape[1], rows):
        stokes = np.tensordot(pinv, optics.to_float(images[:, y : y + rows]), axes=1)
        local = optics.rotate_stokes(stokes, np.radians(field_deg[y : y + rows])[..., None])
        for k, offset in enumerate(np.radians(optics.PAPER_ANGLES_DEG)):
            out[k, y : y + rows] = optics.intensity_from_stokes(local, offset)
    return out, list(optics.PAPER_ANGLES_DEG)
