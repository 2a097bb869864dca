"""Optics core against closed forms and round trips."""

import numpy as np
import pytest
import torch

from separate import optics

RNG = np.random.default_rng(7)


@pytest.mark.parametrize("n", [1.33, 1.474, 1.5, 1.7])
def test_brewster_angle_is_atan_n_and_rp_vanishes_there(n):
    theta_b = optics.brewster_angle(n)
    assert theta_b == pytest.approx(np.arctan(n), rel=1e-12)
    r_s, r_p = optics.fresnel_reflectance(np.array(theta_b), n)
    assert r_p == pytest.approx(0.0, abs=1e-15)
    # at Brewster θt = 90° − θB, so r_s = (1 − n²)/(1 + n²)
    assert r_s == pytest.approx(((n**2 - 1) / (n**2 + 1)) ** 2, rel=1e-12)
    # and nowhere else: R_p > 0 a degree either side
    assert min(optics.fresnel_reflectance(np.array([theta_b - 0.0175, theta_b + 0.0175]), n)[1]) > 1e-5


def test_fresnel_textbook_values_at_45_deg_for_n_1_5():
    # Hecht, Optics: for n = 1.5 at 45°, R_s = 0.0920 and R_p = 0.0085 (R_p = R_s²).
    r_s, r_p = optics.fresnel_reflectance(np.radians(45.0), 1.5)
    assert r_s == pytest.approx(0.092, abs=2e-4)
    assert r_p == pytest.approx(0.00847, abs=1e-4)
    assert r_p == pytest.approx(r_s**2, rel=1e-9)
    # closed form at 45°: n·cos θt = √(n² − ½), so r_s = (1 − √(2n² − 1)) / (1 + √(2n² − 1))
    root = np.sqrt(2 * 1.5**2 - 1)
    assert r_s == pytest.approx(((1 - root) / (1 + root)) ** 2, rel=1e-12)


@pytest.mark.parametrize("n", [1.33, 1.474, 1.7])
def test_fresnel_slopes_are_the_derivatives_of_the_reflectances(n):
    theta = np.linspace(0.0, 1.5, 61)
    d_s, d_p = optics.fresnel_reflectance_and_slope(theta, n)[2:]
    step = 1e-6
    (s1, p1), (s0, p0) = optics.fresnel_reflectance(theta + step, n), optics.fresnel_reflectance(theta - step, n)
    np.testing.assert_allclose(d_s[1:], ((s1 - s0) / (2 * step))[1:], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(d_p[1:], ((p1 - p0) / (2 * step))[1:], rtol=1e-6, atol=1e-9)
    assert d_s[0] == 0.0 and d_p[0] == 0.0                       # flat at normal incidence
    assert np.all(d_s[1:] > 0)                                   # R_s rises monotonically
    # R_p has its minimum (zero) at Brewster's angle: its slope changes sign there
    brewster = optics.brewster_angle(n)
    assert np.all(d_p[1:][theta[1:] < brewster - 0.01] < 0) and np.all(d_p[theta > brewster + 0.01] > 0)
    torch_slopes = optics.fresnel_reflectance_and_slope(torch.from_numpy(theta), n)[2:]
    np.testing.assert_allclose(torch_slopes[0].numpy(), d_s, rtol=1e-12)


@pytest.mark.parametrize("n", [1.33, 1.474, 1.5, 1.7])
def test_normal_incidence_and_grazing(n):
    r_s, r_p = optics.fresnel_reflectance(np.array(0.0), n)
    expected = ((n - 1) / (n + 1)) ** 2                 # 0.04 for n = 1.5
    assert r_s == pytest.approx(expected, rel=1e-12) and r_p == pytest.approx(expected, rel=1e-12)
    assert optics.reflectance(np.array(0.0), n) == pytest.approx(expected, rel=1e-12)
    r_s, r_p = optics.fresnel_reflectance(np.array(np.pi / 2 - 1e-9), n)
    assert r_s == pytest.approx(1.0, abs=1e-6) and r_p == pytest.approx(1.0, abs=1e-6)


def test_energy_conservation_reflected_plus_transmitted():
    theta = np.linspace(0, np.radians(89), 50)
    n = 1.474
    r_s, r_p = optics.fresnel_reflectance(theta, n)
    # transmittance from amplitude coefficients: T = n cos θt / cos θi · t²
    cos_i, cos_t = np.cos(theta), np.cos(optics.snell(theta, n))
    t_s = 2 * cos_i / (cos_i + n * cos_t)
    t_p = 2 * cos_i / (n * cos_i + cos_t)
    factor = n * cos_t / cos_i
    np.testing.assert_allclose(r_s + factor * t_s**2, 1.0, atol=1e-12)
    np.testing.assert_allclose(r_p + factor * t_p**2, 1.0, atol=1e-12)


def test_snell():
    assert optics.snell(np.radians(30.0), 1.5) == pytest.approx(np.arcsin(0.5 / 1.5), rel=1e-12)
    theta = np.linspace(0, np.pi / 2, 7)
    np.testing.assert_allclose(1.474 * np.sin(optics.snell(theta, 1.474)), np.sin(theta), atol=1e-15)


def test_malus_law_behind_an_ideal_polarizer():
    # fully polarized light of intensity 1 at angle ψ: I(φ) = cos²(φ − ψ); unpolarized light: I = S0/2 at every φ
    psi = np.radians(23.0)
    phi = np.radians(np.arange(0.0, 180.0, 15.0))
    polarized = np.array([1.0, np.cos(2 * psi), np.sin(2 * psi)])
    np.testing.assert_allclose([optics.intensity_from_stokes(polarized, a) for a in phi], np.cos(phi - psi) ** 2, atol=1e-15)
    np.testing.assert_allclose([optics.intensity_from_stokes(np.array([2.0, 0.0, 0.0]), a) for a in phi], 1.0, atol=1e-15)
    # the reflection of unpolarized light, seen through the polarizer: R_s·cos² + R_p·sin² of (φ − φ⊥), over two;
    # at Brewster only the s-component is reflected, so the reflection vanishes with the polarizer across φ⊥
    theta, phi_perp = np.radians(55.0), np.radians(10.0)
    r_s, r_p = optics.fresnel_reflectance(theta, 1.5)
    seen = [optics.render(1.0, 0.0, theta, phi_perp, a, 1.5) for a in phi]
    np.testing.assert_allclose(seen, (r_s * np.cos(phi - phi_perp) ** 2 + r_p * np.sin(phi - phi_perp) ** 2) / 2, atol=1e-15)
    theta_b = optics.brewster_angle(1.5)
    assert optics.render(1.0, 0.0, theta_b, phi_perp, phi_perp + np.pi / 2, 1.5) == pytest.approx(0.0, abs=1e-15)
    assert optics.render(1.0, 0.0, theta_b, phi_perp, phi_perp, 1.5) == pytest.approx(((1.5**2 - 1) / (1.5**2 + 1)) ** 2 / 2)


def test_rendering_sums_to_the_unpolarized_image():
    i_r, i_t = RNG.random((2, 16, 16, 3))
    theta = RNG.uniform(0, 1.4, (16, 16))
    phi_perp = RNG.uniform(-np.pi / 4, np.pi / 4, (16, 16))
    r_obs, t_obs = optics.observable_layers(i_r, i_t, theta)
    s0 = optics.render(i_r, i_t, theta, phi_perp, 0.3) + optics.render(i_r, i_t, theta, phi_perp, 0.3 + np.pi / 2)
    np.testing.assert_allclose(s0, r_obs + t_obs, atol=1e-12)
    # per pixel, Eq. 1 with the s- and p-reflectances weighted by the polarizer's cos² and sin² of (φ − φ⊥)
    r_s, r_p = optics.fresnel_reflectance(theta, optics.N_GLASS)
    alpha = (r_s * np.cos(0.3 - phi_perp) ** 2 + r_p * np.sin(0.3 - phi_perp) ** 2)[..., None]
    np.testing.assert_allclose(optics.render(i_r, i_t, theta, phi_perp, 0.3), alpha * i_r / 2 + (1 - alpha) * i_t / 2,
                               atol=1e-12)


@pytest.mark.parametrize("angles_deg", [(0, 45, 90), (0, 45, 90, 135)])
def test_render_stokes_canonical_projection_round_trip(angles_deg):
    h, w = 32, 24
    i_r, i_t = RNG.random((2, h, w, 3)) * 2
    theta = RNG.uniform(0.05, 1.45, (h, w))
    phi0 = np.radians(17.0)
    phi_perp = phi0 + RNG.uniform(-np.pi / 4 + 0.01, np.pi / 4 - 0.01, (h, w))
    angles = phi0 + np.radians(angles_deg)
    stack = np.stack([optics.render(i_r, i_t, theta, phi_perp, a) for a in angles])
    stokes = optics.stokes_from_images(stack, angles)
    i_perp, i_par, phi_perp_hat = optics.canonical_projection(stokes, phi_ref=phi0)
    np.testing.assert_allclose(i_perp, optics.render(i_r, i_t, theta, phi_perp, phi_perp), atol=1e-10)
    np.testing.assert_allclose(i_par, optics.render(i_r, i_t, theta, phi_perp, phi_perp + np.pi / 2), atol=1e-10)
    # φ⊥ is defined where the two layers differ; the angle is per pixel and channel
    differs = np.abs(i_perp - i_par) > 1e-6
    np.testing.assert_allclose(phi_perp_hat[differs], np.broadcast_to(phi_perp[..., None], differs.shape)[differs], atol=1e-7)


def test_canonical_projection_resolves_the_90_degree_ambiguity_around_the_reference():
    # The same Stokes vector read with references 90° apart swaps I⊥ and I∥.
    stokes = np.array([1.0, 0.3, 0.1])
    a_perp, a_par, a_phi = optics.canonical_projection(stokes, 0.0)
    b_perp, b_par, b_phi = optics.canonical_projection(stokes, np.pi / 2)
    assert a_perp == pytest.approx(b_par) and a_par == pytest.approx(b_perp)
    assert abs(a_phi) <= np.pi / 4 and abs(b_phi - np.pi / 2) <= np.pi / 4
    assert np.mod(a_phi - b_phi, np.pi / 2) == pytest.approx(0.0, abs=1e-12)
    # reflection brighter than transmission: I⊥ (s-direction) is the brighter canonical image
    perp, par, _ = optics.canonical_projection(stokes, 0.0)
    assert perp > par


def test_least_squares_with_five_nonuniform_angles_matches_the_closed_form():
    s_true = np.stack([RNG.uniform(1, 2, (8, 8)), RNG.uniform(-0.5, 0.5, (8, 8)), RNG.uniform(-0.5, 0.5, (8, 8))])
    angles = np.radians([3.0, 31.0, 70.0, 118.0, 161.0])
    stack = np.stack([optics.intensity_from_stokes(s_true, a) for a in angles])
    np.testing.assert_allclose(optics.stokes_from_images(stack, angles), s_true, atol=1e-12)
    # the textbook closed forms for 0/45/90/135 and 0/45/90, from the same scene
    i0, i45, i90, i135 = (optics.intensity_from_stokes(s_true, np.radians(a)) for a in (0, 45, 90, 135))
    four = optics.stokes_from_images(np.stack([i0, i45, i90, i135]), np.radians([0, 45, 90, 135]))
    np.testing.assert_allclose(four, np.stack([(i0 + i45 + i90 + i135) / 2, i0 - i90, i45 - i135]), atol=1e-12)
    three = optics.stokes_from_images(np.stack([i0, i45, i90]), np.radians([0, 45, 90]))
    np.testing.assert_allclose(three, np.stack([i0 + i90, i0 - i90, 2 * i45 - i0 - i90]), atol=1e-12)


def test_dolp_and_aolp_of_a_known_state():
    stokes = np.array([2.0, 1.0 * np.cos(2 * 0.4), 1.0 * np.sin(2 * 0.4)])
    assert optics.dolp(stokes) == pytest.approx(0.5, rel=1e-6)
    assert optics.aolp(stokes) == pytest.approx(0.4)


def test_torch_and_numpy_agree_and_are_differentiable():
    stack = RNG.random((3, 4, 5))
    angles = np.radians([0, 45, 90])
    ref = optics.canonical_projection(optics.stokes_from_images(stack, angles))
    x = torch.tensor(stack, requires_grad=True)
    out = optics.canonical_projection(optics.stokes_from_images(x, angles))
    for a, b in zip(ref, out):
        np.testing.assert_allclose(b.detach().numpy(), a, atol=1e-12)
    (out[0].sum() + out[1].sum()).backward()
    assert torch.isfinite(x.grad).all()


@pytest.mark.parametrize("angles_deg", [(0, 45), (0, 180, 90), (10, 10, 10, 10)])
def test_stokes_rejects_degenerate_angles(angles_deg):
    with pytest.raises(ValueError, match="expected"):
        optics.stokes_from_images(np.zeros((len(angles_deg), 2, 2)), np.radians(angles_deg))


def test_angle_span_check():
    optics.check_angles(np.radians([0, 45, 90]), min_span=np.radians(90))
    with pytest.raises(ValueError, match="spanning at least 90"):
        optics.check_angles(np.radians([0, 30, 60]), min_span=np.radians(90))


def test_bad_refractive_index():
    with pytest.raises(ValueError, match="n > 1"):
        optics.fresnel_reflectance(np.array(0.3), 0.9)


def test_stokes_from_polarization_inverts_dolp_and_aolp():
    s0 = np.array([[0.2, 0.9], [0.5, 1.0]])
    dolp, aolp = np.array([[0.0, 0.3], [0.7, 1.0]]), np.array([[0.1, -1.2], [0.6, 1.5]])
    stokes = optics.stokes_from_polarization(s0, dolp, aolp)
    assert stokes.shape == (3, 2, 2)
    np.testing.assert_allclose(optics.dolp(stokes, eps=0.0), dolp, atol=1e-12)
    np.testing.assert_allclose(optics.aolp(stokes)[dolp > 0], aolp[dolp > 0], atol=1e-12)
    # Malus: behind a polarizer along the light's angle, S0·(1 + DoLP)/2; across it, S0·(1 − DoLP)/2
    along = optics.intensity_from_stokes(optics.stokes_from_polarization(s0, 0.4, 0.3), 0.3)
    across = optics.intensity_from_stokes(optics.stokes_from_polarization(s0, 0.4, 0.3), 0.3 + np.pi / 2)
    np.testing.assert_allclose(along, s0 * 0.7, atol=1e-12)
    np.testing.assert_allclose(across, s0 * 0.3, atol=1e-12)


def test_radiances_from_layers_inverts_observable_layers():
    rng = np.random.default_rng(5)
    i_r, i_t = rng.uniform(0, 1, (2, 4, 5, 3))
    theta = rng.uniform(0.2, 1.3, (4, 5))
    r_obs, t_obs = optics.observable_layers(i_r, i_t, theta)
    back = optics.radiances_from_layers(r_obs, t_obs, theta)
    np.testing.assert_allclose(back[0], i_r, rtol=1e-12)
    np.testing.assert_allclose(back[1], i_t, rtol=1e-12)
    # at normal incidence ρ = ((n − 1)/(n + 1))², so I_R = R_obs/ρ
    rho0 = ((optics.N_GLASS - 1) / (optics.N_GLASS + 1)) ** 2
    np.testing.assert_allclose(optics.radiances_from_layers(np.full((2, 2), rho0), np.zeros((2, 2)), 0.0)[0], 1.0)
