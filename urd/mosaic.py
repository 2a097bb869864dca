"""Division-of-focal-plane polarization mosaics → 0/45/90/135 stacks.

A layout names, for each pixel of its repeating tile, the polarizer angle (degrees, urd's
convention: counter-clockwise from the image x axis) and, for colour sensors, the colour.
Colour sensors put a 2×2 block of polarizer pixels under each colour-filter cell, so the tile
is 4×4: colour blocks ``colours`` (2×2) of polarizer blocks ``angles`` (2×2).

Layouts, verified on the real captures in ../shared/data/polarization:

* ``imx250mzr`` — Sony IMX250MZR (mono): ``[[90, 45], [135, 0]]``. On the polanalyser
  polarizer-target capture the four filters (labelled 0, 45, 90, 135 left to right) come out
  with AoLP 90, 45, 0, 135: 45° apart, each dark in the channel 90° from its AoLP.
* ``imx250myr`` — Sony IMX250MYR (colour): the same polarizer block under RGGB colour blocks.
* ``wen2019`` — the CPDNet colour mosaic (Wen et al. 2019): ``[[0, 45], [135, 90]]`` under
  ``[R G; G B]`` colour blocks; reproduces net_input.png from gt_*.png exactly.
"""

from __future__ import annotations

import dataclasses
import enum

import cv2
import numpy as np

ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)


@dataclasses.dataclass(frozen=True)
class LayoutSpec:
    angles: tuple[tuple[int, int], tuple[int, int]]
    colours: tuple[str, str] | None  # rows of the colour-block pattern, e.g. ("RG", "GB")


class MosaicLayout(enum.Enum):
    """Polarization mosaic layouts (see the module docstring)."""

    IMX250MZR = "imx250mzr"
    IMX250MYR = "imx250myr"
    WEN2019 = "wen2019"

    @property
    def spec(self) -> LayoutSpec:
        return {
            "imx250mzr": LayoutSpec(((90, 45), (135, 0)), None),
            "imx250myr": LayoutSpec(((90, 45), (135, 0)), ("RG", "GB")),
            "wen2019": LayoutSpec(((0, 45), (135, 90)), ("RG", "GB")),
        }[self.value]


def _check_raw(raw: np.ndarray, layout: MosaicLayout) -> None:
    tile = 4 if layout.spec.colours else 2
    if raw.ndim != 2 or raw.shape[0] % tile or raw.shape[1] % tile:
        raise ValueError(f"expected a 2-D mosaic with sides divisible by {tile}, got shape {raw.shape}")


def demosaic_bilinear(sub: np.ndarray, colours: tuple[str, str]) -> np.ndarray:
    """Bilinear demosaic of a 2×2 colour mosaic by normalized convolution; linear in the data.

    Args:
        sub: H×W float32 mosaic.
        colours: the 2×2 tile as two rows of letters R, G, B (e.g. ("RG", "GB")).

    Returns:
        H×W×3 float32 RGB.
    """
    h, w = sub.shape
    out = np.empty((h, w, 3), np.float32)
    kernel = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]], np.float32)
    for k, name in enumerate("RGB"):
        mask = np.zeros((h, w), np.float32)
        for r in range(2):
            for c in range(2):
                if colours[r][c] == name:
                    mask[r::2, c::2] = 1.0
        num = cv2.filter2D(sub * mask, -1, kernel, borderType=cv2.BORDER_REFLECT)
        den = cv2.filter2D(mask, -1, kernel, borderType=cv2.BORDER_REFLECT)
        out[..., k] = np.where(mask > 0, sub, num / den)
    return out


def split_mosaic(raw: np.ndarray, layout: MosaicLayout) -> tuple[np.ndarray, list[float]]:
    """Split a raw mosaic into a polarization stack.

    Args:
        raw: H×W mosaic (any numeric dtype; kept in its units as float32).
        layout: the sensor layout.

    Returns:
        stack (4, H/2, W/2, C) float32 for angles 0, 45, 90, 135 (C = 1 mono, 3 colour: the
        colour planes bilinearly demosaiced), and the angles in degrees.
    """
    _check_raw(raw, layout)
    spec = layout.spec
    data = raw.astype(np.float32)
    planes = []
    for angle in ANGLES_DEG:
        (r, c), = [(r, c) for r in range(2) for c in range(2) if spec.angles[r][c] == angle]
        sub = data[r::2, c::2]
        planes.append(sub[..., None] if spec.colours is None else demosaic_bilinear(sub, spec.colours))
    return np.stack(planes), list(ANGLES_DEG)


def build_mosaic(stack: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    """Inverse of sampling: full-resolution images (4, H, W, C) at 0/45/90/135 → H×W mosaic."""
    spec = layout.spec
    _, h, w, _ = stack.shape
    out = np.empty((h, w), stack.dtype)
    for r in range(2):
        for c in range(2):
            a = ANGLES_DEG.index(spec.angles[r][c])
            if spec.colours is None:
                out[r::2, c::2] = stack[a, r::2, c::2, 0]
                continue
            for cr in range(2):
                for cc in range(2):
                    k = "RGB".index(spec.colours[cr][cc])
                    y, x = 2 * cr + r, 2 * cc + c
                    out[y::4, x::4] = stack[a, y::4, x::4, k]
    return out
