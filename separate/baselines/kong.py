"""Kong, Tai & Shin, "A physically-based approach to reflection separation: from physical
modeling to constrained optimization", TPAMI 36(2), 2014 — re-implemented.

Three shots at unknown absolute angles. Per pixel the sinusoid fit gives φ⊥ (within ±45° of the
first shot's angle, `common.canonical`) and the canonical images I⊥, I∥, a 2×2 Fresnel mixture
of the layers whose coefficients R_s, R_p depend on the
angle of incidence θ(x), which varies over the image. θ comes from one constrained
optimization over the whole image, solved coarse to fine (Kong et al.'s multiscale scheme):

    min_θ  X(R̂_θ, T̂_θ) + λ·N²·mean|∇θ|²   s.t.  R̂_θ ≥ 0,  T̂_θ ≥ 0,  θ_min ≤ θ ≤ θ_max

on the luminance, where R̂_θ, T̂_θ invert the mixture at θ, X is the normalized correlation of
their gradient magnitudes (the two layers' edges should not coincide), N is the image side in
pixels (so λ does not depend on the resolution). The positivity constraints are the physical
ones — the reflection must be at least as polarized as the light observed, which bounds θ
around Brewster's angle — and enter as a quadratic penalty; the bounds enter by a sigmoid
parametrization. The coarsest pyramid level starts from the best global θ on a grid; each
finer level (factor 2) starts from the coarser one's θ. The mixture is then inverted per
colour channel with the final θ map.

Deviations: single-interface Fresnel coefficients (urd's optics core; Kong et al. model both
surfaces of the pane), and Adam on the penalized energy (its gradient in closed form, `_energy`)
rather than their solver.
Defaults: λ = 1 (chosen on 32 patches of urd's synthetic benchmark: 0.05 overfits noise and
misalignment, 0.5–2 are within 0.1 dB), 150 Adam steps per level, coarsest side ≥ 32 px.

θ range (urd's choice, as for `separate.baselines.schechner`, after collapses on real scenes):
θ in [10°, 80°]. Below 10° R_s ≈ R_p and the inversion amplifies noise by hundreds; towards
grazing incidence every layer becomes "reflection". If the coarsest level's grid search ends
on either bound, the optimization starts from Brewster's angle instead (the best-conditioned
mixture, R_p = 0), and the bounds keep every pixel's θ inside the range.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np
import torch

from separate import optics
from separate.baselines.common import Interval, canonical, fresnel_inverse, luminance

PENALTY = 1e3


def _difference_parts(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward differences along x and y and |∇image|, each (H−1)×(W−1)."""
    dx = image[:-1, 1:] - image[:-1, :-1]
    dy = image[1:, :-1] - image[:-1, :-1]
    magnitude = dx * dx
    magnitude += dy * dy
    magnitude += 1e-12
    return dx, dy, np.sqrt(magnitude, out=magnitude)


def _energy(theta: np.ndarray, i_perp: np.ndarray, i_par: np.ndarray, smoothness: float) -> tuple[float, np.ndarray]:
    """The penalized energy of a θ map (rad, H×W) for luminance canonical images (H×W), and
    its gradient dE/dθ (per rad, H×W), derived by hand.

    R̂_θ = A(θ)·I⊥ + B(θ)·I∥ and T̂_θ = I⊥ + I∥ − R̂_θ (`separate.optics.mixture_coefficients`),
    so dE/dθ = (∂E/∂R̂ − ∂E/∂T̂)·(A′·I⊥ + B′·I∥) + the smoothness term's gradient.
    """
    h, w = theta.shape
    side, pixels = max(h, w), h * w
    angle = torch.from_numpy(theta)                              # torch's float64 cos/sin: ~8× numpy's here
    r_s, r_p, dr_s, dr_p = (r.numpy() for r in optics.fresnel_reflectance_and_slope(angle))
    a, b = optics.mixture_coefficients(r_s, r_p)
    da, db = optics.mixture_coefficient_slopes(r_s, r_p, dr_s, dr_p)
    s0 = i_perp + i_par
    r_hat = a * i_perp + b * i_par
    t_hat = s0 - r_hat

    # exclusion X = Σ gr·gt / sqrt(Σ gr² · Σ gt²) of the gradient magnitudes gr, gt
    dx_r, dy_r, gr = _difference_parts(r_hat)
    dx_t, dy_t, gt = _difference_parts(t_hat)
    cross, norm_r, norm_t = (gr * gt).sum(), (gr * gr).sum(), (gt * gt).sum()
    root = np.sqrt(norm_r * norm_t)
    exclusion = cross / root
    quotient = gt / gr
    weight_r = quotient / root - exclusion / norm_r             # ∂X/∂gr / gr
    weight_t = 1 / (quotient * root) - exclusion / norm_t       # ∂X/∂gt / gt
    kx = weight_r * dx_r - weight_t * dx_t
    ky = weight_r * dy_r - weight_t * dy_t
    d_layer = np.zeros_like(theta)                              # ∂E/∂R̂ − ∂E/∂T̂
    d_layer[:-1, 1:] += kx
    kx += ky
    d_layer[:-1, :-1] -= kx
    d_layer[1:, :-1] += ky

    # positivity penalty on min(R̂, 0), min(T̂, 0)
    scale2 = s0.mean() ** 2
    low_r, low_t = np.minimum(r_hat, 0), np.minimum(t_hat, 0)
    violation = ((low_r * low_r).sum() + (low_t * low_t).sum()) / pixels / scale2
    low_r -= low_t
    low_r *= 2 * PENALTY / pixels / scale2
    d_layer += low_r
    da *= i_perp
    db *= i_par
    da += db
    grad = d_layer * da

    step_x, step_y = np.diff(theta, axis=1), np.diff(theta, axis=0)
    rough = (step_x * step_x).mean() + (step_y * step_y).mean()
    step_x *= 2 * smoothness * side**2 / step_x.size
    step_y *= 2 * smoothness * side**2 / step_y.size
    grad[:, 1:] += step_x
    grad[:, :-1] -= step_x
    grad[1:] += step_y
    grad[:-1] -= step_y
    energy = exclusion + PENALTY * violation + smoothness * side**2 * rough
    return float(energy), grad


def _bounded(logit: torch.Tensor, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """θ = lo + (hi − lo)·sigmoid(logit) (rad; the bounds held by the parametrization) and dθ/dlogit."""
    sigmoid = torch.sigmoid(logit).numpy()
    return lo + (hi - lo) * sigmoid, (hi - lo) * sigmoid * (1 - sigmoid)


def _pyramid(image: np.ndarray, min_side: int) -> list[np.ndarray]:
    """Area-averaged levels, finest first, down to a short side of at least ``min_side``."""
    levels = [image]
    while min(levels[-1].shape) >= 2 * min_side:
        levels.append(cv2.resize(levels[-1], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
    return levels


#: The θ range (deg) every pixel's angle of incidence is held in.
BOUNDS_DEG = (10.0, 80.0)


def theta_map(i_perp: np.ndarray, i_par: np.ndarray, smoothness: float = 1.0, steps: int = 150,
              min_side: int = 32, bounds_deg: tuple[float, float] = BOUNDS_DEG,
              progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Per-pixel angle of incidence (rad, H×W) in ``bounds_deg`` from the coarse-to-fine
    constrained optimization (module docstring); ``progress`` is called with (Adam steps done,
    steps of all levels) after every step."""
    if not 0.0 < bounds_deg[0] < bounds_deg[1] < 90.0:
        raise ValueError(f"expected bounds (lo, hi) with 0 < lo < hi < 90 deg, got {bounds_deg}")
    lo, hi = np.radians(bounds_deg)
    perp_levels = _pyramid(luminance(i_perp).astype(np.float32), min_side)
    par_levels = _pyramid(luminance(i_par).astype(np.float32), min_side)
    grid = np.radians(np.arange(bounds_deg[0] + 1.0, bounds_deg[1], 1.0))
    coarse_perp, coarse_par = perp_levels[-1].astype(np.float64), par_levels[-1].astype(np.float64)
    scores = [_energy(np.full(coarse_perp.shape, t), coarse_perp, coarse_par, smoothness)[0] for t in grid]
    best = int(np.argmin(scores))
    start = optics.brewster_angle() if best in (0, grid.size - 1) else grid[best]
    theta = np.full(perp_levels[-1].shape, start, np.float32)
    total = steps * len(perp_levels)
    for level, (perp, par) in enumerate(zip(reversed(perp_levels), reversed(par_levels))):
        theta = cv2.resize(theta, (perp.shape[1], perp.shape[0]), interpolation=cv2.INTER_LINEAR)
        u = np.clip((theta - lo) / (hi - lo), 1e-4, 1 - 1e-4)
        logit = torch.tensor(np.log(u / (1 - u)))
        optim = torch.optim.Adam([logit], lr=0.05)
        for step in range(steps):
            theta, slope = _bounded(logit, lo, hi)
            grad = _energy(theta, perp, par, smoothness)[1]
            grad *= slope
            logit.grad = torch.from_numpy(grad)
            optim.step()
            if progress is not None:
                progress(level * steps + step + 1, total)
        theta = _bounded(logit, lo, hi)[0]
    return theta


#: The valid values of `separate`'s parameters: λ ≥ 0 (0: no smoothness term), at least one Adam
#: step per level, and a coarsest side (px) of at least 2, which θ's differences need.
PARAM_RANGES = {"smoothness": Interval(at_least=0.0), "steps": Interval(at_least=1), "min_side": Interval(at_least=2)}


def separate(images: np.ndarray, angles_deg: list[float], smoothness: float = 1.0, steps: int = 150,
             min_side: int = 32, progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(R̂, T̂) of a stack (N, H, W, C) with angles (deg), θ varying over the image; ``progress``
    as in `theta_map`."""
    i_perp, i_par, _ = canonical(images, angles_deg)
    if not (i_perp + i_par > 0).any():                          # a dark frame: no light, and no energy to minimize
        return np.zeros(i_perp.shape, np.float32), np.zeros(i_perp.shape, np.float32)
    return fresnel_inverse(i_perp, i_par, theta_map(i_perp, i_par, smoothness, steps, min_side, progress=progress))
