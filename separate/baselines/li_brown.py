"""Li & Brown, "Single image layer separation using relative smoothness", CVPR 2014.

One image I = T + R where the reflection R is smoother than the transmission T: minimize
||L ⊗ (I − T)||² + λ·Σ_d |∂_d T|, a Laplacian penalty on R's high frequencies and a sparse
(ℓ1) gradient prior on T, subject to 0 ≤ T ≤ I. Solved by half-quadratic splitting with FFTs
(β from 20 doubling to 1e5), per colour channel. The input is the
unpolarized image S0; defaults λ = 100 (on images scaled to max 1), 0 ≤ T ≤ I.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from separate import optics
from separate.baselines.common import Interval, half_quadratic

BETA_MAX = 1e5
#: The valid values of `separate`'s parameters: λ ≥ 0 (0: no gradient prior).
PARAM_RANGES = {"lam": Interval(at_least=0.0)}


def layer_separation(image: np.ndarray, lam: float = 100.0, beta0: float = 20.0, eps: float = 1e-3,
                     progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """T of a single H×W×C image (ℓ1 prior: soft thresholding of T's gradients); R = image − T.
    ``progress`` is called with (iterations done, iterations of all channels)."""
    total = image.shape[2] * math.ceil(math.log2(BETA_MAX / beta0))
    started = 0

    def soft(gx: np.ndarray, gy: np.ndarray, beta: float) -> tuple[np.ndarray, np.ndarray]:
        nonlocal started
        if progress is not None:
            progress(started, total)
        started += 1
        shrink = lam / (2 * beta)
        return (np.sign(gx) * np.maximum(np.abs(gx) - shrink, 0), np.sign(gy) * np.maximum(np.abs(gy) - shrink, 0))

    t_hat = half_quadratic(image, soft, beta0, eps, BETA_MAX, keep_below_input=True)
    if progress is not None:
        progress(total, total)
    return t_hat


def separate(images: np.ndarray, angles_deg: list[float], lam: float = 100.0,
             progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    s0 = optics.stokes_from_images(images, np.radians(angles_deg))[0].astype(np.float32)
    scale = max(float(s0.max()), 1e-6)
    t_hat = layer_separation(s0 / scale, lam, progress=progress) * scale
    return (s0 - t_hat).astype(np.float32), t_hat.astype(np.float32)
