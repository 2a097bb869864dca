"""Full-resolution inference with the separation network.

Images of any size are processed in overlapping tiles of equal size whose origins lie on the
network's 8-pixel grid (so strided convolutions see the same pixels as on the whole image);
each tile's output is weighted by a ramp that is ~0 near its borders (where the receptive field
is cut) and the weighted sum is normalized, which leaves no seams: with the default 160 px
overlap, tiled and whole-image results agree within 1e-4 (1 MP test image; 1.2e-3 with 128 px).
Memory is bounded by the tile size, not the image size.
One exposure scale, mean(S0) of the whole image, is used for every tile.

Input handling: NaN or infinite pixels are an error; negative pixels (linear decoding noise
below black) are clipped to 0; the angles must span at least 90°. Monochrome shots (one
channel, or colour channels that are all equal, as urd stores a mono sensor's frames) carry no
colour: the network sees the grey image in each of its colour channels and its outputs are
averaged over them, so R̂ and T̂ are grey too (an RGB-trained network otherwise invents tints).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from separate import optics
from separate.model import build_model
from separate.precision import Precision, resolve
from urd.errors import WeightsError

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
OVERLAP = 160  # px between tiles: tiled and whole-image results agree within 1e-4
DEFAULT_WEIGHTS = WEIGHTS_DIR / "urd-canonical.pt"


def load_model(path: Path | None = None) -> tuple[torch.nn.Module, dict]:
    """Load shipped or trained weights; WeightsError if missing, corrupt or mismatched.

    Accepts a weights file (``{"model", "model_config"}``) or a training checkpoint.
    Returns the model in eval mode and a description (file, sha256, config, card).
    """
    path = Path(path or DEFAULT_WEIGHTS)
    if not path.is_file():
        raise WeightsError(f"weights file {path} not found (train with 'urd train' or reinstall urd)")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        model = build_model(state["model_config"])
        model.load_state_dict({k: v.float() for k, v in state["model"].items()})
    except Exception as exc:  # noqa: BLE001 - any failure to read means the file is unusable
        raise WeightsError(f"weights file {path} is corrupt or does not fit the model: {exc}") from exc
    model.eval()
    card = path.with_suffix(".json")
    info = {"file": str(path), "sha256": digest, "config": state["model_config"],
            "card": json.loads(card.read_text()) if card.is_file() else None}
    return model, info


def check_inputs(images: np.ndarray, angles_deg: list[float]) -> None:
    """Validate a stack (N, H, W, C) and its angles (deg) without copying the stack."""
    if images.ndim != 4 or images.shape[0] < 3 or images.shape[-1] not in (1, 3):
        raise ValueError(f"expected at least 3 shots stacked as (N>=3, H, W, C in 1,3), got {images.shape}")
    if len(angles_deg) != images.shape[0]:
        raise ValueError(f"expected {images.shape[0]} angles (one per image), got {len(angles_deg)}")
    optics.check_angles(np.radians(angles_deg), min_span=np.radians(90.0))
    if not np.isfinite(images.sum(dtype=np.float64)):                  # NaN and inf propagate to the sum
        bad = sum(int((~np.isfinite(shot)).sum()) for shot in images)
        raise ValueError(f"expected finite pixel values, got {bad} NaN or infinite values")


def _ramp(length: int, overlap: int, at_start: bool, at_end: bool) -> np.ndarray:
    """1-D blending weight at a border shared with another tile: ~0 over the first half of
    ``overlap`` (pixels whose receptive field is cut by the tile border), then a linear rise."""
    w = np.ones(length, np.float32)
    margin = overlap // 2
    ramp = np.clip((np.arange(overlap, dtype=np.float32) + 0.5 - margin) / (overlap - margin), 1e-6, 1.0)
    if not at_start:
        w[:overlap] = ramp
    if not at_end:
        w[-overlap:] = np.minimum(w[-overlap:], ramp[::-1])
    return w


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


@torch.no_grad()
def separate_stack(model: torch.nn.Module, images: np.ndarray, angles_deg: list[float], tile: int = 768,
                   overlap: int = OVERLAP, precision: str = "auto",
                   progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Separate an aligned stack into (R̂, T̂), each H×W×C float32 linear.

    Args:
        model: the network (``model.channels`` colour channels).
        images: (N, H, W, C) linear shots, N ≥ 3, C = ``model.channels`` or 1; monochrome
            stacks give monochrome results (module docstring).
        angles_deg: polarizer angles of the shots (deg), spanning at least 90°.
        tile, overlap: tile size and overlap (px); tile is rounded to a multiple of 8.
        precision: "auto", "fp32" or "bf16" (`separate.precision.resolve`: auto takes bf16
            only where the CPU runs it natively).
        progress: called with (tiles done, tiles total).
    """
    check_inputs(images, angles_deg)
    bf16 = resolve(precision) is Precision.BF16
    n, h, w, c = images.shape
    if c not in (1, model.channels):
        raise ValueError(f"expected shots with 1 or {model.channels} channels for this network, got {c}")
    mono = all(np.array_equal(shot[..., 0], shot[..., k]) for shot in images for k in range(1, c))
    tile = max(64, tile // 8 * 8)
    overlap = min(overlap, tile // 2)
    angles = [float(a) for a in np.radians(angles_deg)]
    shot_means = np.array([np.clip(shot, 0.0, None).mean(dtype=np.float64) for shot in images])  # mean(S0) is linear in them
    s0_mean = float(np.linalg.pinv(optics.stokes_matrix(angles))[0] @ shot_means)
    scale = torch.tensor([max(s0_mean, 1e-6)])
    r_sum = np.zeros((h, w, c), np.float32)
    t_sum = np.zeros((h, w, c), np.float32)
    weight = np.zeros((h, w, 1), np.float32)
    rows, cols = tile_spans(h, tile, overlap), tile_spans(w, tile, overlap)
    done, total = 0, len(rows) * len(cols)
    for y, y1 in rows:
        for x, x1 in cols:
            patch = np.clip(images[:, y:y1, x:x1], 0.0, None, dtype=np.float32).transpose(0, 3, 1, 2)
            patch = torch.from_numpy(np.ascontiguousarray(patch))[None]
            if c == 1:
                patch = patch.expand(-1, -1, model.channels, -1, -1)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                r_hat, t_hat = model(patch, angles, scale)
            if mono:
                r_hat, t_hat = (o.float().mean(dim=1, keepdim=True).expand(-1, c, -1, -1) for o in (r_hat, t_hat))
            wy = _ramp(y1 - y, overlap, y == 0, y1 == h)
            wx = _ramp(x1 - x, overlap, x == 0, x1 == w)
            wt = (wy[:, None] * wx[None, :])[..., None]
            r_sum[y:y1, x:x1] += r_hat[0].float().numpy().transpose(1, 2, 0) * wt
            t_sum[y:y1, x:x1] += t_hat[0].float().numpy().transpose(1, 2, 0) * wt
            weight[y:y1, x:x1] += wt
            done += 1
            if progress:
                progress(done, total)
    r_sum /= weight
    t_sum /= weight
    return r_sum, t_sum


def match_histograms(estimate: np.ndarray, reference: np.ndarray, quantiles: int = 1024) -> np.ndarray:
    """Parameter-free colour correction (paper §3.4): each channel of ``estimate`` (H×W×C) gets
    the value distribution of the same channel of ``reference`` by a monotone quantile mapping
    (``quantiles`` points, linear between; quantiles from at most ~1 M pixels of each image)."""
    if estimate.ndim != 3 or reference.ndim != 3 or estimate.shape[-1] != reference.shape[-1]:
        raise ValueError(f"expected two H×W×C images with equal C, got {estimate.shape} and {reference.shape}")
    q = np.linspace(0.0, 1.0, quantiles)
    out = np.empty_like(estimate)
    for c in range(estimate.shape[-1]):
        src, ref = estimate[..., c], reference[..., c]
        src_q = np.quantile(src.ravel()[:: max(1, src.size // 1_000_000)], q)
        ref_q = np.quantile(ref.ravel()[:: max(1, ref.size // 1_000_000)], q)
        out[..., c] = np.interp(src, src_q, ref_q)
    return out
