"""The real polarization captures in ``../shared/data/polarization`` as urd stacks.

`captures`: eight scenes (see that folder's README): four Sony IMX250MZR mosaics (camera, carps,
fruits, polarizer; 8-bit linear sensor codes), three Lapray 2018 near-infrared division-of-time
scenes (glass, liquid, painting; 16-bit), and Wen 2019 scene61 (8-bit RGB per angle).

`no_glass_captures`: the real views without glass (the scene's own polarization: sky, foliage,
gloss, metal), each assigned to one side of a fixed split (`NO_GLASS_TEST`): "train" captures may
feed training data, "test" captures only the semi-real benchmark (`separate.semireal`) and the
no-glass checks. Mono captures stay mono (three equal channels).

Each is returned as (N, H, W, 3) float32 linear with its polarizer angles in degrees, optionally
reduced. 8-bit files are read as linear sensor codes.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from urd.core.errors import RawFormatError
from urd.core.images import codes_to_linear, read_image, read_raw_codes
from urd.core.mosaic import Demosaic, MosaicLayout, demosaic

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "polarization"
ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)


@dataclasses.dataclass(frozen=True)
class Capture:
    """One real capture: its name, kind, and the files it comes from."""

    name: str
    kind: str                     # "mosaic" (IMX250MZR), "frames" (one file per angle) or "cells" (`HAGEN_CELL_DEG`)
    files: tuple[Path, ...]
    mono: bool = False


def captures(root: Path = SHARED) -> list[Capture]:
    """The eight captures, in a fixed order (empty when the folder is absent)."""
    if not root.is_dir():
        return []
    out = [_imx250mzr(root, name) for name in ("camera", "carps", "fruits", "polarizer")]
    out += [Capture(f"lapray2018-{name}", "frames", tuple(root / "lapray2018-nir" / name / f"nir_{a:g}.tif" for a in ANGLES_DEG), True)
            for name in ("glass", "liquid", "painting")]
    out.append(Capture("wen2019-scene61", "frames", tuple(root / "wen2019-rgbpol" / "scene61" / f"gt_{a:g}.png" for a in ANGLES_DEG)))
    return out


def _imx250mzr(root: Path, name: str) -> Capture:
    return Capture(f"imx250mzr-{name}", "mosaic", (root / "imx250mzr-polanalyser" / f"{name}_IMX250MZR.png",), True)


#: The no-glass captures kept out of training: the semi-real benchmark's held-out part.
NO_GLASS_TEST = (tuple(f"dphr2022-outdoor-{k:02d}" for k in range(1, 20, 2))
                 + ("lmmse-cpfa-3", "qiu2019-kettle", "imx250mzr-camera", "imx250mzr-fruits", "wen2019-scene61"))
#: Angles (deg, urd's convention) of a 2×2 cell of the Hagen 2023 mono mosaic once turned upside
#: down. The raw frame is Sony's IMX250MZR layout, ((90, 45), (135, 0)); turning it upside down puts
#: the 135° and 0° pixels on top and mirrors every angle (α → −α: 45° ↔ 135°). The pairing is the
#: only one for which I0 + I90 = I45 + I135 holds (residual 2.4% of S0; 6% and 14% for the others).
HAGEN_CELL_DEG = ((45.0, 0.0), (90.0, 135.0))


def no_glass_captures(root: Path = SHARED, split: str | None = None) -> list[Capture]:
    """The real views without glass, in a fixed order; only the "train" or "test" side of the
    split (`NO_GLASS_TEST`) when ``split`` is given (empty when the folder is absent)."""
    if split not in (None, "train", "test"):
        raise ValueError(f"expected split 'train', 'test' or None, got {split!r}")
    if not root.is_dir():
        return []
    out = [Capture(f"dphr2022-outdoor-{k:02d}", "frames",
                   tuple(root / "dphr2022-outdoor" / f"scene_{k:02d}" / f"pol_{a:g}.png" for a in ANGLES_DEG)) for k in range(20)]
    out += [Capture(f"lmmse-cpfa-{k}", "frames", tuple(root / "lmmse-cpfa" / f"{a:g}_{k}.png" for a in ANGLES_DEG)) for k in (1, 2, 3)]
    out += [Capture(f"qiu2019-{name}", "frames", tuple(root / "qiu2019-cpfa" / f"{name}_{a:g}.png" for a in ANGLES_DEG))
            for name in ("woodwall", "kettle")]
    out.append(Capture("almansa-video-frame1", "frames",
                       tuple(root / "almansa-video" / f"frame1_{a:03.0f}.png" for a in ANGLES_DEG), True))
    out.append(Capture("hagen2023-core-bldg", "cells", (root / "hagen2023-mosaics" / "core_bldg_monopol.tif",), True))
    out += [_imx250mzr(root, "camera"), _imx250mzr(root, "fruits"),
            Capture("wen2019-scene61", "frames", tuple(root / "wen2019-rgbpol" / "scene61" / f"gt_{a:g}.png" for a in ANGLES_DEG))]
    out = [c for c in out if all(f.is_file() for f in c.files)]
    if split is None:
        return out
    return [c for c in out if (c.name in NO_GLASS_TEST) == (split == "test")]


def area_reduce(image: np.ndarray, max_side: int | None) -> np.ndarray:
    """``image`` (H×W or H×W×C) area-averaged to at most ``max_side`` px long (as it is when shorter or None)."""
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
        stack = codes_to_linear(codes, frame.dtype)                      # linear sensor codes
        if stack.shape[-1] == 1:
            stack = np.repeat(stack, 3, axis=-1)
        shots = [area_reduce(np.ascontiguousarray(shot), max_side) for shot in stack]
        return np.stack(shots).astype(np.float32), [float(a) for a in angles]
    if capture.kind == "cells":
        codes = cv2.imread(str(capture.files[0]), cv2.IMREAD_GRAYSCALE)    # LZW TIFF: OpenCV reads it, tifffile needs imagecodecs
        if codes is None:
            raise RawFormatError(f"{capture.files[0]}: not an image file urd can read")
        frame = codes_to_linear(codes[::-1, :, None], codes.dtype)
        cells = [(a, frame[i::2, j::2]) for i, row in enumerate(HAGEN_CELL_DEG) for j, a in enumerate(row)]
        cells.sort(key=lambda cell: cell[0])
        h, w = (min(c.shape[k] for _, c in cells) for k in (0, 1))
        shots = [area_reduce(np.ascontiguousarray(np.repeat(c[:h, :w], 3, axis=2)), max_side) for _, c in cells]
        return np.stack(shots).astype(np.float32), [a for a, _ in cells]
    shots = [area_reduce(read_image(path), max_side) for path in capture.files]
    return np.stack(shots).astype(np.float32), list(ANGLES_DEG)
