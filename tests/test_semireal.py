"""The scene's own polarization: the pane's Stokes optics against closed forms, the real no-glass
captures and their split, polarized training data, and the semi-real benchmark's scenes."""

import dataclasses

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import SHARED_DATA
from separate import optics, semireal
from separate.synthesis import (Synthesizer, SynthesisConfig, default_pool, load_image_pool, own_polarization, real_pool, through_mosaic,
                                turn_stokes)
from urd.cli import app
from urd.core import samples

NO_GLASS = samples.no_glass_captures(SHARED_DATA / "polarization")
needs_captures = pytest.mark.skipif(not NO_GLASS, reason=f"the real polarization captures (../shared/data, the team's "
                                    f"shared reference data) are not present: {SHARED_DATA / 'polarization'}")


@pytest.mark.slow
def test_photo_and_capture_pools_are_read_once_per_process_and_cannot_be_written():
    """Training runs, benchmarks and semi-real scene sets of one process share one copy of each pool."""
    pools = [default_pool("val")] + ([real_pool("train")] if NO_GLASS else [])
    for pool, again in zip(pools, [default_pool("val"), real_pool("train")]):
        assert again is pool and len(pool) >= 2
        arrays = [a for entry in pool for a in (entry[:2] if isinstance(entry, tuple) else (entry,))]
        assert arrays and not any(a.flags.writeable for a in arrays)
        with pytest.raises(ValueError, match="read-only"):
            arrays[0].flat[0] = 0


def test_pane_of_unpolarized_layers_renders_as_eq_1():
    rng = np.random.default_rng(0)
    i_r, i_t = rng.random((2, 6, 7, 3))
    theta, phi_perp = rng.uniform(0.2, 1.4, (6, 7)), rng.uniform(0.0, np.pi, (6, 7))
    zeros = np.zeros_like(i_r)
    part_r, part_t = optics.pane_stokes(np.stack([i_r, zeros, zeros]), np.stack([i_t, zeros, zeros]), theta, phi_perp)
    for phi in (0.0, 0.4, 1.9):
        np.testing.assert_allclose(optics.intensity_from_stokes(part_r + part_t, phi),
                                   optics.render(i_r, i_t, theta, phi_perp, phi), atol=1e-12)
    r_obs, t_obs = optics.observable_layers(i_r, i_t, theta)
    np.testing.assert_allclose(part_r[0], r_obs, atol=1e-12)
    np.testing.assert_allclose(part_t[0], t_obs, atol=1e-12)


def test_diattenuator_closed_forms():
    light = optics.stokes_from_polarization(np.float64(2.0), 0.6, np.radians(20.0))
    # an ideal polarizer at 50 deg passes (S0/2)(1 + DoLP cos 2(AoLP - 50 deg)) (Malus)
    out = optics.diattenuate(light, 1.0, 0.0, np.radians(50.0))
    assert out[0] == pytest.approx(1.0 * (1 + 0.6 * np.cos(np.radians(-60.0))))
    assert optics.dolp(out) == pytest.approx(1.0, abs=1e-6)
    assert np.degrees(optics.aolp(out)) == pytest.approx(50.0)
    # a pane's transmission (Brewster: R_p = 0) polarizes unpolarized light across phi_perp
    theta_b = optics.brewster_angle()
    r_s, r_p = optics.fresnel_reflectance(theta_b)
    out = optics.diattenuate(np.array([1.0, 0.0, 0.0]), 1 - r_s, 1 - r_p, np.radians(10.0))
    assert r_p == pytest.approx(0.0, abs=1e-12)
    assert out[0] == pytest.approx(1 - r_s / 2)
    assert optics.dolp(out) == pytest.approx(r_s / (2 - r_s))
    assert optics.axis_gap_deg(np.degrees(optics.aolp(out)), 100.0) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("theta_deg", [30.0, 50.0, 70.0, 80.0])
def test_reflected_polarized_light_turns_as_jones_calculus(theta_deg):
    # light polarized at 45 deg to the s-direction, reflected: its field (r_s·E_s, r_p·E_p) with the
    # textbook amplitudes, read in the frame that keeps the reflection right-handed (E_p mirrored),
    # leaves at -atan(r_p / r_s) from s; beyond Brewster's angle r_p changes sign and so does the angle
    n, theta = 1.5, np.radians(theta_deg)
    cos_i, cos_t = np.cos(theta), np.sqrt(1 - (np.sin(theta) / n) ** 2)
    amp_s, amp_p = (cos_i - n * cos_t) / (cos_i + n * cos_t), (n * cos_i - cos_t) / (n * cos_i + cos_t)
    phi_perp = np.radians(15.0)
    light = optics.stokes_from_polarization(np.float64(1.0), 1.0, phi_perp + np.radians(45.0))
    part_r, part_t = optics.pane_stokes(light, np.zeros(3), theta, phi_perp, n)
    expected = np.degrees(phi_perp - np.arctan(amp_p / amp_s))
    assert optics.axis_gap_deg(np.degrees(optics.aolp(part_r)), expected) == pytest.approx(0.0, abs=1e-9)
    assert part_r[0] == pytest.approx((amp_s**2 + amp_p**2) / 2)
    assert optics.dolp(part_r) == pytest.approx(1.0)
    assert np.all(part_t == 0)


@pytest.mark.parametrize("flip,turns,expected_deg", [(False, 1, 120.0), (True, 0, -30.0), (True, 1, 60.0), (False, 2, 30.0)])
def test_turned_stokes_turn_their_polarization(flip, turns, expected_deg):
    stokes = optics.stokes_from_polarization(np.ones((4, 4, 1), np.float32), 0.5, np.radians(30.0)).astype(np.float32)
    out = turn_stokes(stokes, flip, turns)
    assert optics.axis_gap_deg(np.degrees(optics.aolp(out)), expected_deg) == pytest.approx(0.0, abs=1e-4)
    np.testing.assert_allclose(optics.dolp(out), 0.5, atol=1e-6)


def test_turned_stokes_follow_the_turned_image():
    """Shooting a turned scene through a polarizer turned alike gives the turned shot."""
    rng = np.random.default_rng(1)
    s0 = rng.random((5, 5, 1)) + 1
    stokes = optics.stokes_from_polarization(s0, rng.random((5, 5, 1)) * 0.5, rng.uniform(0, np.pi, (5, 5, 1))).astype(np.float32)
    phi = np.radians(25.0)
    shot = optics.intensity_from_stokes(stokes, phi)
    turned = turn_stokes(stokes, False, 1)
    np.testing.assert_allclose(optics.intensity_from_stokes(turned, phi + np.pi / 2), np.rot90(shot), atol=1e-5)
    mirrored = turn_stokes(stokes, True, 0)
    np.testing.assert_allclose(optics.intensity_from_stokes(mirrored, -phi), shot[:, ::-1], atol=1e-5)


def test_own_polarization_stays_physical():
    photo = optics.photo_to_linear(load_image_pool(None, 128)[0][:128, :128])
    for seed in range(4):
        dolp, aolp = own_polarization(np.random.default_rng(seed), photo, 0.6)
        assert dolp.shape == aolp.shape == photo.shape[:2]
        assert 0.0 <= dolp.min() and dolp.max() <= 0.95
        assert dolp.mean() > 0.005


def _clean(cfg: SynthesisConfig) -> SynthesisConfig:
    return dataclasses.replace(cfg, noise=False, nrd_prob=0.0, angle_noise_deg=0.0)


def test_a_mono_captures_sample_is_grey_in_both_layers():
    """A mono capture behind the pane makes a mono sample: a colour reflection beside a grey
    transmission would tell the layers apart by colour, which no mono camera can."""
    pool = load_image_pool(None, 256)
    rng = np.random.default_rng(0)
    grey_view = np.repeat(rng.uniform(0.2, 0.8, (1, 96, 96, 1)).astype(np.float32), 3, axis=-1)
    stokes = np.concatenate([grey_view, 0.1 * grey_view, np.zeros_like(grey_view)])
    real = [(stokes, np.zeros((96, 96), bool), True)]
    cfg = _clean(SynthesisConfig(patch=64, real_prob=1.0))
    batch = Synthesizer(pool, cfg, seed=4, real=real).batch(4)
    for layer in ("r", "t", "obs"):
        np.testing.assert_array_equal(batch[layer][..., 0], batch[layer][..., 1])
        np.testing.assert_array_equal(batch[layer][..., 0], batch[layer][..., 2])
    assert batch["r"].std() > 0                                       # a reflection was there


@pytest.mark.parametrize("switch", ["t_polarized_prob", "mono_prob", "defocus_prob"])
def test_polarized_training_samples_keep_r_plus_t_the_shots_s0(switch):
    pool = load_image_pool(None, 256)
    cfg = _clean(SynthesisConfig(**{switch: 1.0}))
    batch = Synthesizer(pool, cfg, seed=3).batch(4)
    for obs, r, t, angles in zip(batch["obs"], batch["r"], batch["t"], batch["angles"]):
        s0 = optics.stokes_from_images(obs, angles)[0]
        np.testing.assert_allclose(r + t, s0, atol=2e-5)
        if switch == "mono_prob":
            np.testing.assert_allclose(t[..., 0], t[..., 2], atol=1e-6)


@pytest.mark.parametrize("t_polarized_prob", [0.0, 1.0])
def test_strength_sets_the_reflections_share_and_keeps_the_shots_consistent(t_polarized_prob):
    pool = load_image_pool(None, 256)
    cfg = _clean(SynthesisConfig(strength=(0.3, 0.6), abrupt_prob=0.0, t_polarized_prob=t_polarized_prob))
    batch = Synthesizer(pool, cfg, seed=4).batch(6)
    ratios = batch["r"].mean(axis=(1, 2, 3)) / batch["t"].mean(axis=(1, 2, 3))
    assert np.all((ratios > 0.3 - 1e-4) & (ratios < 0.6 + 1e-4)), ratios
    for obs, r, t, angles in zip(batch["obs"], batch["r"], batch["t"], batch["angles"]):
        unclipped = (obs < 1.0).all(axis=0)                       # up to 1% of a sample's shots may clip
        np.testing.assert_allclose((r + t)[unclipped], optics.stokes_from_images(obs, angles)[0][unclipped], atol=2e-5)
    with pytest.raises(ValueError, match="strength"):
        SynthesisConfig(strength=(0.5, 0.2))


def test_new_switches_off_draw_the_paper_samples():
    """The polarization switches at 0 draw nothing: the same seed gives the same samples with a
    real pool handed in or not."""
    pool = load_image_pool(None, 256)
    stokes = np.ones((3, 200, 200, 3), np.float32)
    a = Synthesizer(pool, SynthesisConfig(), seed=5).batch(3)
    b = Synthesizer(pool, SynthesisConfig(), seed=5, real=[(stokes, np.zeros((200, 200), bool), False)]).batch(3)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def test_mosaic_samples_come_as_urd_ingest_gives_them():
    pool = load_image_pool(None, 512)
    cfg = _clean(SynthesisConfig(angles="any-true-side", patch=64, mosaic_prob=1.0, mono_prob=0.5, no_glass_prob=0.3))
    batch = Synthesizer(pool, cfg, seed=2).batch(8)
    assert batch["obs"].shape == (8, 3, 64, 64, 3) and (batch["shots"] == 4).all()
    for obs, r, t, angles in zip(batch["obs"], batch["r"], batch["t"], batch["angles"]):
        grey = all(np.array_equal(x[..., 0], x[..., k]) for x in (r, t) for k in (1, 2))
        assert grey == np.array_equal(obs[..., 0], obs[..., 1])            # IMX250MZR for grey layers, IMX250MYR else
        error = np.abs(optics.stokes_from_images(obs, angles)[0] - (r + t)).mean() / (r + t).mean()
        assert 1e-4 < error < (0.03 if grey else 0.15)                    # demosaiced, close to the cells' means
    # shots constant over the frame come back as they were; φ⊥ is averaged as an axis (0.01 and π − 0.01 → ~0)
    shots = np.ones((4, 8, 8, 3), np.float32) * np.float32([0.2, 0.3, 0.4, 0.3])[:, None, None, None]
    layer = np.full((8, 8, 3), 0.25, np.float32)
    phi = np.tile(np.float32([0.01, np.pi - 0.01]), (8, 4))
    out = through_mosaic(shots, layer, layer, np.zeros(4), np.zeros(4), np.full((8, 8), 0.5, np.float32), phi)
    np.testing.assert_allclose(out[0], shots[:, :4, :4], atol=1e-6)
    assert out[1].shape == (4, 4, 3) and np.allclose(out[5], 0.5) and (np.minimum(out[6], np.pi - out[6]) < 1e-3).all()
    with pytest.raises(ValueError, match="ANY angle mode"):
        SynthesisConfig(mosaic_prob=0.5)


@needs_captures
def test_no_glass_split_is_fixed_and_disjoint():
    train = {c.name for c in samples.no_glass_captures(SHARED_DATA / "polarization", "train")}
    test = {c.name for c in samples.no_glass_captures(SHARED_DATA / "polarization", "test")}
    assert train and test and not train & test
    assert test == set(samples.NO_GLASS_TEST) & {c.name for c in NO_GLASS}
    assert {"imx250mzr-fruits", "imx250mzr-camera", "wen2019-scene61"} <= test
    with pytest.raises(ValueError, match="split"):
        samples.no_glass_captures(SHARED_DATA / "polarization", "val")


@pytest.mark.slow
@needs_captures
def test_every_no_glass_capture_obeys_malus():
    """I0 + I90 = I45 + I135 within 3% of S0 for every capture (the angle labels pair right)."""
    for capture in NO_GLASS:
        stack, angles = samples.load(capture, max_side=256)
        by_angle = dict(zip(angles, stack))
        residual = np.abs(by_angle[0.0] + by_angle[90.0] - by_angle[45.0] - by_angle[135.0]).mean()
        assert residual / (by_angle[0.0] + by_angle[90.0]).mean() < 0.03, capture.name
        if capture.mono:
            np.testing.assert_array_equal(stack[..., 0], stack[..., 1])


@pytest.mark.slow
@needs_captures
def test_real_training_samples_are_polarized_and_consistent():
    cfg = _clean(SynthesisConfig(real_prob=1.0, no_glass_prob=0.5))
    synth = Synthesizer(load_image_pool(None, 256), cfg, seed=2)
    batch = synth.batch(6)
    for obs, r, t, angles in zip(batch["obs"], batch["r"], batch["t"], batch["angles"]):
        np.testing.assert_allclose(r + t, optics.stokes_from_images(obs, angles)[0], atol=2e-5)
    assert (batch["r"].reshape(6, -1).max(axis=1) == 0).any()         # a view without glass: R = 0


@pytest.mark.slow
@needs_captures
def test_semireal_scenes_have_exact_ground_truth():
    captures = [c for c in NO_GLASS if c.name in ("dphr2022-outdoor-01", "imx250mzr-fruits")]
    scenes = semireal.make_scenes(captures, size=64)
    conditions = {(s.capture, s.condition) for s in scenes}
    assert ("dphr2022-outdoor-01", "3 shots, colour made grey") in conditions
    assert ("imx250mzr-fruits", "3 shots, colour made grey") not in conditions
    assert ("imx250mzr-fruits", "3 shots, faint reflection") in conditions
    for scene in scenes:
        expected = int(scene.condition[0]) if scene.condition[0].isdigit() else 3
        assert len(scene.shots) == len(scene.angles_deg) == expected
        s0 = optics.stokes_from_images(scene.shots, np.radians(scene.angles_deg))[0]
        # nominal angles are off by up to 2 deg and the shots carry zero-mean noise: S0 holds on average
        assert abs(s0.mean() - (scene.r + scene.t).mean()) < 0.01 * (scene.r + scene.t).mean()
        if scene.condition == "no glass":
            assert not scene.r.any()
        else:
            lo, hi = semireal.FAINT_STRENGTH if scene.condition.endswith("faint reflection") else semireal.STRENGTH
            assert lo * 0.999 < scene.r.mean() / scene.t.mean() < hi * 1.001
    again = semireal.make_scenes(captures[::-1], size=64)          # a capture's scenes do not depend on the list
    first = [s for s in scenes if s.capture == captures[0].name]
    np.testing.assert_array_equal(first[3].shots, [s for s in again if s.capture == captures[0].name][3].shots)


@needs_captures
def test_semireal_tables_score_every_method():
    captures = [c for c in NO_GLASS if c.name == "dphr2022-outdoor-01"]
    tables, records = semireal.run_semireal(("none", "schechner"), size=48, captures=captures)
    assert "| 3 shots | 2 |" in tables and "| 6 shots | 1 |" in tables
    none_share = [r["r_share"] for r in records if r["method"] == "none" and r["condition"] == "no glass"]
    assert none_share == [0.0]
    assert "| **mean** | **0.0%** |" in tables


def test_semireal_goes_alone():
    result = CliRunner().invoke(app, ["bench", "--semireal", "--count", "4"])
    assert result.exit_code == 2
    assert "--semireal goes alone" in result.output
    result = CliRunner().invoke(app, ["bench", "--weights", "x.pt"])
    assert result.exit_code == 2 and "--weights goes with --semireal" in result.output
