"""Tiles of a large image for the network: where they lie and how their outputs are blended.

Images of any size are processed in overlapping tiles of equal size whose origins lie on the
network's 8-pixel grid (so strided convolutions see the same pixels as on the whole image);
each tile's output is weighted by a ramp that is ~0 near its borders (where the receptive field
is cut) and the weights are normalized (their sum over the tiles is one at every pixel), which
leaves no seams (`separate.infer` gives the agreement with whole-image results). numpy only:
the command line checks a tile size without importing torch.
"""

from __future__ import annotations

import operator

import numpy as np

TILE = 2048     # px: a 6000 × 4000 image takes 4 × 3 tiles (1.19× its pixels); see separate.infer's docstring
OVERLAP = 160   # px between tiles: tiled and whole-image results agree within 3.9e-5 (fp32, separate.infer)
MIN_TILE = 128  # px: smaller tiles spend most of their pixels on the overlap


def check_tiling(tile: int, overlap: int) -> tuple[int, int]:
    """Validate tile size and overlap (px); return the tile rounded down to the 8-px grid and
    the overlap. ValueError unless tile ≥ `MIN_TILE` and ≥ 2·overlap, and overlap ≥ 0."""
    try:
        if isinstance(tile, bool) or isinstance(overlap, bool):
            raise TypeError
        tile, overlap = operator.index(tile), operator.index(overlap)
    except TypeError:
        raise TypeError(f"expected integer tile and overlap (px), got {tile!r} and {overlap!r}") from None
    if overlap < 0:
        raise ValueError(f"expected an overlap of at least 0 px, got {overlap}")
    if tile // 8 * 8 < max(MIN_TILE, 2 * overlap):
        raise ValueError(f"expected a tile of at least {max(MIN_TILE, 2 * overlap)} px (≥ {MIN_TILE} and ≥ 2 × "
                         f"overlap {overlap}, rounded down to a multiple of 8), got {tile}")
    return tile // 8 * 8, overlap


def border_ramp(length: int, overlap: int, at_start: bool, at_end: bool) -> np.ndarray:
    """1-D blending weight at a border shared with another tile: ~0 over the first half of
    ``overlap`` (pixels whose receptive field is cut by the tile border), then a linear rise."""
    w = np.ones(length, np.float32)
    if overlap == 0:
        return w
    margin = overlap // 2
    ramp = np.clip((np.arange(overlap, dtype=np.float32) + 0.5 - margin) / (overlap - margin), 1e-6, 1.0)
    if not at_start:
        w[:overlap] = ramp
    if not at_end:
        w[-overlap:] = np.minimum(w[-overlap:], ramp[::-1])
    return w


def blend_weights(spans: list[tuple[int, int]], size: int, overlap: int) -> list[np.ndarray]:
    """Each span's ramp (`border_ramp`) divided by the sum of all spans' ramps at each pixel, so that
    the weights of the tiles covering a pixel sum to one (the 2-D weights are products)."""
    ramps = [border_ramp(end - start, overlap, start == 0, end == size) for start, end in spans]
    total = np.zeros(size, np.float32)
    for (start, end), ramp in zip(spans, ramps):
        total[start:end] += ramp
    return [ramp / total[start:end] for (start, end), ramp in zip(spans, ramps)]


def tile_spans(size: int, tile: int, overlap: int) -> list[tuple[int, int]]:
    """Tiles along one axis as (start, end) px: as few as tiles of at most ``tile`` px allow,
    all of one length and evenly spread (no thin last tile), starts on the 8-px grid of the
    network's down-sampling, neighbours overlapping by at least ``overlap``."""
    if size <= tile:
        return [(0, size)]
    reach = overlap + 16                       # rounding both starts to the 8-px grid costs ≤ 15 px
    n = -(-(size - reach) // (tile - reach))
    length = -(-(size + (n - 1) * reach) // (8 * n)) * 8     # ≤ tile by the choice of n
    starts = [i * (size - length) // (n - 1) // 8 * 8 for i in range(n - 1)] + [-(-(size - length) // 8) * 8]
    return [(start, min(size, start + length)) for start in starts]
