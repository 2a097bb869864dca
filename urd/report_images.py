"""The images of the HTML report (`urd.report_html`): pure array functions and the JPEG views.

Colour maps (viridis), AoLP as hue, the S0/DoLP/AoLP maps of aligned shots computed with
`separate.optics`, the per-scene display gain, and the full-resolution, thumbnail and medium
JPEG views written for the page.

Display: linear values are multiplied by one gain k per scene, k = 1 / (99.5th percentile of
S0), shots by 2k (a shot records (S0 + S1 cos 2φ + S2 sin 2φ)/2, so 2·I_φ is on S0's scale);
then sRGB-encoded (IEC 61966-2-1) and clipped to [0, 1].
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from separate.maps import MAPS
from separate.optics import aolp, dolp, stokes_from_images
from urd.core.errors import DatasetError

#: Percentile of S0 mapped to white (per scene).
EXPOSURE_PERCENTILE = 99.5
#: DoLP at which the AoLP map reaches full saturation.
AOLP_FULL_SATURATION_DOLP = 0.3
#: JPEG quality of full-resolution views and of thumbnails.
JPEG_QUALITY_FULL, JPEG_QUALITY_THUMB = 95, 90


# ---------------------------------------------------------------------------------------------
# Pure image functions


def colormap_image(values: np.ndarray) -> np.ndarray:
    """H×W values in [0, 1] (clipped) → H×W×3 uint8 RGB through the viridis colormap."""
    codes = np.round(np.clip(np.nan_to_num(np.asarray(values, np.float32)), 0.0, 1.0) * 255.0).astype(np.uint8)
    return cv2.applyColorMap(codes, cv2.COLORMAP_VIRIDIS)[..., ::-1].copy()


def hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Hue in turns [0, 1), saturation and value in [0, 1] (arrays of one shape) → (..., 3) float32 RGB."""
    h6 = np.mod(np.asarray(h, np.float32), 1.0) * 6.0
    sector = np.floor(h6).astype(np.int64) % 6
    f = h6 - np.floor(h6)
    s, v = np.asarray(s, np.float32), np.asarray(v, np.float32)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    r = np.choose(sector, [v, q, p, p, t, v])
    g = np.choose(sector, [t, v, v, q, p, p])
    b = np.choose(sector, [p, p, t, v, v, q])
    return np.stack([r, g, b], axis=-1).astype(np.float32)


def aolp_image(aolp_rad: np.ndarray, dolp_map: np.ndarray, value: np.ndarray) -> np.ndarray:
    """AoLP as hue: H×W maps → H×W×3 uint8 RGB.

    Hue = AoLP over 0..180° (0° red, 60° green, 120° blue); saturation = DoLP /
    `AOLP_FULL_SATURATION_DOLP` (clipped); value = ``value`` in [0, 1] (the displayed S0).
    """
    hue = np.mod(np.asarray(aolp_rad, np.float64), np.pi) / np.pi
    sat = np.clip(np.nan_to_num(np.asarray(dolp_map, np.float32)) / AOLP_FULL_SATURATION_DOLP, 0.0, 1.0)
    rgb = hsv_to_rgb(hue, sat, np.clip(value, 0.0, 1.0))
    return np.round(rgb * 255.0).astype(np.uint8)


def polarization_maps(shots: Sequence[tuple[float, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S0 (H×W×C), DoLP (H×W) and AoLP (H×W, rad) of aligned shots, by `separate.optics`.

    DoLP and AoLP are those of the Stokes vector summed over the colour channels (the light's
    total polarization). Raises ValueError when the angles do not determine a Stokes fit.
    """
    angles = np.radians([float(a) for a, _ in shots])
    stack = np.stack([as_hwc(image) for _, image in shots]).astype(np.float32)
    stokes = stokes_from_images(stack, angles)                      # (3, H, W, C)
    total = stokes.sum(axis=-1)                                     # (3, H, W)
    return stokes[0], np.clip(dolp(total), 0.0, 1.0), aolp(total)


def as_hwc(image: np.ndarray) -> np.ndarray:
    """An H×W image as H×W×1; an H×W×C image as it is."""
    image = np.asarray(image)
    return image[..., None] if image.ndim == 2 else image


def exposure_gain(s0: np.ndarray) -> float:
    """k = 1 / (EXPOSURE_PERCENTILE-th percentile of S0), 1 when that is not positive."""
    p = float(np.percentile(np.nan_to_num(s0), EXPOSURE_PERCENTILE)) if s0.size else 0.0
    return 1.0 / p if math.isfinite(p) and p > 1e-12 else 1.0


def field_image(field_deg: np.ndarray) -> tuple[np.ndarray, float, float]:
    """A reference field (deg) as a viridis image over its own range, and that range (deg)."""
    lo, hi = float(np.min(field_deg)), float(np.max(field_deg))
    span = hi - lo if hi - lo > 1e-6 else 1.0
    return colormap_image((np.asarray(field_deg, np.float32) - lo) / span), lo, hi


def map_preview(name: str, values: np.ndarray) -> tuple[np.ndarray, str]:
    """A polarization map (`separate.maps.MAPS`: H×W, or H×W×C averaged over C) as H×W×3 uint8
    RGB, and the range it spans in the map's units: AoLP as hue over [0, 180) deg (cyclic, as
    `aolp_image`: 0° and 180° are both red); the others in viridis, DoLP over [0, 1], S1 and S2
    over ±their 99.5th percentile of |value|, S0 over [0, its 99.5th percentile], φ⊥ and θ over
    their own range. NaN (dark pixels) is black. ValueError for values of another shape."""
    values = np.asarray(values, np.float32)
    if values.ndim not in (2, 3) or 0 in values.shape:
        raise ValueError(f"{name}: expected an H×W or H×W×C map, got shape {values.shape}")
    values = values.mean(axis=-1) if values.ndim == 3 else values
    if name == "AoLP":
        full = np.ones_like(values)
        rgb = np.round(hsv_to_rgb(np.nan_to_num(values) / 180.0, full, full) * 255.0).astype(np.uint8)
        rgb[~np.isfinite(values)] = 0
        return rgb, "0 to 180 deg as hue, cyclic"
    finite = values[np.isfinite(values)]
    if name == "DoLP":
        lo, hi = 0.0, 1.0
    elif name in ("S1", "S2"):
        hi = float(np.percentile(np.abs(finite), EXPOSURE_PERCENTILE)) if finite.size else 1.0
        lo = -hi
    elif name == "S0":
        lo, hi = 0.0, float(np.percentile(finite, EXPOSURE_PERCENTILE)) if finite.size else 1.0
    else:
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    span = hi - lo if hi - lo > 1e-9 else 1.0
    rgb = colormap_image((values - lo) / span)
    rgb[~np.isfinite(values)] = 0
    unit = MAPS[name][0].split()[0].rstrip(",") if name in MAPS else ""      # "deg", "linear", "1"
    return rgb, f"{lo:.3g} to {hi:.3g}" + (f" {unit}" if unit == "deg" else " (linear, 1.0 = sensor white)" if unit == "linear" else "")


def write_png(path: Path, rgb: np.ndarray, long_side: int = 1024) -> None:
    """An H×W×3 uint8 RGB image as a PNG of at most ``long_side`` px long."""
    ok, data = cv2.imencode(".png", np.ascontiguousarray(_resize_long_side(rgb, long_side)[..., ::-1]))
    if not ok:
        raise DatasetError(f"{path}: PNG encoding failed")
    path.write_bytes(data.tobytes())


# ---------------------------------------------------------------------------------------------
# Files


@dataclasses.dataclass
class WrittenImage:
    """A written image: relative paths of its full, thumbnail (and medium) views, and their sizes."""

    full: str
    thumb: str
    size: tuple[int, int]          # (width, height) of the full view
    thumb_size: tuple[int, int]
    mid: str | None = None


def _resize_long_side(rgb: np.ndarray, long_side: int) -> np.ndarray:
    scale = long_side / max(rgb.shape[:2])
    if scale >= 1:
        return rgb
    size = (max(1, round(rgb.shape[1] * scale)), max(1, round(rgb.shape[0] * scale)))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def _write_jpeg(path: Path, rgb: np.ndarray, quality: int) -> tuple[int, int]:
    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise DatasetError(f"{path}: JPEG encoding failed")
    path.write_bytes(data.tobytes())
    return rgb.shape[1], rgb.shape[0]


def write_image(root: Path, rel_stem: str, rgb: np.ndarray, thumb_px: int, mid: bool = False) -> WrittenImage:
    """Write the full view and thumbnail (and a medium view) of an H×W×3 uint8 RGB image."""
    size = _write_jpeg(root / f"{rel_stem}.jpg", rgb, JPEG_QUALITY_FULL)
    thumb_size = _write_jpeg(root / f"{rel_stem}_t.jpg", _resize_long_side(rgb, thumb_px), JPEG_QUALITY_THUMB)
    image = WrittenImage(f"{rel_stem}.jpg", f"{rel_stem}_t.jpg", size, thumb_size)
    if mid:
        _write_jpeg(root / f"{rel_stem}_m.jpg", _resize_long_side(rgb, 2 * thumb_px), JPEG_QUALITY_FULL)
        image.mid = f"{rel_stem}_m.jpg"
    return image
