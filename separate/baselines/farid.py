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
    on a 0.02° grid; at most ``max_samples`` evenly strided samples are used.
    """
    sample = x[:, :: max(1, x.shape[1] // max_samples)]
    centred = sample - sample.mean(axis=1, keepdims=True)
    evals, evecs = np.linalg.eigh(np.cov(centred))
    whiten = np.diag(1.0 / np.sqrt(np.maximum(evals, 1e-20))) @ evecs.T
    z = whiten @ centred

    def rotation(a: float) -> np.ndarray:
        return np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])

    def score(a: float) -> float:
        s = rotation(a) @ z
        return float(np.abs((s**4).mean(axis=1) - 3.0).sum())

    coarse = max(np.radians(np.arange(0.0, 90.0, 1.0)), key=score)
    fine = max(coarse + np.radians(np.arange(-1.0, 1.0, 0.02)), key=score)
    return rotation(fine) @ whiten


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
