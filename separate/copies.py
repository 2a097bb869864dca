"""Light that R̂ shows as a copy of T̂, returned to T̂.

A reflection is an image of its own: behind glass, R and T are different scenes, and over any
window of a few dozen pixels R̂ and T̂ are nearly uncorrelated. Where R̂ is instead a scaled
copy of T̂ (Pearson correlation near 1 over the window), the polarized light the separation
put into R̂ is the transmitted scene's own: blue sky polarized by scattering, a scene seen with
no glass at all, a sensor's polarization crosstalk. `return_copies` moves that part back:

    ρ, a = corr(dR̂, dT̂), cov(dR̂, dT̂)⁺ / var(dT̂)    (per channel, Gaussian window of σ px)
    w = clip((ρ − ρ₀) / (ρ₁ − ρ₀), 0, 1)
    m = clip(w·a·T̂, 0, R̂),   R̂ ← R̂ − m,   T̂ ← T̂ + m

so R̂ + T̂ is unchanged (to float32 rounding). The statistics compare the layers' detail, dX = X − blur(X, `DETAIL`
px): two different scenes often share their coarse layout (bright sky above, dark ground
below), and correlated that way they would pass for copies. They are taken on the image reduced
to at most `STATS_SIDE` px, where the window is σ = `SIGMA` px, and interpolated back: on any
frame from 512 px up the window spans the same share of the view (smaller frames are not
enlarged). The variance floor is relative to the frame's mean brightness, so detail below
~0.1% of it (deep shadows) is not compared.

Chosen on bsds500/val (32 synthetic patches of 256², the shipped network) among window sizes
and thresholds: with σ 48 px, detail σ 2 px, ρ₀ 0.5, ρ₁ 0.9 no patch changed (T̂ PSNR +0.000 dB;
bsds500-test and the bundled photos, 64 patches each: within 0.001 dB);
docs/benchmarks.md gives the real captures' R̂ shares with and without it. Specular sheen on glossy objects (fruit skins,
varnish) is not a copy in this sense: its brightness follows the surface's normals, not T̂, and
stays in R̂.
"""

from __future__ import annotations

import concurrent.futures

import cv2
import numpy as np

STATS_SIDE = 512    # px: the statistics' grid, at most this long side
SIGMA = 48.0        # px on that grid: the window's Gaussian σ
DETAIL = 2.0        # px on that grid: the detail is what a Gaussian blur of this σ removes
RHO = (0.5, 0.9)    # correlation where the return starts and where it is whole
_EPS = 1e-6         # variance floor, in units of the image's mean brightness squared


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(x, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def copy_share(r_hat: np.ndarray, t_hat: np.ndarray, sigma: float = SIGMA,
               rho: tuple[float, float] = RHO) -> np.ndarray:
    """The multiple w·a of T̂ that R̂ copies (module docstring), per pixel and channel.

    Args:
        r_hat, t_hat: H×W×C linear layers of one image, float (any size, C ≤ 4; the statistics
            of at most `STATS_SIDE` px).
        sigma: the window's Gaussian σ, px on the statistics' grid.
        rho: (ρ₀, ρ₁), 0 ≤ ρ₀ < ρ₁ ≤ 1.

    Returns:
        H×W×C float32, ≥ 0.
    """
    if r_hat.ndim != 3 or r_hat.shape != t_hat.shape or r_hat.shape[2] > 4:
        raise ValueError(f"expected two H×W×C layers of one shape, C ≤ 4, got {r_hat.shape} and {t_hat.shape}")
    if r_hat.dtype.kind != "f" or t_hat.dtype.kind != "f":
        raise ValueError(f"expected float layers, got {r_hat.dtype} and {t_hat.dtype}")
    if len(rho) != 2 or not 0.0 <= rho[0] < rho[1] <= 1.0 or not 0 < sigma <= STATS_SIDE:
        raise ValueError(f"expected 0 < sigma <= {STATS_SIDE} px and rho (rho0, rho1) with 0 <= rho0 < rho1 <= 1, "
                         f"got sigma {sigma}, rho {rho}")
    h, w = r_hat.shape[:2]
    scale = min(1.0, STATS_SIDE / max(h, w))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small_r, small_t = (cv2.resize(x, size, interpolation=cv2.INTER_AREA) if scale < 1 else x.copy()
                        for x in (r_hat.astype(np.float32, copy=False), t_hat.astype(np.float32, copy=False)))
    small_r, small_t = small_r.reshape(size[1], size[0], -1), small_t.reshape(size[1], size[0], -1)
    unit = float((small_r + small_t).mean())
    share = np.zeros_like(small_t)
    if not np.isfinite(unit) or unit <= 0:                  # a dark or broken frame: nothing to compare
        return np.zeros((h, w, share.shape[2]), np.float32)

    def channel(c: int) -> None:
        r, t = small_r[..., c] / unit, small_t[..., c] / unit
        r, t = r - _blur(r, DETAIL), t - _blur(t, DETAIL)
        mr, mt = _blur(r, sigma), _blur(t, sigma)
        var_r = np.maximum(_blur(r * r, sigma) - mr * mr, 0.0) + _EPS
        var_t = np.maximum(_blur(t * t, sigma) - mt * mt, 0.0) + _EPS
        cov = _blur(r * t, sigma) - mr * mt
        weight = np.clip((cov / np.sqrt(var_r * var_t) - rho[0]) / (rho[1] - rho[0]), 0.0, 1.0)
        share[..., c] = weight * np.maximum(cov, 0.0) / var_t

    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:     # the blurs release the GIL: 0.29 → 0.2 s
        list(pool.map(channel, range(small_t.shape[2])))
    if scale < 1:
        share = cv2.resize(share, (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, -1)
    return share


def return_copies(r_hat: np.ndarray, t_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R̂, T̂ (H×W×C linear, float; returned as float32) with the part of R̂ that copies T̂ moved
    into T̂ (module docstring); R̂ + T̂ is unchanged. The inputs are not modified."""
    r_hat, t_hat = np.asarray(r_hat, np.float32), np.asarray(t_hat, np.float32)
    moved = copy_share(r_hat, t_hat)
    if not moved.any():
        return r_hat, t_hat
    np.multiply(moved, t_hat, out=moved)
    np.minimum(moved, r_hat, out=moved)
    np.maximum(moved, 0.0, out=moved)
    t_out = t_hat + moved
    return np.subtract(r_hat, moved, out=moved), t_out
