"""The per-pixel reference field, per-pixel presentation, the angle-of-incidence estimate and the
physics-anchored (Fresnel-gated) network."""

import dataclasses
from functools import partial

import cv2
import numpy as np
import pytest
import torch

from separate import metrics, optics
from separate.infer import FusedNet, load_model, separate_stack
from separate.methods import get_method
from separate.model import SeparationNet, fresnel_bases, with_fresnel_base
from separate.incidence import estimate_incidence_deg, estimate_incidence_field, robust_plane
from separate.reference import estimate_reference_deg, estimate_reference_field
from separate.presentation import field_at, present, present_field
from separate.synthesis import AngleMode, SynthesisConfig, Synthesizer, load_image_pool, perturbed_incidence
from separate.train import TrainConfig, train

POOL = load_image_pool(None)


def wide_view(h=240, w=360, turn_deg=26.0, centre_deg=57.0, theta_deg=50.0, seed=0):
    """A flat pane seen through a wide lens: φ⊥ turning linearly by ±turn_deg across the frame."""
    rng = np.random.default_rng(seed)
    refl = optics.photo_to_linear(cv2.resize(POOL[0], (w, h))) * 1.5
    trans = optics.photo_to_linear(cv2.resize(POOL[2], (w, h))) * 0.7
    xs = np.linspace(-1.0, 1.0, w)[None, :].repeat(h, 0)
    phi_perp = np.radians(centre_deg + turn_deg * xs).astype(np.float32)
    theta = np.radians(theta_deg)
    angles = [0.0, 45.0, 90.0]
    obs = np.stack([optics.render(refl, trans, theta, phi_perp, np.radians(a)) for a in angles]).astype(np.float32)
    obs = obs + rng.normal(0.0, 1e-3, obs.shape).astype(np.float32)
    r_obs, t_obs = optics.observable_layers(refl, trans, theta)
    return obs, angles, np.degrees(phi_perp), r_obs, t_obs


def test_the_field_follows_a_turning_s_direction_that_one_global_angle_misses():
    obs, angles, phi_true, _, _ = wide_view()
    field = field_at(estimate_reference_field(obs, angles), obs.shape[1:3])
    field_error = np.abs(optics.axis_gap_deg(field, phi_true))
    global_error = np.abs(optics.axis_gap_deg(estimate_reference_deg(obs, angles), phi_true))
    assert field_error.mean() < 2.0 and field_error.max() < 5.0
    assert global_error.mean() > 10.0 and global_error.max() > 20.0


def test_a_constant_field_presents_as_the_global_reference_and_a_turning_one_per_pixel():
    obs, angles, phi_true, _, _ = wide_view(h=64, w=96)
    one, _ = present(obs, angles, 40.0)
    same, local = present_field(obs, angles, np.full(obs.shape[1:3], 40.0, np.float32))
    assert local == [0.0, 45.0, 90.0]
    np.testing.assert_allclose(same, one, atol=1e-5)
    # at the true field every pixel's first shot is the one at its own φ⊥: I⊥ of the canonical projection
    at_truth, _ = present_field(obs, angles, phi_true.astype(np.float32))
    stokes = optics.stokes_from_images(obs, np.radians(angles))
    expected = optics.intensity_from_stokes(optics.rotate_stokes(stokes, np.radians(phi_true)[..., None]), 0.0)
    np.testing.assert_allclose(at_truth[0], expected, atol=1e-5)
    with pytest.raises(ValueError, match="expected a reference field of shape"):
        present_field(obs, angles, np.zeros((3, 3), np.float32))


def test_no_polarization_gives_a_constant_field():
    flat = np.repeat(optics.photo_to_linear(cv2.resize(POOL[1], (96, 64)))[None] / 2, 3, axis=0).astype(np.float32)
    field = estimate_reference_field(flat, [0.0, 45.0, 90.0])
    assert np.ptp(field) == 0.0


@pytest.mark.parametrize("theta_deg", [35.0, 50.0, 65.0])
def test_the_angle_of_incidence_is_recovered_from_a_flat_pane(theta_deg):
    obs, angles, phi_true, _, _ = wide_view(h=256, w=384, turn_deg=0.0, theta_deg=theta_deg)
    assert estimate_incidence_deg(obs, angles, 57.0) == pytest.approx(theta_deg, abs=4.0)


def test_fresnel_bases_are_the_layers_at_the_true_angle():
    obs, angles, phi_true, r_obs, t_obs = wide_view(h=64, w=96, turn_deg=0.0, theta_deg=40.0)
    stokes = optics.stokes_from_images(obs, np.radians(angles))
    i_perp, i_par = optics.canonical_intensities(stokes, np.radians(57.0))
    to_t = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]  # noqa: E731
    base_r, base_t = fresnel_bases(to_t(i_perp), to_t(i_par), torch.tensor([np.radians(40.0)]))
    assert metrics.psnr(base_t[0].numpy().transpose(1, 2, 0), t_obs) > 38
    assert metrics.psnr(base_r[0].numpy().transpose(1, 2, 0), r_obs) > 38
    np.testing.assert_allclose((base_r + base_t).numpy(), to_t(i_perp + i_par).numpy().clip(0), atol=1e-6)


def test_fresnel_bases_stay_finite_at_head_on_incidence():
    obs, angles, _, _, _ = wide_view(h=32, w=48, turn_deg=0.0, theta_deg=40.0)
    stokes = optics.stokes_from_images(obs, np.radians(angles))
    i_perp, i_par = optics.canonical_intensities(stokes, np.radians(57.0))
    to_t = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1), np.float32))[None]  # noqa: E731
    theta = torch.linspace(np.radians(1e-4), np.radians(1.0), 32 * 48).view(1, 1, 32, 48)    # R_s − R_p is 0 in float32
    base_r, base_t = fresnel_bases(to_t(i_perp), to_t(i_par), theta)
    assert torch.isfinite(base_r).all() and torch.isfinite(base_t).all()
    np.testing.assert_allclose((base_r + base_t).numpy(), to_t(i_perp + i_par).numpy().clip(0), atol=1e-6)


def test_the_angle_of_incidence_map_of_a_curved_pane_follows_it():
    obs, angles, phi_true, _, _ = wide_view(h=192, w=288, turn_deg=0.0, theta_deg=45.0)
    xs = np.linspace(-1.0, 1.0, 288)[None, :].repeat(192, 0)
    theta = np.radians(45.0 + 15.0 * xs)                       # 30° on the left, 60° on the right
    refl = optics.photo_to_linear(cv2.resize(POOL[0], (288, 192))) * 1.5
    trans = optics.photo_to_linear(cv2.resize(POOL[2], (288, 192))) * 0.7
    obs = np.stack([optics.render(refl, trans, theta, np.radians(57.0), np.radians(a)) for a in angles]).astype(np.float32)
    field = field_at(estimate_incidence_field(obs, angles, 57.0), obs.shape[1:3])
    error = np.abs(field - np.degrees(theta))[:, 30:-30]
    assert np.median(error) < 4.0
    assert field[:, -60:].mean() - field[:, :60].mean() > 15.0     # one global number could not say this


def test_the_incidence_plane_follows_the_majority_of_blocks_not_clear_outliers():
    # the 4×4 block minima of a benchmark patch at θ = 66–82° (bsds500/test, seed 2018, no. 19):
    # six clear blocks read 28–44° where the texture fakes a minimum; from a least-squares start
    # the biweight lost the other eight (the fit used to fall back to a flat 61°), the median start
    # finds the plane through them
    theta = np.array([34, 28, 42, 78, 78, 76, 78, 78, 76, 74, 34, 36, 72, 44], float)
    clarity = np.array([.39, .67, .16, .67, .46, .49, .70, .74, .83, .64, .77, .71, .62, .37])
    blocks = np.array([1, 2, 3, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15])
    x, y = (blocks % 4 + 0.5) / 4 - 0.5, (blocks // 4 + 0.5) / 4 - 0.5
    a, b, c = robust_plane(x, y, theta, clarity)
    assert a == pytest.approx(77.0, abs=1.5)
    inliers = theta > 70
    assert np.abs(a + b * x[inliers] + c * y[inliers] - theta[inliers]).max() < 4.0


def test_the_incidence_plane_follows_a_steep_slope():
    # θ turning by 30° across the 4×4 blocks (a wide view of a pane), ±2° of noise: a fit started
    # from the flat median keeps the middle columns and a slope of ~10°; the least-squares start finds it
    rng = np.random.default_rng(3)
    blocks = np.arange(16)
    x, y = (blocks % 4 + 0.5) / 4 - 0.5, (blocks // 4 + 0.5) / 4 - 0.5
    theta, clarity = 45.0 + 40.0 * x + rng.normal(0.0, 2.0, 16), rng.uniform(0.2, 0.8, 16)
    a, b, c = robust_plane(x, y, theta, clarity)
    assert a == pytest.approx(45.0, abs=2.0) and b == pytest.approx(40.0, abs=4.0) and abs(c) < 4.0


def test_too_few_agreeing_blocks_give_their_weighted_median():
    theta, clarity = np.array([20.0, 40.0, 60.0, 75.0]), np.array([0.1, 0.1, 0.9, 0.1])
    np.testing.assert_allclose(robust_plane(np.zeros(4), np.zeros(4), theta, clarity), [60.0, 0.0, 0.0])


def test_perturbed_incidence_stays_in_range_near_the_truth_or_fails_outright():
    rng = np.random.default_rng(0)
    theta = np.full((32, 32), np.radians(50.0), np.float32)
    draws = np.degrees(np.stack([perturbed_incidence(rng, theta) for _ in range(400)]))
    assert ((draws >= 10.0 - 1e-4) & (draws <= 80.0 + 1e-4)).all()
    errors = np.abs(draws - 50.0).max(axis=(1, 2))
    near = (errors < 20.0).mean()
    assert 0.9 < near < 0.99                                      # ~5% failed estimates
    assert np.ptp(draws[0]) > 0.0                                 # a smooth local error on top of the global one


def test_a_fresnel_network_starts_near_its_canonical_answer_and_runs_fused_and_as_a_module():
    torch.manual_seed(0)
    canonical = SeparationNet(width=8, upsample="resize").eval()
    model = with_fresnel_base(canonical).eval()
    assert model.config()["base"] == "fresnel" and model.head.weight.shape[1] == 15
    obs, theta = torch.rand(1, 3, 3, 40, 48), torch.full((1, 1, 40, 48), 0.8)
    with pytest.raises(ValueError, match="expected theta exactly when base is 'fresnel'"):
        model(obs)
    with torch.no_grad():
        r_ref, t_ref = model(obs, scale=torch.tensor([0.3]), theta=theta)
        r_can, t_can = canonical(obs, scale=torch.tensor([0.3]))
        _, base_t = fresnel_bases(*canonical_pair(obs), theta)
    # the gate starts near g = 0.018: within 3% of the way from the network's answer (negatives clipped) to the inversion's
    t_can = t_can.clamp_min(0.0)
    assert (t_ref - t_can).abs().max() <= 0.03 * (base_t - t_can).abs().max()
    assert (t_ref - t_can).abs().max() > 0
    if FusedNet.available():
        r_fused, t_fused = FusedNet(model)(obs.clone(), model_angles(), torch.tensor([0.3]), theta=theta)
        torch.testing.assert_close(t_fused.contiguous(), t_ref, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(r_fused.contiguous(), r_ref, atol=1e-4, rtol=1e-4)
        with torch.no_grad():                                       # an open gate, anchored in strips of 16 rows
            model.gate.convs[-1].bias.fill_(2.0)
            r_open, t_open = model(obs, scale=torch.tensor([0.3]), theta=theta)
        r_strips, t_strips = FusedNet(model, strip_rows=16)(obs.clone(), model_angles(), torch.tensor([0.3]), theta=theta)
        torch.testing.assert_close(t_strips.contiguous(), t_open, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(r_strips.contiguous(), r_open, atol=1e-4, rtol=1e-4)


def test_an_open_gate_gives_the_fresnel_inversion():
    model = with_fresnel_base(SeparationNet(width=8, upsample="resize")).eval()
    with torch.no_grad():
        model.gate.convs[-1].bias.fill_(30.0)                      # g = 1
    obs, angles, _, r_obs, t_obs = wide_view(h=64, w=96, turn_deg=0.0, theta_deg=40.0)
    r_hat, t_hat = separate_stack(model, obs, angles, tile=4096, overlap=0, precision="fp32", reference_deg=57.0, theta_deg=40.0)
    assert metrics.psnr(t_hat, t_obs) > 38 and metrics.psnr(r_hat, r_obs) > 38


def test_the_bands_of_a_difference_sum_to_it_and_split_it_by_frequency():
    from separate.model import bands, gaussian_blur
    torch.manual_seed(0)
    x = torch.rand(1, 3, 48, 64)
    parts = bands(x)
    torch.testing.assert_close(sum(parts), x, atol=1e-6, rtol=0)
    torch.testing.assert_close(gaussian_blur(torch.full((1, 1, 20, 30), 0.7), 2.0), torch.full((1, 1, 20, 30), 0.7))
    traced = x.clone().requires_grad_()                          # torch's convolutions (training) and OpenCV's agree
    torch.testing.assert_close(gaussian_blur(traced, 4.0).detach(), gaussian_blur(x, 4.0), atol=1e-6, rtol=0)
    checker = (torch.arange(64)[None, :] + torch.arange(48)[:, None]) % 2 * 1.0          # the finest detail there is
    fine, middle, coarse = bands(checker[None, None].expand(1, 3, 48, 64).contiguous() - 0.5)
    assert fine.abs().mean() > 0.4 and coarse.abs().mean() < 0.01
    ramp = torch.linspace(0, 1, 64)[None, None, None].expand(1, 3, 48, 64).contiguous()    # the coarsest
    fine, middle, coarse = bands(ramp)
    assert (coarse - ramp)[..., 12:-12].abs().max() < 1e-3 and fine[..., 12:-12].abs().max() < 1e-3


def test_a_broad_minimum_of_the_mutual_information_is_not_trusted(monkeypatch):
    from separate import incidence
    obs, angles, _, _, _ = wide_view(turn_deg=0.0, theta_deg=72.0)
    aligned = incidence.estimate_incidence(obs, angles, 57.0)
    assert aligned.clear and aligned.sharpness >= incidence.INCIDENCE_SHARPNESS_MIN
    assert np.median(aligned.field_deg) == pytest.approx(72.0, abs=2.0)

    def bowl(i_perp, i_par, grid_deg):      # flat-bottomed: a least value, no dip
        return 1.0 + 2e-5 * (grid_deg - 60.0) ** 4

    monkeypatch.setattr(incidence, "information_by_incidence", bowl)
    broad = incidence.estimate_incidence(obs, angles, 57.0)
    grid = np.arange(10.0, 80.5, 2.0)
    assert broad.sharpness == pytest.approx(2e-5 * 6**4 / np.median(bowl(None, None, grid)))
    assert broad.clarity >= incidence.INCIDENCE_CLARITY_MIN and not broad.clear

    def vee(i_perp, i_par, grid_deg):       # the cancellation's dip
        return 1.0 + 0.02 * np.abs(grid_deg - 72.0)

    monkeypatch.setattr(incidence, "information_by_incidence", vee)
    sharp = incidence.estimate_incidence(obs, angles, 57.0)
    assert sharp.clear and np.median(sharp.field_deg) == pytest.approx(72.0, abs=0.5)


def test_an_unclear_angle_of_incidence_runs_the_network_without_its_gate():
    from separate.incidence import estimate_incidence
    from separate.model import without_gate
    anchored = load_model("urd-anchored")[0]
    canonical = without_gate(anchored)
    noise = np.random.default_rng(5).uniform(0.1, 0.3, (3, 96, 128, 3)).astype(np.float32)   # no pane to tell θ
    assert not estimate_incidence(noise, [0.0, 45.0, 90.0], 0.0).clear
    r_a, t_a = separate_stack(anchored, noise, [0.0, 45.0, 90.0], precision="fp32")
    r_c, t_c = separate_stack(canonical, noise, [0.0, 45.0, 90.0], precision="fp32")
    np.testing.assert_array_equal(t_a, t_c)
    np.testing.assert_array_equal(r_a, r_c)
    obs, angles, _, _, _ = wide_view(h=64, w=96, turn_deg=0.0, theta_deg=50.0)
    for bad in (0.0, 90.0, -5.0, np.full((4, 4, 2), 50.0)):
        with pytest.raises(ValueError, match="expected an angle of incidence in"):
            separate_stack(anchored, obs, angles, precision="fp32", theta_deg=bad)
    _, t_map = separate_stack(anchored, obs, angles, precision="fp32", theta_deg=np.full((8, 12), 50.0))
    _, t_one = separate_stack(anchored, obs, angles, precision="fp32", theta_deg=50.0)
    np.testing.assert_allclose(t_map, t_one, atol=1e-6)                  # a small map is resized to the image


@pytest.mark.slow
def test_the_network_records_whether_it_used_its_gate():
    from urd.separation import describe_incidence

    run, info = get_method("network", precision="fp32")
    noise = np.random.default_rng(5).uniform(0.1, 0.3, (3, 96, 128, 3)).astype(np.float32)
    run(noise, [0.0, 45.0, 90.0], 0.0)
    record = info["incidence"]
    assert not record["gate"] and set(record) == {"median_deg", "range_deg", "clarity", "sharpness", "gate"}
    assert describe_incidence(record).startswith("angle of incidence not clear from the shots (clarity ")
    obs, angles, _, _, _ = wide_view(turn_deg=0.0, theta_deg=72.0)
    run(obs, angles, 57.0)
    assert info["incidence"]["gate"] and info["incidence"]["median_deg"] == pytest.approx(72.0, abs=2.0)
    run_given, _ = get_method("network", precision="fp32", incidence_deg=72.0, return_copies=False)
    direct = separate_stack(load_model("urd-anchored")[0], obs, angles, precision="fp32", reference_deg=57.0,
                            theta_deg=72.0)
    np.testing.assert_array_equal(run_given(obs, angles, 57.0)[1], direct[1])
    for weights, bad, reason in (("urd-anchored", 90.0, "in \\(0, 90\\) deg"), ("urd-canonical", 40.0, "physics-anchored")):
        with pytest.raises(ValueError, match=reason):
            get_method("network", weights=weights, incidence_deg=bad)


def test_the_side_trials_of_the_network_are_schechners_inversion():
    obs, angles, _, _, _ = wide_view(h=64, w=96, turn_deg=0.0, theta_deg=50.0)
    trial = get_method("network")[0](obs, angles, 30.0, trial=True)
    schechner = get_method("schechner")[0](obs, angles, 30.0)
    network = get_method("network")[0](obs, angles, 30.0)
    np.testing.assert_array_equal(np.maximum(trial[1], 0), schechner[1])    # the trial keeps the negative light
    assert trial[1].min() < 0
    assert np.abs(network[1] - schechner[1]).max() > 1e-3                 # the network's own answer differs


def test_a_plane_fit_to_one_row_of_blocks_has_no_made_up_tilt():
    from separate.incidence import _plane_fit
    x, y = np.array([-0.375, -0.125, 0.125, 0.375]), np.full(4, -0.375)
    coef = _plane_fit(x, y, 50.0 + 10.0 * x, np.ones(4))
    np.testing.assert_allclose(coef, [50.0, 10.0, 0.0], atol=1e-9)
    coef = _plane_fit(np.array([0.1, 0.2, 0.3, 0.4]), np.array([0.0, 0.5, -0.5, 0.2]), np.array([40.0, 45.0, 35.0, 42.0]), np.ones(4))
    assert abs(coef[2] - 10.0) < 1e-9 and abs(coef[1]) < 1e-9


def canonical_pair(obs):
    from separate.model import canonical_inputs
    return canonical_inputs(obs)[1:]


def model_angles():
    from separate.model import NOMINAL_ANGLES
    return NOMINAL_ANGLES


@pytest.mark.slow
def test_the_shipped_network_takes_a_field_tile_by_tile_like_the_presented_stack():
    model, _ = load_model("urd-canonical")              # the shipped network's backbone (the gate adds its own θ estimate)
    obs, angles, phi_true, _, _ = wide_view(h=200, w=272)
    field = field_at(estimate_reference_field(obs, angles), obs.shape[1:3])
    _, t_field = separate_stack(model, obs, angles, tile=4096, overlap=0, precision="fp32", reference_deg=field)
    shots, local = present_field(obs, angles, field)
    _, t_presented = separate_stack(model, np.maximum(shots, 0.0), local, tile=4096, overlap=0, precision="fp32")
    np.testing.assert_allclose(t_field, t_presented, atol=1e-4)
    _, t_tiled = separate_stack(model, obs, angles, tile=136, overlap=64, precision="fp32", reference_deg=field)
    assert np.abs(t_tiled - t_field).mean() < 1e-3


def test_every_polarization_method_takes_the_auto_field_and_the_global_reference():
    obs, angles, _, _, t_obs = wide_view(h=96, w=144)
    for name in ("network", "schechner", "farid"):
        run, info = get_method(name)
        assert "per pixel" in info["reference_policy"]
        _, t_auto = run(obs, angles)
        run_global, info_global = get_method(name, reference="global")
        assert info_global["reference_policy"].startswith("global")
        _, t_global = run_global(obs, angles)
        assert t_auto.shape == t_global.shape == t_obs.shape
        assert np.abs(t_auto - t_global).max() > 1e-3                  # the turning pane: auto takes the field
        if name != "network":                                           # the network's gain here is 0.07 dB
            assert metrics.psnr(t_auto, t_obs) > metrics.psnr(t_global, t_obs) + 0.2
    _, t_schechner = get_method("schechner")[0](obs, angles)
    assert metrics.psnr(t_schechner, t_obs) > 30


def test_synthesis_switches_no_glass_views_and_turning_s_directions():
    base = SynthesisConfig(patch=64, angles=AngleMode.ANY_TRUE_SIDE, reference_field=True)
    clean = dataclasses.replace(base, no_glass_prob=1.0, noise=False, angle_noise_deg=0.0)
    none = Synthesizer(POOL, clean, seed=2).batch(6)
    assert not none["r"].any() and not none["theta"].any()
    # the target is everything the camera sees (T = S0 of the shots), which is polarized
    s0 = np.stack([optics.stokes_from_images(o, a)[0] for o, a in zip(none["obs"], none["angles"])])
    np.testing.assert_allclose(s0, none["t"], atol=1e-4)
    stokes = [optics.stokes_from_images(o, a) for o, a in zip(none["obs"], none["angles"])]
    assert max(float(np.percentile(optics.dolp(s), 99)) for s in stokes) > 0.05
    turning = Synthesizer(POOL, dataclasses.replace(base, phi_field_prob=1.0, incidence_estimate=True), seed=3).batch(6)
    spread = np.ptp(np.degrees(turning["phi_perp"]).reshape(6, -1), axis=1)
    assert spread.max() > 5.0 and (spread > 0).all()
    assert turning["theta_est"].shape == (6, 64, 64)
    assert ((turning["theta_est"] > np.radians(9)) & (turning["theta_est"] < np.radians(81))).all()
    np.testing.assert_allclose(np.degrees(turning["angles"]), [[0.0, 45.0, 90.0]] * 6, atol=1e-4)


@pytest.mark.slow
def test_training_only_the_gate_of_a_fresnel_network_from_canonical_weights(tmp_path):
    from separate.train import save_checkpoint
    start = SeparationNet(width=8, upsample="resize")
    cfg = TrainConfig(width=8, upsample="resize", patch=64, batch=2, micro_batch=2, steps=2, val_samples=2, val_every=2)
    save_checkpoint(tmp_path / "start.pt", start, None, 0, cfg, {})
    fresnel = dataclasses.replace(cfg, base="fresnel", trainable="gate", angles="any-true-side", reference_field=True,
                                  no_glass_prob=0.2, lr=1e-2)
    record = train(fresnel, tmp_path / "run", init=tmp_path / "start.pt")
    assert record["step"] == 2 and np.isfinite(record["psnr_t"])
    state = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    assert state["model_config"]["base"] == "fresnel"
    for name, value in start.state_dict().items():                 # the backbone frozen, the gate trained
        torch.testing.assert_close(state["model"][name], value)
    fresh = with_fresnel_base(start).state_dict()
    assert any(not torch.equal(state["model"][k], fresh[k]) for k in fresh if k.startswith("gate."))


def test_training_all_but_the_gate_keeps_the_gate_and_moves_the_backbone(tmp_path):
    from separate.train import save_checkpoint
    start = with_fresnel_base(SeparationNet(width=8, upsample="resize"))
    cfg = TrainConfig(width=8, upsample="resize", base="fresnel", trainable="backbone", angles="any-true-side",
                      reference_field=True, patch=64, batch=2, micro_batch=2, steps=2, val_samples=2, val_every=2, lr=1e-2)
    save_checkpoint(tmp_path / "start.pt", start, None, 0, cfg, {})
    record = train(cfg, tmp_path / "run", init=tmp_path / "start.pt")
    assert record["step"] == 2 and np.isfinite(record["psnr_t"])
    state = torch.load(tmp_path / "run" / "last.pt", weights_only=True)["model"]
    for name, value in start.state_dict().items():
        assert torch.equal(state[name], value) == name.startswith("gate."), name


def test_a_gate_only_config_needs_the_fresnel_network(tmp_path):
    config = tmp_path / "gate.toml"
    config.write_text('trainable = "gate"\n')
    with pytest.raises(ValueError, match="trainable"):
        TrainConfig.from_toml(config)
    config.write_text('trainable = "gate"\nbase = "fresnel"\n')
    assert TrainConfig.from_toml(config).trainable == "gate"
    config.write_text('trainable = "backbone"\n')
    with pytest.raises(ValueError, match="trainable"):
        TrainConfig.from_toml(config)


def pane(theta_deg, reflection_gain, transmission_gain, phi_perp_deg=30.0, h=192, w=288):
    refl = optics.photo_to_linear(cv2.resize(POOL[0], (w, h))) * reflection_gain
    trans = optics.photo_to_linear(cv2.resize(POOL[3], (w, h))) * transmission_gain
    angles = [0.0, 45.0, 90.0]
    obs = np.stack([optics.render(refl, trans, np.radians(theta_deg), np.radians(phi_perp_deg), np.radians(a))
                    for a in angles]).astype(np.float32)
    return obs / obs.mean() * 0.2, angles


def sheen_behind_pane(reflection, transmission, reflection_gain, sheen_dolp, h=192, w=288):
    """Shots (0/45/90°) through a pane at 40° with φ⊥ 30° whose transmitted view has a sheen of its own
    polarized across the glass's s-direction (at 120°), stronger than the reflection is polarized."""
    refl = optics.photo_to_linear(cv2.resize(POOL[reflection], (w, h))) * reflection_gain
    trans = optics.photo_to_linear(cv2.resize(POOL[transmission], (w, h)))
    dolp = np.zeros((h, w, 1), np.float32)
    dolp[60:120, 100:180] = sheen_dolp
    stokes_t = optics.stokes_from_polarization(trans, dolp, np.radians(120.0)).astype(np.float32)
    zeros = np.zeros_like(refl)
    parts = optics.pane_stokes(np.stack([refl, zeros, zeros]), stokes_t, np.radians(40.0), np.radians(30.0))
    angles = [0.0, 45.0, 90.0]
    obs = np.stack([optics.intensity_from_stokes(parts[0] + parts[1], np.radians(a)) for a in angles]).astype(np.float32)
    return obs / obs.mean() * 0.2, angles


@pytest.mark.slow
def test_a_side_read_from_the_higher_dolp_is_checked_by_separating_both():
    from separate.reference import Basis, decide_side, inspect_stack

    trial = partial(get_method("schechner")[0], trial=True)
    for case in [(1, 2, 3.0, 0.7), (0, 3, 4.0, 0.8)]:       # the sheen reaches a higher DoLP than the reflection
        obs, angles = sheen_behind_pane(*case)
        inspection = inspect_stack(obs, angles)
        assert inspection.estimate.basis is Basis.TAILS and abs(optics.axis_gap_deg(inspection.reference_deg, 120.0)) < 1.0
        decided = decide_side(obs, angles, inspection, trial)
        assert decided.estimate.basis is Basis.TRIAL and abs(optics.axis_gap_deg(decided.reference_deg, 30.0)) < 1.0, case
        assert any("than the more strongly polarized orientation's 120.0 deg" in w for w in decided.warnings)
    # turning would put more light into R̂ while the information falls by less than half: kept,
    # as a view without glass whose own polarization the turn would read as a reflection
    obs, angles = sheen_behind_pane(0, 3, 2.0, 0.6)
    inspection = inspect_stack(obs, angles)
    assert inspection.estimate.basis is Basis.TAILS and decide_side(obs, angles, inspection, trial) is inspection
    obs, angles = sheen_behind_pane(1, 2, 1.0, 0.5)          # the reflection's orientation reaches higher: kept
    inspection = inspect_stack(obs, angles)
    assert inspection.estimate.basis is Basis.TAILS and abs(optics.axis_gap_deg(inspection.reference_deg, 30.0)) < 1.0
    assert decide_side(obs, angles, inspection, trial) is inspection


@pytest.mark.slow
@pytest.mark.parametrize("method", ["network", "schechner"])
def test_an_assumed_side_is_settled_by_separating_both(method):
    from separate.reference import Basis, decide_side, inspect_stack

    run, _ = get_method(method)
    # a bright reflection in glass seen nearly head-on: weak polarization of one orientation, assumed transmission
    obs, angles = pane(22.0, 2.0, 0.15)
    inspection = inspect_stack(obs, angles)
    assert inspection.estimate.basis is Basis.TRANSMISSION and abs(optics.axis_gap_deg(inspection.reference_deg, 30.0)) > 80
    decided = decide_side(obs, angles, inspection, run)
    assert abs(optics.axis_gap_deg(decided.reference_deg, 30.0)) < 1.0
    assert decided.estimate.basis is Basis.TRIAL and decided.estimate.reference_deg == decided.reference_deg
    assert np.abs(decided.field - decided.reference_deg).max() < 1.0          # the field goes round the new reference
    assert any("decided by separating both" in w for w in decided.warnings)
    assert not any("urd assumes the transmission dominates" in w for w in decided.warnings)
    # a bright transmission at a steep angle: the assumption was right and stays
    obs, angles = pane(60.0, 0.03, 1.5)
    inspection = inspect_stack(obs, angles)
    assert inspection.estimate.basis is Basis.TRANSMISSION
    assert decide_side(obs, angles, inspection, run) is inspection


def test_auto_presents_a_weak_polarization_of_one_orientation_at_one_angle_and_a_strong_one_per_pixel():
    from separate.reference import Basis, resolve_reference

    trial = get_method("schechner")[0]
    obs, angles = pane(60.0, 0.03, 1.5)                    # a faint reflection: weak, one orientation
    inspection, reference = resolve_reference(obs, angles, "auto", trial)
    assert inspection.estimate.basis is Basis.TRANSMISSION
    assert np.ndim(reference) == 0 and reference == inspection.reference_deg
    obs, angles, phi_true, _, _ = wide_view(h=96, w=144)    # a strong reflection, φ⊥ turning across the frame
    inspection, reference = resolve_reference(obs, angles, "auto", trial)
    assert inspection.estimate.basis is not Basis.TRANSMISSION and np.shape(reference) == obs.shape[1:3]
    assert np.abs(optics.axis_gap_deg(reference, phi_true)).mean() < 3.0


def test_a_separation_at_one_angle_says_why_and_writes_it_as_a_constant_map(tmp_path):
    import tifffile

    from urd.separation import separate_images

    obs, angles = pane(60.0, 0.03, 1.5)                    # weak polarization of one orientation
    paths = []
    for angle, shot in zip(angles, obs):
        paths.append(tmp_path / f"shot_{angle:g}.tiff")
        tifffile.imwrite(paths[-1], shot, photometric="rgb")
    run = get_method("schechner")[0]
    result = separate_images(paths, angles, tmp_path / "one", run)
    assert result.reference_kind.startswith("estimated, one angle: the polarization is weak")
    used = tifffile.imread(tmp_path / "one" / "reference_deg.tiff")
    assert np.ptp(used) == 0 and used.flat[0] == pytest.approx(result.reference_deg, abs=1e-3)
    obs, angles, _, _, _ = wide_view(h=96, w=144)
    for path, shot in zip(paths, obs):
        tifffile.imwrite(path, shot, photometric="rgb")
    result = separate_images(paths, angles, tmp_path / "field", run)
    assert result.reference_kind == "estimated per pixel, a field"
    assert np.ptp(tifffile.imread(tmp_path / "field" / "reference_deg.tiff")) > 20
