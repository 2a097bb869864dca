"""Li & Brown, "Single image layer separation using relative smoothness", CVPR 2014.

One image I = T + R where the reflection R is smoother than the transmission T: minimize
||L ⊗ (I − T)||² + λ·Σ_d |∂_d T|, a Laplacian penalty on R's high frequencies and a sparse
(ℓ1) gradient prior on T, subject to 0 ≤ T ≤ I. Solved by half-quadratic splitting with FFTs
(β from 2λ doubling to 1e5·... as in the paper's schedule), per colour channel. The input is the
unpolarized image S0; defaults λ = 100 (on images scaled to max 1), 0 ≤ T ≤ I.
"""

from __future__ import annotations

import numpy as np

from separate import optics
from separate.baselines.common import DX, DY, LAPLACIAN, psf2otf


def layer_separation(image: np.ndarray, lam: float = 100.0, beta0: float = 20.0, beta_max: float = 1e5,
                     eps: float = 1e-3) -> np.ndarray:
    """T of a single H×W×C image; R = image − T."""
    h, w = image.shape[:2]
    lap, dx, dy = psf2otf(LAPLACIAN, (h, w)), psf2otf(DX, (h, w)), psf2otf(DY, (h, w))
    lap2, d2 = np.abs(lap) ** 2, np.abs(dx) ** 2 + np.abs(dy) ** 2
    out = np.empty_like(image)
    for c in range(image.shape[2]):
        i_hat = np.fft.fft2(image[..., c])
        t = image[..., c].astype(np.float64)
        beta = beta0
        while beta < beta_max:
            t_hat = np.fft.fft2(t)
            gx, gy = np.real(np.fft.ifft2(dx * t_hat)), np.real(np.fft.ifft2(dy * t_hat))
            shrink = lam / (2 * beta)
            gx = np.sign(gx) * np.maximum(np.abs(gx) - shrink, 0)
            gy = np.sign(gy) * np.maximum(np.abs(gy) - shrink, 0)
            num = (lap2 + eps) * i_hat + beta * (np.conj(dx) * np.fft.fft2(gx) + np.conj(dy) * np.fft.fft2(gy))
            t = np.real(np.fft.ifft2(num / (lap2 + eps + beta * d2)))
            t = np.clip(t, 0, image[..., c])
            beta *= 2
        out[..., c] = t
    return out


def separate(images: np.ndarray, angles_deg: list[float], lam: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    s0 = optics.stokes_from_images(images, np.radians(angles_deg))[0].astype(np.float32)
    scale = max(float(s0.max()), 1e-6)
    t_hat = layer_separation(s0 / scale, lam) * scale
    return (s0 - t_hat).astype(np.float32), t_hat.astype(np.float32)
