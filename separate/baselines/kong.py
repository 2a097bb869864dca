"""Kong, Tai & Shin, "A physically-based approach to reflection separation: from physical
modeling to constrained optimization", TPAMI 36(2), 2014 — re-implemented.

Three shots at unknown absolute angles. Per pixel the sinusoid fit gives φ⊥ and the canonical
images I⊥ ≥ I∥, a 2×2 Fresnel mixture of the layers whose coefficients R_s, R_p depend on the
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
surfaces of the pane), and Adam on the penalized energy rather than their solver.
Defaults: λ = 1 (chosen on 32 patches of urd's synthetic benchmark: 0.05 overfits noise and
misalignment, 0.5–2 are within 0.1 dB), 150 Adam steps per level, coarsest side ≥ 32 px.

θ range (urd's choice, as for `separate.baselines.schechner`, after collapses on real scenes):
θ in [10°, 80°]. Below 10° R_s ≈ R_p and the inversion amplifies noise by hundreds; towards
grazing incidence every layer becomes "reflection". If the coarsest level's grid search ends
on either bound, the optimization starts from Brewster's angle instead (the best-conditioned
mixture, R_p = 0), and the bounds keep every pixel's θ inside the range.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from separate import optics
from separate.baselines.common import canonical, fresnel_inverse, luminance, mixture_inverse

PENALTY = 1e3


def _gradient_magnitude(image: torch.Tensor) -> torch.Tensor:
    """|∇image| by forward differences, (H−1)×(W−1)."""
    return torch.sqrt(image.diff(dim=1)[:-1] ** 2 + image.diff(dim=0)[:, :-1] ** 2 + 1e-12)


def _energy(theta: torch.Tensor, i_perp: torch.Tensor, i_par: torch.Tensor, smoothness: float) -> torch.Tensor:
    """The penalized energy of a θ map (rad, H×W) for luminance canonical images (H×W)."""
    side = max(theta.shape)
    r_s, r_p = optics.fresnel_reflectance(theta)
    r_hat, t_hat = mixture_inverse(i_perp, i_par, r_s, r_p)
    gr, gt = _gradient_magnitude(r_hat), _gradient_magnitude(t_hat)
    exclusion = (gr * gt).sum() / torch.sqrt((gr**2).sum() * (gt**2).sum())
    scale = (i_perp + i_par).mean()
    violation = (torch.relu(-r_hat) ** 2 + torch.relu(-t_hat) ** 2).mean() / scale**2
    rough = (theta.diff(dim=1) ** 2).mean() + (theta.diff(dim=0) ** 2).mean()
    return exclusion + PENALTY * violation + smoothness * side**2 * rough


def _bounded(logit: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """θ = lo + (hi − lo)·sigmoid(logit): the bounds held by the parametrization."""
    return lo + (hi - lo) * torch.sigmoid(logit)


def _pyramid(image: np.ndarray, min_side: int) -> list[np.ndarray]:
    """Area-averaged levels, finest first, down to a short side of at least ``min_side``."""
    levels = [image]
    while min(levels[-1].shape) >= 2 * min_side:
        levels.append(cv2.resize(levels[-1], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
    return levels


#: The θ range (deg) every pixel's angle of incidence is held in.
BOUNDS_DEG = (10.0, 80.0)


def theta_map(i_perp: np.ndarray, i_par: np.ndarray, smoothness: float = 1.0, steps: int = 150,
              min_side: int = 32, bounds_deg: tuple[float, float] = BOUNDS_DEG) -> np.ndarray:
    """Per-pixel angle of incidence (rad, H×W) in ``bounds_deg`` from the coarse-to-fine
    constrained optimization (module docstring)."""
    if not 0.0 < bounds_deg[0] < bounds_deg[1] < 90.0:
        raise ValueError(f"expected bounds (lo, hi) with 0 < lo < hi < 90 deg, got {bounds_deg}")
    lo, hi = np.radians(bounds_deg)
    perp_levels = _pyramid(luminance(i_perp).astype(np.float32), min_side)
    par_levels = _pyramid(luminance(i_par).astype(np.float32), min_side)
    grid = np.radians(np.arange(bounds_deg[0] + 1.0, bounds_deg[1], 1.0))
    coarse_perp, coarse_par = torch.from_numpy(perp_levels[-1]), torch.from_numpy(par_levels[-1])
    with torch.no_grad():
        scores = [float(_energy(torch.full(coarse_perp.shape, t, dtype=torch.float64), coarse_perp.double(),
                                coarse_par.double(), smoothness)) for t in grid]
    best = int(np.argmin(scores))
    start = optics.brewster_angle() if best in (0, grid.size - 1) else grid[best]
    theta = np.full(perp_levels[-1].shape, start, np.float32)
    for perp, par in zip(reversed(perp_levels), reversed(par_levels)):
        theta = cv2.resize(theta, (perp.shape[1], perp.shape[0]), interpolation=cv2.INTER_LINEAR)
        u = np.clip((theta - lo) / (hi - lo), 1e-4, 1 - 1e-4)
        logit = torch.tensor(np.log(u / (1 - u)), requires_grad=True)
        perp_t, par_t = torch.from_numpy(perp), torch.from_numpy(par)
        optim = torch.optim.Adam([logit], lr=0.05)
        for _ in range(steps):
            optim.zero_grad()
            _energy(_bounded(logit, lo, hi), perp_t, par_t, smoothness).backward()
            optim.step()
        theta = _bounded(logit, lo, hi).detach().numpy()
    return theta


def separate(images: np.ndarray, angles_deg: list[float], smoothness: float = 1.0, steps: int = 150,
             min_side: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """(R̂, T̂) of a stack (N, H, W, C) with angles (deg), θ varying over the image."""
    i_perp, i_par, _ = canonical(images, angles_deg)
    return fresnel_inverse(i_perp, i_par, theta_map(i_perp, i_par, smoothness, steps, min_side))
