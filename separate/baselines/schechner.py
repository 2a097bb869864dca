"""Schechner, Shamir & Kiryati, "Polarization and statistical analysis of scenes containing a
semireflector", JOSA A 17(2), 2000.

The two images at the canonical polarizer angles are a 2×2 mixture of the layers whose
coefficients are Fresnel's R_s and R_p at one, unknown, angle of incidence θ. For each θ on a
grid the mixture is inverted in closed form; the θ whose layers have the least mutual
information (the layers are statistically independent) is chosen. Paper defaults: a single
global θ, n = 1.474 here (the glass urd assumes).

Search range (urd's choice, after the criterion collapsed on real scenes, e.g. 95% of a glass
facade's light in R̂ at θ = 87°): θ in 10°–80° in 0.5° steps. Outside it the inversion is
degenerate: below 10° R_s − R_p < 0.003, so the inverse amplifies noise and misregistration by
hundreds; towards grazing incidence R_s and R_p approach 1 and every layer becomes
"reflection". A minimum on either end of the range means the criterion prefers such a
degenerate mixture, and θ falls back to Brewster's angle (56°), where R_p = 0: I∥ = I_T/2 holds
transmitted light alone and R̂ is what I⊥ holds beyond it, the best-conditioned inversion, which
moves only the polarized light into R̂.
"""

from __future__ import annotations

import numpy as np

from separate.baselines.common import Interval, canonical, fresnel_inverse, luminance
from separate.incidence import incidence_by_information
from separate.reference import INCIDENCE_RANGE_DEG

#: The θ grid step (deg) over `separate.reference.INCIDENCE_RANGE_DEG`.
GRID_STEP_DEG = 0.5
#: The valid values of `separate`'s parameters (deg): a fixed θ within the search range, where the
#: inversion is well conditioned (below 10° it amplifies noise by hundreds: module docstring); a grid step of at most 20°, which keeps at least 3
#: grid angles, all below 90° (the grid may pass the range's end by under half a step), and of at
#: least 0.01° (7001 angles; finer only costs time and memory).
PARAM_RANGES = {"theta_deg": Interval(at_least=INCIDENCE_RANGE_DEG[0], at_most=INCIDENCE_RANGE_DEG[1]), "grid_step_deg": Interval(at_least=0.01, at_most=20.0)}


def estimate_theta(i_perp: np.ndarray, i_par: np.ndarray, grid_deg: np.ndarray) -> float:
    """The angle of incidence (rad) minimizing the mutual information of the recovered layers
    over ``grid_deg`` (deg, ascending), on the canonical images' luminance; Brewster's angle if
    the minimum is on the grid's first or last point (module docstring;
    `separate.incidence.incidence_by_information`)."""
    return incidence_by_information(luminance(i_perp), luminance(i_par), grid_deg)


def separate(images: np.ndarray, angles_deg: list[float], theta_deg: float | None = None,
             grid_step_deg: float = GRID_STEP_DEG) -> tuple[np.ndarray, np.ndarray]:
    """(R̂, T̂) with a global angle of incidence; ``theta_deg`` fixes it instead of the MI search.
    φ⊥ is read within ±45° of ``angles_deg[0]`` (`separate.methods` presents the shots at the
    estimated reference first)."""
    i_perp, i_par, _ = canonical(images, angles_deg)
    if theta_deg is not None:
        theta = np.radians(theta_deg)
    else:
        theta = estimate_theta(i_perp, i_par, np.arange(INCIDENCE_RANGE_DEG[0], INCIDENCE_RANGE_DEG[1] + grid_step_deg / 2, grid_step_deg))
    return fresnel_inverse(i_perp, i_par, theta)
