"""Helpers shared by the baselines: parameter ranges, canonical images, Fresnel inversion, FFT operators."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from separate import optics
from separate.optics import mixture_inverse


class Interval(NamedTuple):
    """The valid values of a numeric parameter: each bound that is not None holds
    (``above < x``, ``at_least ≤ x``, ``x < below``, ``x ≤ at_most``)."""

    above: float | None = None
    at_least: float | None = None
    below: float | None = None
    at_most: float | None = None

    def __contains__(self, value: float) -> bool:
        return ((self.above is None or value > self.above) and (self.at_least is None or value >= self.at_least)
                and (self.below is None or value < self.below) and (self.at_most is None or value <= self.at_most))

    def __str__(self) -> str:
        """E.g. "> 0 and < 90"."""
        bounds = zip(("> ", "≥ ", "< ", "≤ "), self)
        return " and ".join(f"{sign}{bound:g}" for sign, bound in bounds if bound is not None)


def canonical(images: np.ndarray, angles_deg: list[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """I⊥, I∥ (H×W×C) and φ⊥ (rad, H×W×C) of a stack, φ⊥ within ±45° of the first angle
    (`separate.methods` presents the shots with the estimated s-direction first)."""
    stokes = optics.stokes_from_images(images, np.radians(angles_deg))
    return optics.canonical_projection(stokes, np.radians(angles_deg[0]))


def fresnel_inverse(i_perp: np.ndarray, i_par: np.ndarray, theta: np.ndarray | float,
                    n: float = optics.N_GLASS) -> tuple[np.ndarray, np.ndarray]:
    """Invert I⊥ = (R_s I_R + (1−R_s) I_T)/2, I∥ = (R_p I_R + (1−R_p) I_T)/2 (Eq. 1 at the canonical
    angles) for the observable layers (R_obs, T_obs) at angle of incidence ``theta`` (rad)."""
    r_s, r_p = optics.fresnel_reflectance(np.asarray(theta, np.float64), n)
    r_s, r_p = optics.expand_map(r_s, i_perp), optics.expand_map(r_p, i_perp)
    r_obs, t_obs = mixture_inverse(i_perp, i_par, r_s, r_p)
    return r_obs.astype(np.float32), t_obs.astype(np.float32)


def luminance(image: np.ndarray) -> np.ndarray:
    return image.mean(axis=-1) if image.ndim == 3 else image


def psf2otf(kernel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Optical transfer function of a small kernel for images of ``shape`` (circular)."""
    padded = np.zeros(shape, np.float64)
    kh, kw = kernel.shape
    padded[:kh, :kw] = kernel
    padded = np.roll(padded, (-(kh // 2), -(kw // 2)), axis=(0, 1))
    return np.fft.fft2(padded)


DX = np.array([[0, 0, 0], [0, -1, 1], [0, 0, 0]], np.float64)
DY = DX.T
LAPLACIAN = np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], np.float64)


def half_quadratic(image: np.ndarray, prior_step, beta0: float, eps: float, beta_max: float = 1e5,
                   keep_below_input: bool = False) -> np.ndarray:
    """min_T ||Δ(T − I)||² + ε||T − I||² + prior(∇T), per channel, by half-quadratic splitting.

    Alternates the gradient sub-problem ``prior_step(gx, gy, beta) -> (gx, gy)`` (a shrinkage)
    with the quadratic sub-problem solved exactly by FFT, doubling β from ``beta0`` to
    ``beta_max``. ``keep_below_input`` projects onto 0 ≤ T ≤ I after every solve.
    """
    h, w = image.shape[:2]
    lap, dx, dy = psf2otf(LAPLACIAN, (h, w)), psf2otf(DX, (h, w)), psf2otf(DY, (h, w))
    data, d2 = np.abs(lap) ** 2 + eps, np.abs(dx) ** 2 + np.abs(dy) ** 2
    out = np.empty_like(image)
    for c in range(image.shape[2]):
        i_hat = np.fft.fft2(image[..., c])
        t = image[..., c].astype(np.float64)
        beta = beta0
        while beta < beta_max:
            t_hat = np.fft.fft2(t)
            gx, gy = prior_step(np.real(np.fft.ifft2(dx * t_hat)), np.real(np.fft.ifft2(dy * t_hat)), beta)
            num = data * i_hat + beta * (np.conj(dx) * np.fft.fft2(gx) + np.conj(dy) * np.fft.fft2(gy))
            t = np.real(np.fft.ifft2(num / (data + beta * d2)))
            if keep_below_input:
                t = np.clip(t, 0, image[..., c])
            beta *= 2
        out[..., c] = t
    return out
