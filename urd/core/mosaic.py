"""Division-of-focal-plane polarization mosaics → registered 0/45/90/135 stacks.

A layout names, for each pixel of its repeating tile, the polarizer angle (degrees, urd's
convention: counter-clockwise from the image x axis) and, for colour sensors, the colour.
Colour sensors put a 2×2 block of polarizer pixels under each colour-filter cell, so the tile
is 4×4: colour blocks ``colours`` (2×2) of polarizer blocks ``angles`` (2×2).

Layouts (the mono and CPDNet ones verified on the real captures in ../shared/data/polarization):

* ``imx250mzr`` — Sony IMX250MZR (mono): ``[[90, 45], [135, 0]]``. On the polanalyser
  polarizer-target capture the four filters (labelled 0, 45, 90, 135 left to right) come out
  with AoLP 90, 45, 0, 135: 45° apart, each dark in the channel 90° from its AoLP.
* ``imx250myr`` — Sony IMX250MYR (colour): the same polarizer block under RGGB colour blocks,
  as the sensor's makers document it; ../shared/data holds no IMX250MYR capture to check it on.
* ``wen2019`` — the CPDNet colour mosaic (Wen et al. 2019): ``[[0, 45], [135, 90]]`` under
  ``[R G; G B]`` colour blocks; reproduces net_input.png from gt_*.png exactly.

Demosaicing (`demosaic`, methods `Demosaic`). The four pixels of a 2×2 polarizer cell see four
points one pixel apart, so taking them as one point (``none``, what `split_mosaic` does) puts
false polarization on every edge. The registered methods estimate every angle at every pixel
and, by default, average each 2×2 cell: each output pixel is then the mean irradiance behind
each of the four polarizers over the same 2×2 footprint. Colour mosaics are demosaiced in two
steps: the colour of each angle's sub-image (a Bayer mosaic at cell level), then the
polarization of each colour plane as a mono mosaic.
"""

from __future__ import annotations

import dataclasses
import enum

import cv2
import numpy as np

ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)

_BILINEAR = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]], np.float32)
# Newton's polynomial interpolation along a line of alternating channels A B A [B] A B A (the
# pixel in brackets is estimated): odd taps interpolate B, even taps add A's second difference
# (Li, Zhao, Pan & Kong, Opt. Express 27, 1376, 2019, their Eqs. 14-17 simplified).
_NEWTON_ODD = np.array([1 / 16, 0, 7 / 16, 0, 7 / 16, 0, 1 / 16], np.float32)
_NEWTON_EVEN = np.array([0, -1 / 4, 0, 1 / 2, 0, -1 / 4, 0], np.float32)
_NEWTON_RATIO = 5.8     # one direction wins outright when its neighbourhood's error is this much smaller


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


class Demosaic(enum.Enum):
    """Polarization demosaicing methods; the values are the names used at the CLI.

    * ``none`` — each polarizer site as it is (`split_mosaic`): one sample per 2×2 cell and
      angle, the four angles one pixel apart (unregistered; false polarization at edges).
    * ``bilinear`` — each angle bilinearly interpolated to every pixel, so all four are
      registered to the same points.
    * ``newton`` — Newton's polynomial interpolation with the polarization-difference model and
      an edge classifier (Li et al., Opt. Express 27, 1376, 2019): third-order interpolation
      along the direction of least change, corrected by the second difference of the pixel's
      own channel (the four channels share their edges).

    Measured by tools/bench_demosaic.py (false DoLP at edges, one pixel per cell): ``newton``
    halves ``bilinear``'s error on synthetic scenes and photos through glass and is slightly
    better on the real Wen 2019 mosaic; ``bilinear`` is better where the polarization itself
    has fine texture (the Lapray 2018 painting under polarized light). Colour mosaics use
    bilinear colour interpolation before either.
    """

    NONE = "none"
    BILINEAR = "bilinear"
    NEWTON = "newton"


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
    for k, name in enumerate("RGB"):
        mask = np.zeros((h, w), np.float32)
        for r in range(2):
            for c in range(2):
                if colours[r][c] == name:
                    mask[r::2, c::2] = 1.0
        num = cv2.filter2D(sub * mask, -1, _BILINEAR, borderType=cv2.BORDER_REFLECT)
        den = cv2.filter2D(mask, -1, _BILINEAR, borderType=cv2.BORDER_REFLECT)
        out[..., k] = np.where(mask > 0, sub, num / den)
    return out


def split_mosaic(raw: np.ndarray, layout: MosaicLayout) -> tuple[np.ndarray, list[float]]:
    """Split a raw mosaic into a polarization stack, each site as it is (`Demosaic.NONE`).

    Args:
        raw: H×W mosaic (any numeric dtype; kept in its units as float32).
        layout: the sensor layout.

    Returns:
        stack (4, H/2, W/2, C) float32 for angles 0, 45, 90, 135 (C = 1 mono, 3 colour: the
        colour planes bilinearly demosaiced), and the angles in degrees. The four angles of an
        output pixel come from four points one pixel apart.
    """
    _check_raw(raw, layout)
    spec = layout.spec
    data = raw.astype(np.float32)
    planes = []
    for angle in ANGLES_DEG:
        r, c = _site(spec, angle)
        sub = data[r::2, c::2]
        planes.append(sub[..., None] if spec.colours is None else demosaic_bilinear(sub, spec.colours))
    return np.stack(planes), list(ANGLES_DEG)


def demosaic(frame: np.ndarray, layout: MosaicLayout | str, method: Demosaic | str = Demosaic.NEWTON, *,
             half_size: bool = True) -> tuple[np.ndarray, list[float]]:
    """Demosaic a polarization mosaic into a stack of the four polarizer angles.

    Args:
        frame: H×W raw mosaic, any integer or float dtype, finite, in the sensor's (linear)
            code units; H and W divisible by the layout's tile (2 mono, 4 colour).
        layout: the sensor layout (`MosaicLayout` or its value, e.g. ``"imx250mzr"``).
        method: `Demosaic` or its value (``"none"``, ``"bilinear"``, ``"newton"``).
        half_size: True (default): one output pixel per 2×2 polarizer cell, (H/2, W/2) — the
            cell's mean behind each polarizer for the registered methods, the site's own
            sample for ``none``. False: every pixel, (H, W) (``none`` repeats each site's
            sample over its cell).

    Returns:
        stack (4, H', W', C) float32 in the frame's code units, for angles 0, 45, 90, 135
        (README convention), C = 1 mono, 3 colour (RGB); and those angles in degrees. The
        ``newton`` values are clipped to the frame's range (its cubic taps can overshoot).

    Raises:
        TypeError: ``frame`` is not a numeric numpy array, or ``layout``/``method``/
            ``half_size`` have the wrong type.
        ValueError: a wrong shape, non-finite values, or an unknown layout or method name.
    """
    if not isinstance(frame, np.ndarray) or not (np.issubdtype(frame.dtype, np.integer) or np.issubdtype(frame.dtype, np.floating)):
        raise TypeError(f"expected frame as a numpy array of integers or floats, got {_describe(frame)}")
    layout = _coerce(layout, MosaicLayout, "layout")
    method = _coerce(method, Demosaic, "method")
    if not isinstance(half_size, (bool, np.bool_)):
        raise TypeError(f"expected half_size as a bool, got {type(half_size).__name__}")
    _check_raw(frame, layout)
    if frame.size == 0:
        raise ValueError(f"expected a non-empty mosaic, got shape {frame.shape}")
    if np.issubdtype(frame.dtype, np.floating) and not np.isfinite(frame).all():
        raise ValueError(f"expected finite values, got {int((~np.isfinite(frame)).sum())} NaN or infinite pixels")
    if method is Demosaic.NONE:
        stack, angles = split_mosaic(frame, layout)
        if not half_size:
            stack = np.repeat(np.repeat(stack, 2, axis=1), 2, axis=2)
        return stack, angles
    spec = layout.spec
    data = frame.astype(np.float32)
    if spec.colours is None:
        planes = [data]
    else:
        # colour first: each angle's sub-image is a Bayer mosaic of cells; then each colour
        # plane, one pixel per sensor pixel, is a mono polarization mosaic
        rgb, _ = split_mosaic(data, layout)
        planes = [np.empty_like(data) for _ in range(3)]
        for k, angle in enumerate(ANGLES_DEG):
            r, c = _site(spec, angle)
            for colour in range(3):
                planes[colour][r::2, c::2] = rgb[k, ..., colour]
    run = _bilinear_mono if method is Demosaic.BILINEAR else _newton_mono
    stack = np.stack([run(plane, spec.angles) for plane in planes], axis=-1)
    if method is Demosaic.NEWTON:
        np.clip(stack, float(data.min()), float(data.max()), out=stack)
    if half_size:
        stack = cell_means(stack, axis=1)
    return np.ascontiguousarray(stack, dtype=np.float32), list(ANGLES_DEG)


def cell_means(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """The mean of each 2×2 cell of axes ``axis`` and ``axis + 1`` (even lengths): half size there."""
    def part(r: int, c: int) -> tuple[slice, ...]:
        return (slice(None),) * axis + (slice(r, None, 2), slice(c, None, 2))

    return (x[part(0, 0)] + x[part(0, 1)] + x[part(1, 0)] + x[part(1, 1)]) * np.float32(0.25)


def _describe(value) -> str:
    if isinstance(value, np.ndarray):
        return f"a {value.dtype} array"
    return type(value).__name__


def _coerce(value, kind: type[enum.Enum], name: str):
    if isinstance(value, kind):
        return value
    if not isinstance(value, str):
        raise TypeError(f"expected {name} as {kind.__name__} or its name, got {type(value).__name__}")
    try:
        return kind(value)
    except ValueError:
        raise ValueError(f"expected {name} one of {', '.join(m.value for m in kind)}, got {value!r}") from None


def _site(spec: LayoutSpec, angle: float) -> tuple[int, int]:
    """Row and column of ``angle`` in the 2×2 polarizer block."""
    (site,) = [(r, c) for r in range(2) for c in range(2) if spec.angles[r][c] == angle]
    return site


def _filter(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Correlation with mirrored borders (reflect-101 keeps each pixel's 2×2 site)."""
    return cv2.filter2D(image, cv2.CV_32F, kernel, borderType=cv2.BORDER_REFLECT_101)


def _assemble(own: np.ndarray, across: np.ndarray, down: np.ndarray, diagonal: np.ndarray,
              angles: tuple[tuple[int, int], tuple[int, int]]) -> np.ndarray:
    """(4, H, W) stack in ANGLES_DEG order from per-pixel estimates of each pixel's own channel,
    its row neighbour's, its column neighbour's and its diagonal neighbour's."""
    out = np.empty((4, *own.shape), np.float32)
    for r in range(2):
        for c in range(2):
            for image, (dr, dc) in ((own, (0, 0)), (across, (0, 1)), (down, (1, 0)), (diagonal, (1, 1))):
                out[ANGLES_DEG.index(angles[(r + dr) % 2][(c + dc) % 2]), r::2, c::2] = image[r::2, c::2]
    return out


def _bilinear_mono(mosaic: np.ndarray, angles: tuple[tuple[int, int], tuple[int, int]]) -> np.ndarray:
    """Bilinear polarization demosaic of an H×W float32 mono mosaic → (4, H, W).

    Each angle's sites form a lattice of step 2; a pixel between two sites (in a row or a
    column) gets their mean, a pixel between four their mean. Borders mirror the mosaic
    (reflect-101), which on a step-2 lattice repeats the outermost site.
    """
    h, w = mosaic.shape[0] // 2, mosaic.shape[1] // 2
    out = np.empty((4, *mosaic.shape), np.float32)
    for r in range(2):
        for c in range(2):
            padded = np.pad(mosaic[r::2, c::2], 1, mode="edge")
            plane = out[ANGLES_DEG.index(angles[r][c])]
            for py in range(2):
                rows = [1] if py == r else [(py - 1 - r) // 2 + 1, (py - 1 - r) // 2 + 2]
                for px in range(2):
                    cols = [1] if px == c else [(px - 1 - c) // 2 + 1, (px - 1 - c) // 2 + 2]
                    total = sum(padded[y:y + h, x:x + w] for y in rows for x in cols)
                    plane[py::2, px::2] = total * np.float32(1.0 / (len(rows) * len(cols)))
    return out


def _line(taps: np.ndarray, direction: str) -> np.ndarray:
    """A 7-tap line kernel along a row ("h"), a column ("v"), the main ("d") or the anti-diagonal ("a")."""
    return {"h": taps[None, :], "v": taps[:, None], "d": np.diag(taps), "a": np.fliplr(np.diag(taps))}[direction]


def _fuse(first: np.ndarray, second: np.ndarray, grad_first: np.ndarray, grad_second: np.ndarray,
          mosaic: np.ndarray) -> np.ndarray:
    """Combine two directional estimates: the edge classifier of Li et al. picks one outright
    when its same-site 3×3 neighbourhood fits the mosaic ``_NEWTON_RATIO`` times better, else
    the two are weighted by the inverse of the gradients along their directions."""
    box = np.zeros((5, 5), np.float32)
    box[::2, ::2] = 1.0
    err_first = _filter(np.abs(first - mosaic), box)
    err_second = _filter(np.abs(second - mosaic), box)
    eps = np.float32(1e-12)
    out = (first * (grad_second + eps) + second * (grad_first + eps)) / (grad_first + grad_second + 2 * eps)
    np.copyto(out, second, where=err_first > _NEWTON_RATIO * err_second)
    np.copyto(out, first, where=err_second > _NEWTON_RATIO * err_first)
    return out


def _gradient(mosaic: np.ndarray, direction: str) -> np.ndarray:
    """|first difference over the neighbours| + |second difference of the own channel| along a direction."""
    first = _line(np.array([0, 0, -1, 0, 1, 0, 0], np.float32), direction)
    second = _line(np.array([0, -1, 0, 2, 0, -1, 0], np.float32), direction)
    return np.abs(_filter(mosaic, first)) + np.abs(_filter(mosaic, second))


def _newton_mono(mosaic: np.ndarray, angles: tuple[tuple[int, int], tuple[int, int]]) -> np.ndarray:
    """Newton-polynomial polarization demosaic of an H×W float32 mono mosaic → (4, H, W)."""
    full = _NEWTON_ODD + _NEWTON_EVEN
    grads = {d: _gradient(mosaic, d) for d in "hvda"}
    # stage 1: row and column neighbours' channels along their line; the diagonal channel along
    # both diagonals, fused
    across = _filter(mosaic, _line(full, "h"))
    down = _filter(mosaic, _line(full, "v"))
    diagonal = _fuse(_filter(mosaic, _line(full, "d")), _filter(mosaic, _line(full, "a")), grads["d"], grads["a"], mosaic)
    # stage 2: the row neighbour's channel also along the column, through the column
    # neighbours' diagonal estimates (and vice versa), fused with the stage-1 estimate
    even_v, even_h = _filter(mosaic, _line(_NEWTON_EVEN, "v")), _filter(mosaic, _line(_NEWTON_EVEN, "h"))
    across = _fuse(across, even_v + _filter(diagonal, _line(_NEWTON_ODD, "v")), grads["h"], grads["v"], mosaic)
    down = _fuse(down, even_h + _filter(diagonal, _line(_NEWTON_ODD, "h")), grads["v"], grads["h"], mosaic)
    return _assemble(mosaic, across, down, diagonal, angles)


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
