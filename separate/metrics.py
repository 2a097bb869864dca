"""Image quality figures used by training, benchmarks and the demo.

All figures are computed on linear images with peak 1 (the synthetic data's white level).
PSNR floors the per-image MSE at 1e-6, so a perfect result reads 60 dB, not infinity.
"""

from __future__ import annotations

import numpy as np
from skimage.metrics import structural_similarity

MSE_FLOOR = 1e-6


def mse(estimate: np.ndarray, truth: np.ndarray, axis=None) -> np.ndarray:
    """Mean squared error over ``axis`` (all axes by default)."""
    diff = np.asarray(estimate, np.float32) - np.asarray(truth, np.float32)
    return np.mean(np.square(diff), axis=axis, dtype=np.float64)


def rmse(estimate: np.ndarray, truth: np.ndarray, axis=None) -> np.ndarray:
    """Root mean squared error over ``axis``."""
    return np.sqrt(mse(estimate, truth, axis))


def psnr(estimate: np.ndarray, truth: np.ndarray, axis=None) -> np.ndarray:
    """Peak signal-to-noise ratio (dB, peak 1) over ``axis``."""
    return psnr_from_mse(mse(estimate, truth, axis))


def psnr_from_mse(mse_value: float | np.ndarray) -> np.ndarray:
    """PSNR (dB, peak 1) of a mean squared error, floored at `MSE_FLOOR`."""
    return 10 * np.log10(1.0 / np.maximum(mse_value, MSE_FLOOR))


def ssim(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Structural similarity of two H×W×C linear images (data range 1)."""
    return float(structural_similarity(estimate, truth, channel_axis=-1, data_range=1.0))


def mutual_information(a: np.ndarray, b: np.ndarray, bins: int = 32) -> float:
    """Mutual information (nats) of two images' values from a joint histogram (1–99% range)."""
    lo_a, hi_a = np.percentile(a, [1, 99])
    lo_b, hi_b = np.percentile(b, [1, 99])
    joint, _, _ = np.histogram2d(a.ravel(), b.ravel(), bins=bins, range=[[lo_a, hi_a + 1e-9], [lo_b, hi_b + 1e-9]])
    p = joint / max(joint.sum(), 1)
    pa, pb = p.sum(axis=1, keepdims=True), p.sum(axis=0, keepdims=True)
    nz = p > 0
    return float((p[nz] * np.log(p[nz] / (pa @ pb)[nz])).sum())
