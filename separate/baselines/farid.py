"""Farid & Adelson, "Separating reflections and lighting using independent components
analysis", CVPR 1999.

Two polarization images are a 2×2 linear mixture of reflection and transmission; ICA recovers
the two sources up to scale and order. Here: the two canonical images (the most different
pair of observations); the unmixing is estimated on their horizontal derivatives (natural
images are far more independent and super-Gaussian in the derivative domain, and the mixing
is the same), pooled over the colour channels (the mixing does not depend on wavelength):
whitening, then the rotation maximizing the sum of absolute excess kurtoses (a 1° grid over
90°, refined to 0.02°: the 2×2 ICA has one free angle).

Scale and order, resolved as for a fair comparison: the sources' means are restored and each
source is scaled by least squares so that a·s1 + b·s2 ≈ S0 (the unpolarized
image, which the layers must add up to); the source more correlated with I∥ (where the
reflection is weakest) is the transmission.
"""

from __future__ import annotations

import numpy as np

from separate.baselines.common import canonical


def ica_2x2(x: np.ndarray, max_samples: int = 100_000) -> np.ndarray:
    """Unmixing matrix W (2×2) for rows of ``x`` (2, P): W·(x − mean) has independent rows.

    The rotation after whitening maximizes Σ|excess kurtosis| on a 1° grid over 90°, refined
    on a 0.02° grid; at most ``max_samples`` evenly strided samples are used. A rotation's
    fourth moments are a quartic in (cos a, sin a) of the whitened samples' five fourth-order
    moments, so every grid angle is scored without rotating the samples.
    """
    sample = x[:, :: max(1, x.shape[1] // max_samples)]
    centred = sample - sample.mean(axis=1, keepdims=True)
    evals, evecs = np.linalg.eigh(np.cov(centred))
    whiten = np.diag(1.0 / np.sqrt(np.maximum(evals, 1e-20))) @ evecs.T
    z1, z2 = whiten @ centred
    z1_2, z2_2 = z1 * z1, z2 * z2
    # E[z1^(4-k) z2^k], k = 0..4
    moments = np.array([(z1_2 * z1_2).mean(), (z1_2 * z1 * z2).mean(), (z1_2 * z2_2).mean(),
                        (z1 * z2_2 * z2).mean(), (z2_2 * z2_2).mean()])
    binomial = np.array([1.0, 4.0, 6.0, 4.0, 1.0])
    powers = np.arange(5)

    def scores(angles: np.ndarray) -> np.ndarray:
        """Σ|excess kurtosis| of both rows of rotation(a)·z for each angle a (rad)."""
        c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
        first = (binomial * c ** (4 - powers) * s**powers) @ moments      # c·z1 + s·z2
        second = (binomial * c**powers * (-s) ** (4 - powers)) @ moments   # −s·z1 + c·z2
        return np.abs(first - 3.0) + np.abs(second - 3.0)

    coarse_grid = np.radians(np.arange(0.0, 90.0, 1.0))
    coarse = coarse_grid[np.argmax(scores(coarse_grid))]
    fine_grid = coarse + np.radians(np.arange(-1.0, 1.0, 0.02))
    a = fine_grid[np.argmax(scores(fine_grid))]
    return np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) @ whiten


def separate(images: np.ndarray, angles_deg: list[float]) -> tuple[np.ndarray, np.ndarray]:
    i_perp, i_par, _ = canonical(images, angles_deg)
    shape = i_perp.shape
    x = np.stack([i_perp.ravel(), i_par.ravel()]).astype(np.float64)
    derivatives = np.stack([np.diff(i_perp, axis=1).ravel(), np.diff(i_par, axis=1).ravel()]).astype(np.float64)
    sources = ica_2x2(derivatives) @ x            # the same mixing acts on the images themselves
    s0 = (i_perp + i_par).ravel()
    coef, *_ = np.linalg.lstsq(sources.T, s0, rcond=None)
    sources *= coef[:, None]
    corr = [abs(np.corrcoef(s, i_par.ravel())[0, 1]) for s in sources]
    t_idx = int(np.argmax(corr))
    t_hat = sources[t_idx].reshape(shape).astype(np.float32)
    r_hat = sources[1 - t_idx].reshape(shape).astype(np.float32)
    return r_hat, t_hat
