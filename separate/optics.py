"""Optics of a dielectric semi-reflector seen through a linear polarizer.

This module is the one place where the Fresnel, Malus and Stokes formulas live; the
synthesizer, the virtual camera, calibration, the network and the baselines all call it.

Conventions (stated once, here and in the README):

* images are float32, linear, H×W×C (or any shape whose leading axis stacks the shots);
  where a function says it takes *codes*, an unsigned-integer stack stands for linear values
  code / (the dtype's maximum), as urd stores aligned shots (uint16: 65535 = 1.0), so a 24 MP
  stack stays in half the memory until a block of it is needed (`code_scale`, `to_float`);
* angles are radians inside the code (degrees only at the CLI and in manifests);
* a polarizer angle φ is measured in the image plane from the +x axis (towards increasing
  column), counter-clockwise as the viewer sees the image (towards row 0);
* θ is the angle of incidence on the glass, φ⊥ the direction of s-polarization (perpendicular
  to the plane of incidence) in the same image-plane convention;
* Stokes: I_φ = (S0 + S1·cos 2φ + S2·sin 2φ) / 2 for an ideal linear polarizer.

Every function accepts numpy arrays and, where it makes sense, torch tensors of any shape
(broadcasting applies); the result has the input's type.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

#: Refractive index of window glass used by default (the paper's value).
N_GLASS = 1.474
#: Display gamma assumed for 8-bit photos (the paper's inverse gamma 2.2).
GAMMA = 2.2
#: The paper's polarizer angles (deg from the first shot), and the angles from the reference at
#: which urd presents shots to every polarization method (`separate.presentation.present`).
PAPER_ANGLES_DEG = (0.0, 45.0, 90.0)

Array = Any  # numpy.ndarray or torch.Tensor


def code_scale(images: np.ndarray) -> float:
    """The linear value of one code of a stack: 1/max for 8- and 16-bit codes (uint16: 1/65535),
    1 for floats. TypeError for other dtypes (signed or wider integers, bool)."""
    if np.issubdtype(images.dtype, np.floating):
        return 1.0
    if images.dtype.kind == "u" and images.dtype.itemsize <= 2:          # either byte order
        return 1.0 / float(np.iinfo(images.dtype).max)
    raise TypeError(f"expected float images or 8- or 16-bit codes (uint8, uint16), got {images.dtype}")


def to_float(images: np.ndarray) -> np.ndarray:
    """Linear float32 values of float images or codes (`code_scale`); float32 is returned as is."""
    if images.dtype == np.float32:
        return images
    return np.multiply(images, np.float32(code_scale(images)), dtype=np.float32)


def _xp(x: Array):
    """Return the array module (numpy or torch) of ``x``."""
    if type(x).__module__.startswith("torch"):
        import torch

        return torch
    return np


def _like(value: np.ndarray, x: Array) -> Array:
    """Convert a numpy constant to the type, dtype and device of ``x``."""
    if type(x).__module__.startswith("torch"):
        import torch

        return torch.as_tensor(value, dtype=x.dtype, device=x.device)
    return np.asarray(value, dtype=np.result_type(x, np.float32))


def snell(theta: Array, n: float = N_GLASS) -> Array:
    """Angle of refraction (rad) for incidence ``theta`` (rad) from air into index ``n``."""
    return _refraction(_xp(theta).sin(theta), n)


def _refraction(sin_i: Array, n: float) -> Array:
    """`snell` from sin θ."""
    return _xp(sin_i).arcsin(sin_i / n)


def brewster_angle(n: float = N_GLASS) -> float:
    """Brewster angle (rad), where R_p vanishes: θ_B = atan(n)."""
    return float(np.arctan(n))


def _fresnel_amplitudes(theta: Array, n: float) -> tuple[Array, Array, Array, Array, Array]:
    """Amplitude reflection coefficients (r_s, r_p) of one air–dielectric interface, their
    denominators (cos θ + n cos θ_t, n cos θ + cos θ_t) and sin θ, at θ (rad)."""
    if n <= 1.0:
        raise ValueError(f"expected a refractive index n > 1, got {n}")
    xp = _xp(theta)
    sin_i, cos_i = xp.sin(theta), xp.cos(theta)
    cos_t = xp.cos(_refraction(sin_i, n))
    den_s, den_p = cos_i + n * cos_t, n * cos_i + cos_t
    return (cos_i - n * cos_t) / den_s, (n * cos_i - cos_t) / den_p, den_s, den_p, sin_i


def fresnel_reflectance(theta: Array, n: float = N_GLASS) -> tuple[Array, Array]:
    """Power reflectances (R_s, R_p) of one air–dielectric interface.

    Args:
        theta: angle of incidence (rad) in [0, π/2], any shape.
        n: refractive index of the dielectric (> 1).

    Returns:
        R_s, R_p in [0, 1], the shape of ``theta``.
    """
    r_s, r_p = _fresnel_amplitudes(theta, n)[:2]
    return r_s**2, r_p**2


def fresnel_reflectance_and_slope(theta: Array, n: float = N_GLASS) -> tuple[Array, Array, Array, Array]:
    """(R_s, R_p) of `fresnel_reflectance` and their derivatives (dR_s/dθ, dR_p/dθ) (per rad), for
    θ in [0, π/2), from one evaluation of the amplitudes.

    With k = n cos θ_t (k² = n² − sin²θ), both amplitudes have dr/dθ = −2(n² − 1) sin θ /
    (k · denominator²), and dR/dθ = 2 r dr/dθ.
    """
    r_s, r_p, den_s, den_p, sin_i = _fresnel_amplitudes(theta, n)
    slope = -2.0 * (n * n - 1.0) * sin_i / _xp(theta).sqrt(n * n - sin_i**2)
    return r_s**2, r_p**2, 2 * r_s * slope / den_s**2, 2 * r_p * slope / den_p**2


def reflectance(theta: Array, n: float = N_GLASS) -> Array:
    """Reflectance ρ = (R_s + R_p)/2 of unpolarized light at incidence ``theta`` (rad)."""
    r_s, r_p = fresnel_reflectance(theta, n)
    return (r_s + r_p) / 2


def dolp_limits(theta: Array, n: float = N_GLASS) -> tuple[Array, Array]:
    """Largest DoLP of light from a pane at incidence ``theta`` (rad), unpolarized layers.

    A pixel's linear polarization is Δ·(I_R − I_T) along φ⊥ over S0 = ρ·I_R + (1−ρ)·I_T
    (ρ = (R_s+R_p)/2, Δ = (R_s−R_p)/2). Where the transmission dominates (I_T > I_R) it points
    along φ⊥ + 90° with DoLP at most Δ/(1−ρ) (reached where I_R = 0); where the reflection
    dominates, along φ⊥ with DoLP at most Δ/ρ (where I_T = 0).

    Returns:
        (transmission_max, reflection_max) = (Δ/(1−ρ), Δ/ρ), the shape of ``theta``.
    """
    r_s, r_p = fresnel_reflectance(theta, n)
    rho, delta = (r_s + r_p) / 2, (r_s - r_p) / 2
    return delta / (1.0 - rho), delta / rho


def mixing_alpha(theta: Array, phi_perp: Array, phi: Array, n: float = N_GLASS) -> Array:
    """Mixing coefficient α = R_s·cos²(φ−φ⊥) + R_p·sin²(φ−φ⊥) of the paper's Eq. 1.

    All angles in radians; arguments broadcast against each other.
    """
    xp = _xp(theta)
    r_s, r_p = fresnel_reflectance(theta, n)
    c2 = xp.cos(phi - phi_perp) ** 2
    return r_s * c2 + r_p * (1.0 - c2)


def expand_map(angle_map: Array, image: Array) -> Array:
    """Give an H×W map a trailing channel axis when ``image`` is H×W×C."""
    ndim = getattr(angle_map, "ndim", 0)
    if ndim and ndim == image.ndim - 1:
        return angle_map[..., None]
    return angle_map


def render(
    i_r: Array, i_t: Array, theta: Array, phi_perp: Array, phi: float, n: float = N_GLASS
) -> Array:
    """Image through a polarizer at angle ``phi`` (paper Eq. 1).

    I_φ = α·I_R/2 + (1−α)·I_T/2.

    Args:
        i_r, i_t: reflected and transmitted radiance at the glass, H×W×C (or H×W), linear.
        theta: angle of incidence (rad), scalar or H×W map.
        phi_perp: s-direction φ⊥ (rad), scalar or H×W map.
        phi: polarizer angle (rad), scalar.
        n: refractive index.

    Returns:
        The observation, same shape as ``i_r``.
    """
    alpha = expand_map(mixing_alpha(theta, phi_perp, phi, n), i_r)
    return alpha * i_r / 2 + (1.0 - alpha) * i_t / 2


def diattenuate(stokes: Array, along: Array, across: Array, axis: Array, phase_sign: Array | float = 1.0) -> Array:
    """Stokes stack (3, ...) after a linear diattenuator: intensity transmittance ``along`` for
    light polarized along ``axis`` (rad) and ``across`` for light polarized across it (a
    dielectric interface's Fresnel reflection or transmission, an ideal polarizer at 1 and 0).

    In the axis's frame (`rotate_stokes`) S0' = (a + b)/2·S0 + (a − b)/2·S1,
    S1' = (a − b)/2·S0 + (a + b)/2·S1, S2' = ±√(ab)·S2; the result is turned back. The sign,
    ``phase_sign``, is −1 where the two components' amplitudes come out in opposite phase
    relative to their phase below Brewster's angle (a reflection beyond it, `pane_stokes`).
    ``along``, ``across``, ``axis`` and ``phase_sign`` broadcast against ``stokes[0]`` (give H×W
    maps a channel axis with `expand_map` for H×W×C stacks).
    """
    xp = _xp(stokes)
    s0, s1, s2 = rotate_stokes(stokes, axis)
    half_sum, half_diff = (along + across) / 2, (along - across) / 2
    turned = xp.stack([half_sum * s0 + half_diff * s1, half_diff * s0 + half_sum * s1,
                       phase_sign * xp.sqrt(along * across) * s2])
    return rotate_stokes(turned, -axis)


def pane_stokes(stokes_r: Array, stokes_t: Array, theta: Array, phi_perp: Array, n: float = N_GLASS) -> tuple[Array, Array]:
    """The light a camera receives from a pane: the reflected and the transmitted part, each a
    Stokes stack (3, H, W, C) (or (3, H, W)).

    ``stokes_r`` is the light that the pane reflects towards the camera, ``stokes_t`` the light
    from behind it, each of any polarization (an unpolarized photo I is (I, 0, 0)); the pane
    reflects with R_s, R_p and transmits with 1 − R_s, 1 − R_p along / across its s-direction
    φ⊥ (`diattenuate`; one interface, as `render`); beyond Brewster's angle the reflected p
    amplitude changes sign against the s amplitude, which turns the sign of the reflected light's
    S2 in the s frame. Their sum seen through a polarizer at φ is
    `intensity_from_stokes`, and for unpolarized layers equals `render`; their S0 are the
    observable layers (R_obs, T_obs) of the separation target (`observable_layers`).

    Args:
        stokes_r, stokes_t: (3, H, W, C) or (3, H, W) linear Stokes stacks.
        theta: angle of incidence (rad), scalar or H×W map.
        phi_perp: s-direction φ⊥ (rad), scalar or H×W map.
        n: refractive index.
    """
    amp_s, amp_p = _fresnel_amplitudes(theta, n)[:2]                  # amp_s < 0; amp_p > 0 below θ_B, < 0 beyond
    r_s, r_p, axis, sign = (expand_map(x, stokes_r[0]) for x in (amp_s**2, amp_p**2, phi_perp, _xp(amp_p).sign(amp_p)))
    return diattenuate(stokes_r, r_s, r_p, axis, sign), diattenuate(stokes_t, 1.0 - r_s, 1.0 - r_p, axis)


def observable_layers(
    i_r: Array, i_t: Array, theta: Array, n: float = N_GLASS
) -> tuple[Array, Array]:
    """The separation target used everywhere in urd.

    R_obs = ρ·I_R and T_obs = (1−ρ)·I_T with ρ = (R_s+R_p)/2, so that R_obs + T_obs = S0,
    the image an unpolarized camera would record.

    Args:
        i_r, i_t: H×W×C (or H×W) radiance at the glass, linear.
        theta: angle of incidence (rad), scalar or H×W map.

    Returns:
        (R_obs, T_obs), each the shape of ``i_r``.
    """
    rho = expand_map(reflectance(theta, n), i_r)
    return rho * i_r, (1.0 - rho) * i_t


def radiances_from_layers(r_obs: Array, t_obs: Array, theta: Array, n: float = N_GLASS) -> tuple[Array, Array]:
    """Inverse of `observable_layers`: the radiances (I_R, I_T) at the glass, I_R = R_obs/ρ and
    I_T = T_obs/(1−ρ), for layers H×W×C (or H×W) and ``theta`` (rad) a scalar or an H×W map."""
    rho = expand_map(reflectance(theta, n), r_obs)
    return r_obs / rho, t_obs / (1.0 - rho)


def photo_to_linear(img_u8: np.ndarray) -> np.ndarray:
    """An 8-bit photo (any shape, uint8), taken as display-encoded with the paper's gamma 2.2,
    → linear float32 in [0, 1]: how synthesis and the virtual camera read their photos (files
    a user hands to urd follow `urd.core.images` instead)."""
    return (img_u8.astype(np.float32) / 255.0) ** GAMMA


def parabola_aoi(
    theta_c: float, distance: float, length: float, sagitta: float, convexity: int, t: np.ndarray
) -> np.ndarray:
    """Angle of incidence (rad) along a parabolic glass profile, in closed form.

    In the plane of incidence the camera is at the origin looking along +y; the surface point
    P_S = (0, d) is seen at incidence ``theta_c``. The profile is x(t) = P_S + t·τ + κt²·ν with
    tangent τ = (cos θc, sin θc), normal ν = (sin θc, −cos θc) and κ = ±4·sagitta/ℓ², over
    t ∈ [−ℓ/2, ℓ/2] (``t`` given in units of ℓ, in [−½, ½]). At each point the normal is
    ν − 2κt·τ and the angle of incidence is the angle between it and the viewing ray.
    A flat pane is ``sagitta`` = 0; ``convexity`` is ±1.
    """
    tau = np.array([np.cos(theta_c), np.sin(theta_c)])
    nu = np.array([np.sin(theta_c), -np.cos(theta_c)])
    kappa = convexity * 4.0 * sagitta / length**2
    tt = t * length
    points = np.array([0.0, distance])[:, None] + tau[:, None] * tt + nu[:, None] * kappa * tt**2
    normals = nu[:, None] - 2.0 * kappa * tt * tau[:, None]
    cos_aoi = np.abs((points * normals).sum(0)) / (np.linalg.norm(points, axis=0) * np.linalg.norm(normals, axis=0))
    return np.arccos(np.clip(cos_aoi, 0.0, 1.0))


def stokes_matrix(angles: Sequence[float]) -> np.ndarray:
    """Measurement matrix A (N×3), rows (1, cos 2φ, sin 2φ)/2, so that I = A·S."""
    phi = np.asarray(angles, dtype=np.float64)
    return np.stack([np.ones_like(phi), np.cos(2 * phi), np.sin(2 * phi)], axis=1) / 2


def stokes_fit(angles: Sequence[float]) -> np.ndarray:
    """The least-squares Stokes fit of shots at ``angles`` (rad) as a matrix (3×N, float64): S =
    F·I, the pseudo-inverse of `stokes_matrix` (applied block by block to large stacks)."""
    return np.linalg.pinv(stokes_matrix(angles))


#: Smallest span (deg, mod 180) of the shots' angles that urd's network takes: re-rendering them at
#: 0/45/90° from their Stokes fit raises the noise by 1.36× RMS (1.9× worst shot) at 0/35/70°,
#: 1.9× (3×) at 0/30/60°; 0/45/90° with ±8° errors (calibrated angles) spans 74° at least.
MIN_SPAN_DEG = 70.0


def angle_span(angles: Sequence[float]) -> float:
    """The span (rad) of polarizer angles (rad) taken mod π: π less the widest gap between them."""
    wrapped = np.sort(np.mod(np.asarray(angles, dtype=np.float64), np.pi))
    return float(np.pi - np.diff(np.concatenate([wrapped, wrapped[:1] + np.pi])).max())


def stokes_noise_gain(angles: Sequence[float]) -> float:
    """The RMS noise of the fitted S1, S2 from shots at ``angles`` (rad) over that from 0/45/90°,
    each shot as noisy: 1 at 0/45/90°, 0.82 at 0/60/120°, 1.8 at 0/30/60°, 14 at 0/10/20°."""
    def rms(phi: Sequence[float]) -> float:
        matrix = stokes_matrix(phi)
        return float(np.sqrt(np.diag(np.linalg.inv(matrix.T @ matrix))[1:].mean()))
    return rms(angles) / rms(np.radians(PAPER_ANGLES_DEG))


def check_angles(angles: Sequence[float], min_span: float = 0.0) -> np.ndarray:
    """Validate polarizer angles (rad) for a Stokes fit and return them as float64.

    Raises ValueError unless there are at least 3 angles giving a well-conditioned fit and,
    when ``min_span`` > 0, the angles (mod π) span at least ``min_span`` radians.
    """
    phi = np.asarray(angles, dtype=np.float64)
    if phi.ndim != 1 or phi.size < 3:
        raise ValueError(f"expected at least 3 polarizer angles, got {np.degrees(phi).round(2).tolist()} deg")
    if not np.isfinite(phi).all():
        raise ValueError(f"expected finite polarizer angles, got {np.degrees(phi).round(2).tolist()} deg")
    if np.linalg.cond(stokes_matrix(phi)) > 100:
        raise ValueError(
            "expected polarizer angles that determine S0, S1, S2: at least 3 directions (mod 180 deg) spread "
            f"over the half turn, like 0, 45, 90; got {np.degrees(phi).round(2).tolist()} deg"
        )
    if min_span > 0:
        span = angle_span(phi)
        if span < min_span - 1e-9:
            raise ValueError(
                f"expected polarizer angles spanning at least {np.degrees(min_span):.0f} deg, "
                f"got {np.degrees(phi).round(2).tolist()} deg (span {np.degrees(span):.1f} deg)"
            )
    return phi


def stokes_from_images(images: Array, angles: Sequence[float]) -> Array:
    """Least-squares linear Stokes parameters from N ≥ 3 polarizer angles.

    Exact for 0/45/90 and 0/45/90/135 and for any N ≥ 3 well-spread angles without noise.

    Args:
        images: (N, ...) stack of linear observations, one per angle.
        angles: N polarizer angles (rad).

    Returns:
        (3, ...) stack S0, S1, S2, same type as ``images``.
    """
    phi = check_angles(angles)
    if images.shape[0] != phi.size:
        raise ValueError(f"expected {phi.size} images (one per angle), got {images.shape[0]}")
    pinv = _like(stokes_fit(phi), images)
    if _xp(images) is np:
        return np.tensordot(pinv, images, axes=1)
    return _xp(images).tensordot(pinv, images, dims=1)


def intensity_from_stokes(stokes: Array, phi: float) -> Array:
    """Intensity behind an ideal polarizer at ``phi`` (rad) for Stokes stack (3, ...)."""
    return (stokes[0] + stokes[1] * np.cos(2 * phi) + stokes[2] * np.sin(2 * phi)) / 2


def stokes_from_polarization(s0: np.ndarray, dolp: np.ndarray | float, aolp: np.ndarray | float) -> np.ndarray:
    """Stokes stack (3, ...) of light of intensity ``s0`` with degree ``dolp`` and angle ``aolp``
    (rad) of linear polarization: the inverse of `dolp` and `aolp` (numpy; arguments broadcast)."""
    return np.stack(np.broadcast_arrays(s0, s0 * dolp * np.cos(2 * aolp), s0 * dolp * np.sin(2 * aolp)))


def dolp(stokes: Array, eps: float = 1e-8, floor: float | None = None) -> Array:
    """Degree of linear polarization sqrt(S1²+S2²)/S0 for a (3, ...) stack: in [0, 1] for
    physical Stokes vectors, above 1 where noise makes them unphysical (not clipped). S0 + ``eps``
    is the divisor, or, with ``floor``, S0 read as at least ``floor`` (dark or negative S0)."""
    xp = _xp(stokes)
    s0 = stokes[0] + eps if floor is None else xp.maximum(stokes[0], _like(np.asarray(floor), stokes))
    return xp.hypot(stokes[1], stokes[2]) / s0


def aolp(stokes: Array) -> Array:
    """Angle of linear polarization ½·atan2(S2, S1) (rad) in (−π/2, π/2] for a (3, ...) stack."""
    xp = _xp(stokes)
    return 0.5 * xp.arctan2(stokes[2], stokes[1])


def axis_gap_deg(a_deg: Array, b_deg: Array) -> Array:
    """Signed difference a − b of two polarizer or polarization axes (deg, numpy), wrapped to
    [−90°, 90°): an axis repeats every 180°."""
    return np.mod(np.asarray(a_deg) - b_deg + 90.0, 180.0) - 90.0


def rotate_stokes(stokes: Array, phi_ref: Array) -> Array:
    """Stokes stack (3, ...) in the frame of the polarizer angle ``phi_ref`` (rad; a scalar or a
    map broadcasting against ``stokes[0]``): S1' = S1 cos 2φ + S2 sin 2φ, S2' = −S1 sin 2φ +
    S2 cos 2φ, so that I at ``phi_ref`` + ψ is (S0 + S1' cos 2ψ + S2' sin 2ψ)/2."""
    xp = _xp(stokes)
    two_phi = 2 * _like(phi_ref, stokes)
    c, s = xp.cos(two_phi), xp.sin(two_phi)
    return xp.stack([stokes[0], stokes[1] * c + stokes[2] * s, -stokes[1] * s + stokes[2] * c])


def mixture_coefficients(r_s: Array, r_p: Array) -> tuple[Array, Array]:
    """(a, b) with R_obs = a·I⊥ + b·I∥ (and T_obs = I⊥ + I∥ − R_obs) for reflectances R_s > R_p:
    the inverse of Eq. 1 at the canonical angles, a = q(1 − R_p), b = −q(1 − R_s),
    q = (R_s + R_p)/(R_s − R_p) (numpy or torch, broadcasting)."""
    ratio = (r_s + r_p) / (r_s - r_p)
    return ratio * (1 - r_p), -ratio * (1 - r_s)


def mixture_coefficient_slopes(r_s: Array, r_p: Array, dr_s: Array, dr_p: Array) -> tuple[Array, Array]:
    """Derivatives (da, db) of `mixture_coefficients` for reflectance derivatives dR_s, dR_p (e.g.
    per radian of θ, `fresnel_reflectance_and_slope`)."""
    ratio = (r_s + r_p) / (r_s - r_p)
    dratio = 2 * (r_s * dr_p - r_p * dr_s) / (r_s - r_p) ** 2
    return dratio * (1 - r_p) - ratio * dr_p, ratio * dr_s - dratio * (1 - r_s)


def mixture_inverse(i_perp: Array, i_par: Array, r_s: Array, r_p: Array) -> tuple[Array, Array]:
    """The observable layers (R_obs, T_obs) of canonical images I⊥, I∥ for reflectances R_s > R_p
    (`mixture_coefficients`; numpy or torch, broadcasting); they sum to S0 = I⊥ + I∥."""
    a, b = mixture_coefficients(r_s, r_p)
    r_obs = a * i_perp + b * i_par
    return r_obs, i_perp + i_par - r_obs


def canonical_projection(stokes: Array, phi_ref: float = 0.0) -> tuple[Array, Array, Array]:
    """Project onto the canonical polarization angles (paper Eq. 2).

    I_φ = I⊥·cos²(φ−φ⊥) + I∥·sin²(φ−φ⊥). The fit determines φ⊥ only up to 90°: swapping φ⊥
    and φ∥ swaps I⊥ and I∥. Like the paper, urd resolves it by taking φ⊥ within ±45° of the
    reference ``phi_ref``: the glass's s-direction estimated from the shots
    (`separate.reference`), which the methods present as their first angle. I⊥ may be darker
    than I∥ (it is wherever the transmission outshines the reflection).

    Args:
        stokes: (3, ...) stack S0, S1, S2.
        phi_ref: reference angle (rad).

    Returns:
        (I⊥, I∥, φ⊥) with φ⊥ − phi_ref in [−π/4, π/4]; I⊥ + I∥ = S0.
    """
    xp = _xp(stokes)
    s1, s2, sign = _canonical_frame(stokes, phi_ref)
    i_perp, i_par = _canonical_pair(stokes[0], s1, s2, sign)
    return i_perp, i_par, phi_ref + 0.5 * xp.arctan2(sign * s2, sign * s1)


def canonical_intensities(stokes: Array, phi_ref: float = 0.0) -> tuple[Array, Array]:
    """(I⊥, I∥) of `canonical_projection`, without φ⊥ (no arctangent: the network's input)."""
    return _canonical_pair(stokes[0], *_canonical_frame(stokes, phi_ref))


def _canonical_frame(stokes: Array, phi_ref: float) -> tuple[Array, Array, Array]:
    """S1, S2 in the frame of ``phi_ref`` (rad) and the sign (±1) that puts φ⊥ within ±45° of it."""
    xp = _xp(stokes)
    c, s = float(np.cos(2 * phi_ref)), float(np.sin(2 * phi_ref))
    s1 = stokes[1] * c + stokes[2] * s
    s2 = -stokes[1] * s + stokes[2] * c
    sign = xp.where(s1 >= 0, 1.0, -1.0)
    if xp is not np:
        sign = sign.to(stokes.dtype)
    return s1, s2, sign


def _canonical_pair(s0: Array, s1: Array, s2: Array, sign: Array) -> tuple[Array, Array]:
    """I⊥ = (S0 + sign·|S12|)/2 and I∥ = (S0 − sign·|S12|)/2 in the frame of `_canonical_frame`."""
    diff = sign * _xp(s0).sqrt(s1**2 + s2**2)
    return (s0 + diff) / 2, (s0 - diff) / 2
