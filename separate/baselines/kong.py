"""Kong, Tai & Shin, "A physically-based approach to reflection separation: from physical
modeling to constrained optimization", TPAMI 36(2), 2014 — a simplified re-implementation.

Like Kong et al.: three shots at unknown absolute angles; per pixel the sinusoid fit gives
φ⊥ and the canonical images I⊥, I∥; the angle of incidence θ varies over the image and is
chosen where the recovered layers are most mutually exclusive (their gradients rarely coincide),
with spatial smoothness. Simplified here: θ is searched per block (default 64 px) on a grid
(2°–88°, 2° steps) minimizing the normalized correlation of the layers' gradient magnitudes,
then smoothed (Gaussian, σ = 1 block) and interpolated to every pixel, where the Fresnel 2×2
mixture is inverted. Kong et al. solve one joint constrained optimization instead.
"""

from __future__ import annotations

import cv2
import numpy as np

from separate.baselines.common import canonical, fresnel_inverse, luminance


def _exclusion(r: np.ndarray, t: np.ndarray) -> float:
    """Normalized correlation of gradient magnitudes of two images (0 = exclusive)."""
    gr = np.hypot(*np.gradient(r))
    gt = np.hypot(*np.gradient(t))
    return float((gr * gt).sum() / (np.sqrt((gr**2).sum() * (gt**2).sum()) + 1e-12))


def theta_map(i_perp: np.ndarray, i_par: np.ndarray, block: int, grid_deg: np.ndarray) -> np.ndarray:
    """Smooth per-pixel angle of incidence (rad) from blockwise mutual-exclusion search."""
    lp, lq = luminance(i_perp), luminance(i_par)
    h, w = lp.shape
    by, bx = max(1, h // block), max(1, w // block)
    coarse = np.zeros((by, bx), np.float32)
    for j in range(by):
        for i in range(bx):
            sl = (slice(j * h // by, (j + 1) * h // by), slice(i * w // bx, (i + 1) * w // bx))
            scores = [_exclusion(*fresnel_inverse(lp[sl], lq[sl], t)) for t in np.radians(grid_deg)]
            coarse[j, i] = np.radians(grid_deg[int(np.argmin(scores))])
    coarse = cv2.GaussianBlur(coarse, (0, 0), 1.0, borderType=cv2.BORDER_REPLICATE)
    return cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)


def separate(images: np.ndarray, angles_deg: list[float], block: int = 64,
             grid_step_deg: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    i_perp, i_par, _ = canonical(images, angles_deg)
    theta = theta_map(i_perp, i_par, block, np.arange(2.0, 88.0, grid_step_deg))
    return fresnel_inverse(i_perp, i_par, theta)
