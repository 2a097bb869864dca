"""The real polarization captures in ``../shared/data/polarization`` as urd stacks.

Eight scenes (see that folder's README): four Sony IMX250MZR mosaics (camera, carps, fruits,
polarizer; 8-bit linear sensor codes), three Lapray 2018 near-infrared division-of-time scenes
(glass, liquid, painting; 16-bit), and Wen 2019 scene61 (8-bit RGB per angle). Each is returned
as (N, H, W, 3) float32 linear with its polarizer angles in degrees, optionally reduced.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from urd.core.images import read_image, read_raw_codes
from urd.core.mosaic import Demosaic, MosaicLayout, demosaic

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "polarization"
ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)


@dataclasses.dataclass(frozen=True)
class Capture:
    """One real capture: its name, kind, and the files it comes from."""

    name: str
    kind: str                     # "mosaic" or "frames"
    files: tuple[Path, ...]


def captures(root: Path = SHARED) -> list[Capture]:
    """The eight captures, in a fixed order (empty when the folder is absent)."""
    if not root.is_dir():
        return []
    out = [Capture(f"imx250mzr-{name}", "mosaic", (root / "imx250mzr-polanalyser" / f"{name}_IMX250MZR.png",))
           for name in ("camera", "carps", "fruits", "polarizer")]
    out += [Capture(f"lapray2018-{name}", "frames", tuple(root / "lapray2018-nir" / name / f"nir_{a:g}.tif" for a in ANGLES_DEG))
            for name in ("glass", "liquid", "painting")]
    out.append(Capture("wen2019-scene61", "frames", tuple(root / "wen2019-rgbpol" / "scene61" / f"gt_{a:g}.png" for a in ANGLES_DEG)))
    return out


def _reduce(image: np.ndarray, max_side: int | None) -> np.ndarray:
    scale = 1.0 if max_side is None else max_side / max(image.shape[:2])
    if scale >= 1:
        return image
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def load(capture: Capture, max_side: int | None = None, method: Demosaic = Demosaic.NEWTON) -> tuple[np.ndarray, list[float]]:
    """The capture as a stack (N, H, W, 3) float32 linear and its angles (deg), at most
    ``max_side`` px long (area-reduced, which keeps the Stokes fit exact)."""
    if capture.kind == "mosaic":
        frame = read_raw_codes(capture.files[0])
        codes, angles = demosaic(frame, MosaicLayout.IMX250MZR, method)
        stack = np.clip(codes.astype(np.float32) / float(np.iinfo(frame.dtype).max), 0.0, 1.0)   # linear sensor codes
        if stack.shape[-1] == 1:
            stack = np.repeat(stack, 3, axis=-1)
        shots = [_reduce(np.ascontiguousarray(shot), max_side) for shot in stack]
        return np.stack(shots).astype(np.float32), [float(a) for a in angles]
    shots = [_reduce(read_image(path), max_side) for path in capture.files]
    return np.stack(shots).astype(np.float32), list(ANGLES_DEG)
