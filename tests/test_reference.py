"""The reference angle: φ⊥ estimated from the shots, the shots presented at it, and methods
whose results do not depend on where the photographer (or a mosaic camera) starts."""

import cv2
import numpy as np
import pytest
import skimage.data

from separate import metrics, optics
from separate.baselines import kong, schechner
from separate.baselines.common import canonical
from separate.methods import get_method
from separate.reference import Basis, estimate_reference, estimate_reference_deg, feasible_theta_deg, polarization_warnings, presence_map
from separate.presentation import present

SIZE = 64
PHI_PERP_DEG = 5.0 + 22.5 * np.arange(8)            # anywhere in [0°, 180°)
ANGLE_SETS = [(0.0, 45.0, 90.0, 135.0), (0.0, 60.0, 120.0)]


def layers(size=SIZE, k_r=1.5, k_t=0.6):
    refl = optics.photo_to_linear(cv2.resize(skimage.data.astronaut(), (size, size), interpolation=cv2.INTER_AREA)) * k_r
    trans = optics.photo_to_linear(cv2.resize(skimage.data.coffee()[:, 100:500], (size, size), interpolation=cv2.INTER_AREA)) * k_t
    return refl, trans


def scene(phi_perp_deg, angles_deg, theta_deg=55.0, noise=0.0, seed=0, k_r=1.5, k_t=0.6):
    """Shots (N, H, W, 3) of a pane at θ and φ⊥ and the observable layers (R_obs, T_obs)."""
    refl, trans = layers(k_r=k_r, k_t=k_t)
    theta, phi_perp = np.radians(theta_deg), np.radians(phi_perp_deg)
    shots = np.stack([optics.render(refl, trans, theta, phi_perp, np.radians(a)) for a in angles_deg])
    shots = shots + np.random.default_rng(seed).normal(0.0, noise, shots.shape)
    r_obs, t_obs = optics.observable_layers(refl, trans, theta)
    return np.clip(shots, 0, None).astype(np.float32), r_obs.astype(np.float32), t_obs.astype(np.float32)


def angle_error(a_deg, b_deg):
    return abs((a_deg - b_deg + 90.0) % 180.0 - 90.0)


@pytest.mark.parametrize("angles", ANGLE_SETS)
def test_estimate_reference_finds_the_s_direction_anywhere(angles):
    for phi in PHI_PERP_DEG:
        shots, _, _ = scene(phi, angles, noise=0.002, seed=int(phi))
        estimate = estimate_reference(shots, angles)
        assert angle_error(estimate.reference_deg, phi) < 1.0, (phi, estimate)
        assert 0.0 <= estimate.reference_deg < 180.0 and estimate.axis_strength > 0.9
    # a transmission-dominated pane (weak, one-sided polarization along φ⊥ + 90°) is read as such
    shots, _, _ = scene(100.0, angles, theta_deg=65.0, k_r=0.05, k_t=1.0)
    estimate = estimate_reference(shots, angles)
    assert estimate.basis is Basis.TRANSMISSION and angle_error(estimate.reference_deg, 100.0) < 1.0
    assert estimate_reference_deg(shots, angles) == estimate.reference_deg


def test_present_is_an_exact_re_rendering_from_any_angles():
    rng = np.random.default_rng(1)
    i_r, i_t = rng.random((2, 24, 20, 3)).astype(np.float32)
    theta, phi_perp = rng.uniform(0.2, 1.3, (24, 20)), rng.uniform(0, np.pi, (24, 20))
    for angles in ([3.0, 31.0, 70.0, 118.0, 161.0], [0.0, 60.0, 120.0], [10.0, 55.0, 100.0, 145.0]):
        shots = np.stack([optics.render(i_r, i_t, theta, phi_perp, np.radians(a)) for a in angles]).astype(np.float32)
        shown, shown_angles = present(shots, angles, 200.0)
        assert shown.shape == (3, 24, 20, 3) and shown.dtype == np.float32
        np.testing.assert_allclose(shown_angles, [20.0, 65.0, 110.0])
        expected = np.stack([optics.render(i_r, i_t, theta, phi_perp, np.radians(a)) for a in shown_angles])
        np.testing.assert_allclose(shown, expected, atol=2e-6)
        # and back: presenting the presented shots at the original angles' reference restores them
        again, _ = present(shown, shown_angles, angles[0])
        direct, _ = present(shots, angles, angles[0])
        np.testing.assert_allclose(again, direct, atol=2e-6)
    # a stack already at the reference + 0/45/90° (mod 180°) is handed back as it is
    shots = np.stack([optics.render(i_r, i_t, theta, phi_perp, np.radians(a)) for a in (30, 75, 120)]).astype(np.float32)
    same, angles = present(shots, [210.0, 255.0, 300.0], 30.0)
    assert same is shots and angles == [30.0, 75.0, 120.0]


def test_argument_checks_say_what_was_expected():
    shots, _, _ = scene(30.0, (0, 45, 90))
    with pytest.raises(TypeError, match="expected images as a numpy array"):
        estimate_reference_deg(shots.tolist(), [0, 45, 90])
    with pytest.raises(ValueError, match=r"expected a stack of shape \(N>=3, H, W, C\)"):
        estimate_reference_deg(shots[:2], [0, 45])
    with pytest.raises(ValueError, match="expected 3 angles"):
        present(shots, [0, 45], 10.0)
    with pytest.raises(ValueError, match="expected polarizer angles that determine"):
        presence_map(shots, [0, 180, 90])
    with pytest.raises(ValueError, match="expected a finite reference"):
        present(shots, [0, 45, 90], float("nan"))
    with pytest.raises(ValueError, match="expected reference 'auto', 'global' or"):
        get_method("schechner", reference="east")


@pytest.mark.slow
@pytest.mark.parametrize("angles", ANGLE_SETS)
def test_results_do_not_depend_on_where_the_angles_start(angles):
    # a pane whose angle of incidence runs from 40° to 70° across the image (Schechner's single
    # θ is then not exact); Schechner on noise-free shots (its MI minimum moves by a degree or
    # two with the noise, whatever φ⊥ is), the network also on noisy ones
    network, _ = get_method("network", precision="fp32")
    sch, _ = get_method("schechner")
    theta = np.broadcast_to(np.linspace(40.0, 70.0, SIZE)[None, :], (SIZE, SIZE))
    psnr = {"network": [], "network, noisy": [], "schechner": [], "network, reference at the first shot": []}
    for phi in PHI_PERP_DEG:
        shots, r_obs, t_obs = scene(phi, angles, theta_deg=theta)
        noisy, _, _ = scene(phi, angles, theta_deg=theta, noise=0.002, seed=7)
        psnr["network"].append(metrics.psnr(network(shots, list(angles))[1], t_obs))
        psnr["network, noisy"].append(metrics.psnr(network(noisy, list(angles))[1], t_obs))
        psnr["schechner"].append(metrics.psnr(sch(shots, list(angles))[1], t_obs))
        psnr["network, reference at the first shot"].append(metrics.psnr(network(shots, list(angles), angles[0])[1], t_obs))
    spread = {k: float(np.ptp(v)) for k, v in psnr.items()}
    assert max(spread["network"], spread["network, noisy"], spread["schechner"]) <= 0.5, spread
    assert min(psnr["network"]) > metrics.psnr(r_obs + t_obs, t_obs) + 5
    # the old rule (φ⊥ within ±45° of the first shot) fails for φ⊥ far from it
    assert spread["network, reference at the first shot"] > 5, spread


def test_a_forced_reference_wins_and_the_policy_is_recorded():
    angles = [0.0, 45.0, 90.0]
    shots, _, t_obs = scene(60.0, angles)
    auto, info = get_method("schechner")
    assert info["reference_policy"].startswith("auto")
    fixed, fixed_info = get_method("schechner", reference=60.0)
    assert fixed_info["reference_policy"].startswith("fixed: 60")
    np.testing.assert_allclose(fixed(shots, angles)[1], auto(shots, angles)[1], atol=1e-5)
    wrong = fixed(shots, angles, 150.0)[1]                       # run's own reference_deg wins
    assert metrics.psnr(wrong, t_obs) < metrics.psnr(auto(shots, angles)[1], t_obs) - 10
    assert get_method("li-brown")[1]["reference_policy"].startswith("not used")


def test_schechner_and_kong_keep_theta_in_a_physical_range():
    # A transmission-dominated pane at 65° with φ⊥ = 60°, read with the first shot (0°) as the
    # reference: the canonical pair is swapped and the unbounded search (2°–88°) collapsed to
    # grazing incidence, putting ~80% of the light into R̂ (a real facade: 95%).
    angles = [0.0, 45.0, 90.0]
    shots, r_obs, t_obs = scene(60.0, angles, theta_deg=65.0, k_r=0.5, k_t=1.0)
    share = float(r_obs.mean() / (r_obs + t_obs).mean())
    i_perp, i_par, _ = canonical(shots, angles)
    assert np.degrees(schechner.estimate_theta(i_perp, i_par, np.arange(2.0, 88.0, 0.5))) > 85
    r_hat, t_hat = schechner.separate(shots, angles)
    assert r_hat.mean() / (r_hat + t_hat).mean() < 0.5
    assert np.degrees(kong.theta_map(i_perp, i_par, steps=20)).min() >= 10 - 1e-3
    # a minimum at the end of the range falls back to Brewster's angle
    assert schechner.estimate_theta(i_perp, i_par, np.arange(70.0, 80.5, 0.5)) == pytest.approx(optics.brewster_angle())
    # with the reference estimated, both find the layers
    for name in ("schechner", "kong"):
        run, _ = get_method(name, steps=20) if name == "kong" else get_method(name)
        r_hat, t_hat = run(shots, angles)
        assert abs(r_hat.mean() / (r_hat + t_hat).mean() - share) < 0.02
        assert metrics.psnr(t_hat, t_obs) > metrics.psnr(r_obs + t_obs, t_obs) + 3


def test_feasible_theta_range_follows_the_dolp_limits():
    lo, hi = feasible_theta_deg(-0.05, 0.5)
    c_t, c_r = optics.dolp_limits(np.radians([lo, hi]))
    assert c_t[0] >= 0.05 - 1e-3 and c_r[0] >= 0.5 and c_r[1] >= 0.5 and lo < np.degrees(optics.brewster_angle()) < hi
    assert feasible_theta_deg(-0.6, 0.5)[0] == feasible_theta_deg(-0.6, 0.5)[1]      # nothing explains it: one point


def test_presence_map_marks_where_the_reflection_is():
    angles = [0.0, 45.0, 90.0, 135.0]
    shots, r_obs, t_obs = scene(40.0, angles)
    presence = presence_map(shots, angles)
    assert presence.shape == (SIZE, SIZE) and presence.dtype == np.float32
    assert presence.min() >= 0 and presence.max() <= 1
    share = (r_obs / (r_obs + t_obs)).mean(axis=-1)
    assert np.corrcoef(presence.ravel(), share.ravel())[0, 1] > 0.7


def test_warnings_name_the_likely_cause():
    angles = [0.0, 45.0, 90.0]
    shots, _, _ = scene(40.0, angles, noise=0.002)
    assert polarization_warnings(shots, angles) == []
    twice = shots.copy()
    twice[2] = twice[1]
    assert any("same file given twice" in w for w in polarization_warnings(twice, angles))
    twice[2, 1, 1] += 0.01                                  # one pixel off the coarse sample's grid differs
    assert not any("same file given twice" in w for w in polarization_warnings(twice, angles))
    still = np.stack([shots.mean(axis=0)] * 3) + np.random.default_rng(3).normal(0, 1e-4, shots.shape).astype(np.float32)
    assert any("polarizer is not turning" in w for w in polarization_warnings(still, angles))
    s0 = shots.mean(axis=0) * 2
    weak = np.stack([s0 / 2 * (1 + 0.008 * np.cos(2 * np.radians(a - 30))) for a in angles]).astype(np.float32)
    found = polarization_warnings(weak, angles)
    assert len(found) == 1 and "too little polarization" in found[0]
    seen_through, _, _ = scene(100.0, angles, theta_deg=65.0, k_r=0.05, k_t=1.0)      # Basis.TRANSMISSION
    found = polarization_warnings(seen_through, angles)
    assert len(found) == 1 and "assumes the transmission dominates" in found[0] and "--reference 10.0" in found[0]


def test_one_inspection_gives_what_the_three_functions_give_and_codes_read_as_floats():
    from separate.reference import inspect_stack

    angles = [0.0, 45.0, 90.0, 135.0]
    shots, _, _ = scene(70.0, angles, noise=0.002)
    inspection = inspect_stack(shots, angles)
    assert inspection.reference_deg == estimate_reference_deg(shots, angles)
    assert inspection.warnings == polarization_warnings(shots, angles)
    np.testing.assert_array_equal(inspection.presence_at(shots.shape[1:3]), presence_map(shots, angles))
    assert inspect_stack(shots, angles, 10.0).reference_deg == 10.0
    codes = np.clip(np.rint(shots * 65535), 0, 65535).astype(np.uint16)
    from_codes = inspect_stack(codes, angles)
    assert angle_error(from_codes.reference_deg, inspection.reference_deg) < 0.05
    assert from_codes.warnings == inspection.warnings
    assert np.abs(from_codes.presence - inspection.presence).max() < 0.01
    np.testing.assert_allclose(present(codes, angles, 70.0)[0], present(codes / np.float32(65535), angles, 70.0)[0], atol=1e-6)
    for other in (np.int32, np.uint32):
        with pytest.raises(TypeError, match=r"expected float images or 8- or 16-bit codes \(uint8, uint16\)"):
            inspect_stack(codes.astype(other), angles)


def test_clipped_pixels_are_marked_and_warned_about():
    from separate.reference import clipped_mask, inspect_stack

    angles = [0.0, 45.0, 90.0]
    shots, _, _ = scene(40.0, angles, noise=0.002)
    assert not clipped_mask(shots).any() and not any("clipped" in w for w in polarization_warnings(shots, angles))
    bright = shots.copy()
    bright[1, :8, :, 2] = 1.0                                   # one shot, one channel, the top 8 rows
    mask = clipped_mask(bright)
    assert mask[:8].all() and not mask[8:].any()
    inspection = inspect_stack(bright, angles)
    share = 100 * 8 / bright.shape[1]
    assert np.array_equal(inspection.clipped, mask)
    assert any(f"{share:.1f}% of the pixels are clipped" in w for w in inspection.warnings)
    codes = np.clip(np.rint(bright * 65535), 0, 65535).astype(np.uint16)
    assert np.array_equal(clipped_mask(codes), mask)
