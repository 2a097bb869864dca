"""Arvanitopoulos, Achanta & Süsstrunk, "Single image reflection suppression", CVPR 2017.

Keep the image's Laplacian (its strong structure) while an ℓ0 prior on gradients removes the
weak, reflection-like ones: minimize ||ΔT − ΔI||² + λ·||∇T||₀ + ε||T − I||². Solved by
half-quadratic splitting (gradient hard-thresholding, then an FFT solve), β doubling from 2λ.
Input: the unpolarized image S0, scaled to max 1 and gamma-encoded (γ = 2.2) as the photos
the paper's λ is set for; paper defaults λ = 0.002, ε = 1e-8. R̂ = S0 − T̂ (linear).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from separate import optics
from separate.baselines.common import Interval, half_quadratic

BETA_MAX = 1e5
#: The valid values of `separate`'s parameters: 0 < λ < β_max / 2, so that β, doubling from 2λ,
#: takes at least one step.
PARAM_RANGES = {"lam": Interval(above=0.0, below=BETA_MAX / 2)}


def suppress(image: np.ndarray, lam: float = 0.002, eps: float = 1e-8,
             progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """T of a single H×W×C image (ℓ0 prior: hard thresholding of T's gradients). ``progress`` is
    called with (iterations done, iterations of all channels)."""
    total = image.shape[2] * math.ceil(math.log2(BETA_MAX / (2 * lam)))
    started = 0

    def hard(gx: np.ndarray, gy: np.ndarray, beta: float) -> tuple[np.ndarray, np.ndarray]:
        nonlocal started
        if progress is not None:
            progress(started, total)
        started += 1
        keep = gx**2 + gy**2 >= lam / beta
        return gx * keep, gy * keep

    t_hat = half_quadratic(image, hard, 2 * lam, eps, BETA_MAX)
    if progress is not None:
        progress(total, total)
    return t_hat


def separate(images: np.ndarray, angles_deg: list[float], lam: float = 0.002,
             progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    s0 = optics.stokes_from_images(images, np.radians(angles_deg))[0].astype(np.float32)
    scale = max(float(s0.max()), 1e-6)
    encoded = np.clip(s0 / scale, 0, None) ** (1 / optics.GAMMA)          # the paper works on ordinary photos
    t_hat = (np.clip(suppress(encoded, lam, progress=progress), 0, None) ** optics.GAMMA * scale).astype(np.float32)
    return (s0 - t_hat).astype(np.float32), t_hat
