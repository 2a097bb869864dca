"""Schechner, Shamir & Kiryati, "Polarization and statistical analysis of scenes containing a
semireflector", JOSA A 17(2), 2000.

The two images at the canonical polarizer angles are a 2×2 mixture of the layers whose
coefficients are Fresnel's R_s and R_p at one, unknown, angle of incidence θ. For each θ on a
grid the mixture is inverted in closed form; the θ whose layers have the least mutual
information (the layers are statistically independent) is chosen. Paper defaults: a single
global θ, n = 1.474 here (the glass urd assumes); grid 2°–88° in 0.5° steps.
"""

from __future__ import annotations

import numpy as np

from separate.baselines.common import canonical, fresnel_inverse, luminance, mutual_information


def estimate_theta(i_perp: np.ndarray, i_par: np.ndarray, grid_deg: np.ndarray) -> float:
    """The angle of incidence (rad) minimizing the mutual information of the recovered layers."""
    small = (slice(None, None, max(1, i_perp.shape[0] // 256)), slice(None, None, max(1, i_perp.shape[1] // 256)))
    scores = []
    for theta in np.radians(grid_deg):
        r, t = fresnel_inverse(i_perp[small], i_par[small], theta)
        scores.append(mutual_information(luminance(r), luminance(t)))
    return float(np.radians(grid_deg[int(np.argmin(scores))]))


def separate(images: np.ndarray, angles_deg: list[float], theta_deg: float | None = None,
             grid_step_deg: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(R̂, T̂) with a global angle of incidence; ``theta_deg`` fixes it instead of the MI search."""
    i_perp, i_par, _ = canonical(images, angles_deg)
    theta = np.radians(theta_deg) if theta_deg is not None else estimate_theta(i_perp, i_par, np.arange(2.0, 88.0, grid_step_deg))
    return fresnel_inverse(i_perp, i_par, theta)
