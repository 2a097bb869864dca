"""Baselines, each on synthetic data that meets its own assumptions, against doing nothing (T̂ = S0)."""

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import skimage.data

from rig import capture_virtual
from separate import metrics, optics
from separate.baselines import arvanitopoulos, farid, kong, li_brown, schechner
from separate.baselines.common import canonical
from separate.methods import METHODS
from urd.core.dataset import Dataset
from urd.ingest import IngestOptions, ingest_scene

ANGLES = [0.0, 45.0, 90.0]


def layers(size=256):
    refl = optics.photo_to_linear(cv2.resize(skimage.data.astronaut(), (size, size), interpolation=cv2.INTER_AREA))
    trans = optics.photo_to_linear(cv2.resize(skimage.data.coffee()[:, 100:500], (size, size), interpolation=cv2.INTER_AREA))
    return refl.astype(np.float32), trans.astype(np.float32)


def shots(refl, trans, theta, phi_perp=np.radians(10.0)):
    return np.stack([optics.render(refl, trans, theta, phi_perp, np.radians(a)) for a in ANGLES]).astype(np.float32)


def no_separation_psnr(refl, trans, theta):
    """PSNR of T̂ = S0 = R_obs + T_obs against T_obs: what doing nothing scores."""
    r_true, t_true = optics.observable_layers(refl, trans, theta)
    return metrics.psnr(r_true + t_true, t_true)


def test_schechner_recovers_layers_and_angle_with_a_uniform_aoi():
    refl, trans = layers(128)
    theta = np.radians(37.0)
    stack = shots(refl, trans, theta)
    r_true, t_true = optics.observable_layers(refl, trans, theta)
    i_perp, i_par, _ = canonical(stack, ANGLES)
    estimate = schechner.estimate_theta(i_perp, i_par, np.arange(2.0, 88.0, 0.5))
    assert abs(np.degrees(estimate) - 37.0) <= 2.0
    r_hat, t_hat = schechner.separate(stack, ANGLES)
    # measured: T̂ 60.0 dB (exact up to the PSNR floor), no separation 36.1 dB
    assert metrics.psnr(t_hat, t_true) >= no_separation_psnr(refl, trans, theta) + 15
    assert metrics.psnr(r_hat, r_true) >= 30


def test_farid_separates_two_independent_sources_up_to_scale():
    refl, trans = layers(128)
    theta = np.radians(50.0)
    stack = shots(refl, trans, theta)
    r_hat, t_hat = farid.separate(stack, ANGLES)
    r_true, t_true = optics.observable_layers(refl, trans, theta)
    assert abs(np.corrcoef(t_hat.ravel(), t_true.ravel())[0, 1]) >= 0.95
    assert abs(np.corrcoef(r_hat.ravel(), r_true.ravel())[0, 1]) >= 0.95
    # with the scale fixed by R̂ + T̂ ≈ S0, measured: T̂ 60.0 dB, no separation 33.6 dB (53.2 and 33.4 at 256²)
    assert metrics.psnr(t_hat, t_true) >= no_separation_psnr(refl, trans, theta) + 10


@pytest.mark.slow
def test_kong_handles_a_varying_angle_of_incidence_better_than_one_global_angle():
    refl, trans = layers(128)
    theta = np.broadcast_to(np.radians(np.linspace(25, 70, 128))[None, :], (128, 128)).astype(np.float32)
    stack = shots(refl, trans, theta)
    r_true, t_true = optics.observable_layers(refl, trans, theta)
    kong_t = metrics.psnr(kong.separate(stack, ANGLES)[1], t_true)
    global_t = metrics.psnr(schechner.separate(stack, ANGLES)[1], t_true)
    # measured: Kong 41.9 dB, Schechner's one global angle 32.1 dB, no separation 31.3 dB
    assert kong_t >= no_separation_psnr(refl, trans, theta) + 6 and kong_t >= global_t + 5


def test_kong_energy_gradient_matches_central_differences():
    # Kong's θ search uses a gradient derived by hand (exclusion, positivity penalty, smoothness):
    # every pixel's entry must match the energy's own central difference
    from separate.baselines import kong

    rng = np.random.default_rng(5)
    theta = rng.uniform(0.4, 1.2, (8, 9))
    i_perp, i_par = rng.uniform(0.2, 1.0, (2, 8, 9))
    i_par *= 0.6                                                # mostly I⊥ > I∥, some negative layers
    energy, grad = kong._energy(theta, i_perp, i_par, smoothness=0.3)
    assert grad.shape == theta.shape and np.isfinite(energy)
    step = 1e-6
    numeric = np.zeros_like(theta)
    for index in np.ndindex(theta.shape):
        up, down = theta.copy(), theta.copy()
        up[index] += step
        down[index] -= step
        numeric[index] = (kong._energy(up, i_perp, i_par, 0.3)[0] - kong._energy(down, i_perp, i_par, 0.3)[0]) / (2 * step)
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-7 * np.abs(numeric).max())


# T̂'s PSNR minus no separation's, measured with a σ = 4 px blurred reflection (the single-image methods' own
# assumption) at two strengths: 0.5 × — Li & Brown +0.83 dB, Arvanitopoulos +0.21 dB (not much worse than
# nothing is asked); 0.8 × — +0.99 dB and +1.40 dB (the reflection must be reduced).
@pytest.mark.parametrize("module", [li_brown, arvanitopoulos])
@pytest.mark.parametrize("strength,margin_db", [(0.5, -0.3), (0.8, 0.5)])
def test_single_image_methods_remove_a_blurred_reflection(module, strength, margin_db):
    refl, trans = layers()
    image = (trans * 0.7 + cv2.GaussianBlur(refl, (0, 0), 4) * strength).astype(np.float32)
    stack = np.stack([image / 2] * 3)                  # unpolarized: every shot is S0/2
    r_hat, t_hat = module.separate(stack, ANGLES)
    assert metrics.psnr(t_hat, trans * 0.7) > metrics.psnr(image, trans * 0.7) + margin_db
    np.testing.assert_allclose(r_hat + t_hat, image, atol=1e-4)


# T̂'s PSNR minus no separation's on the virtual camera's scene below (a curved pane, θ ≈ 30–70° across it,
# a strong sharp reflection), measured through `urd separate` (reference estimated) for capture seeds 1/2/3:
# Kong +0.28/+0.41/+0.51 dB, Schechner +0.20/+0.19/+0.47 (one global θ), Farid −1.59/−0.02/−0.15 (one global
# mixing cannot fit a varying θ), CEILNet +0.04/−0.01/0.00, Li & Brown −4.9/−5.1/−5.1 and Arvanitopoulos
# −6.9/−7.1/−7.0 (they expect a blurred reflection; this one is sharp). Their own data: the tests above.
# Farid's ICA swings from 12.7 to 23.3 dB T̂ PSNR on this scene as the reference moves from 8° to 12° (the true
# φ⊥ runs 7-13°; with the true field it scores 15.5 dB): its margin only says it runs and stays in range.
MARGIN_DB = {"none": -0.01, "kong": 0.1, "schechner": 0.0, "farid": -8.0, "ceilnet": -0.5, "li-brown": -6.0,
             "arvanitopoulos": -8.0}


@pytest.fixture(scope="module")
def virtual_scene(tmp_path_factory):
    """One captured and ingested scene that every method separates (into its own results folder)."""
    ds = Dataset.open_or_create(tmp_path_factory.mktemp("methods") / "ds")
    scene, _ = capture_virtual(ds, size=(256, 192), shake_px=2, shake_deg=0.2, seed=1)
    ingest_scene(scene, IngestOptions())
    return scene, ds.root


# Kong's and Farid's optimizations take most of their ~10 s here: slow (both run fast in the tests above, and
# Kong through `urd separate` in the parameters test below).
@pytest.mark.parametrize("method", [pytest.param(m, marks=pytest.mark.slow) if m in ("kong", "farid") else m
                                    for m in METHODS if m != "network"])
def test_each_method_runs_through_urd_separate(virtual_scene, method):
    from typer.testing import CliRunner

    from urd.cli import app

    scene, root = virtual_scene
    out = CliRunner().invoke(app, ["separate", "scene_01", "--dataset", str(root), "--method", method])  # in-process: no 2 s start-up
    assert out.exit_code == 0, out.output
    entry = scene.load()["results"][method]
    figures = entry["truth_metrics"]
    assert {"R.tiff", "T.tiff", "R_preview.png", "T_preview.png"} <= {Path(f["file"]).name for f in entry["files"]}
    assert figures["T"]["psnr_db"] > figures["T_no_separation"]["psnr_db"] + MARGIN_DB[method]


@pytest.mark.slow
def test_baseline_parameters_from_the_command_line(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=(128, 96), shake_px=1, shake_deg=0.1, seed=2)
    ingest_scene(scene, IngestOptions())
    base = [sys.executable, "-m", "urd.cli", "separate", "scene_01", "--dataset", str(tmp_path / "ds"), "--method", "kong"]
    out = subprocess.run(base + ["--param", "smoothness=0.5", "--param", "steps=10"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert scene.load()["results"]["kong"]["parameters"] == {"smoothness": 0.5, "steps": 10}
    out = subprocess.run(base + ["--force", "--param", "lambda=3"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 2 and "unknown parameters ['lambda']" in out.stderr and "smoothness" in out.stderr


@pytest.mark.parametrize("name", ["schechner", pytest.param("kong", marks=pytest.mark.slow), "farid", "li-brown", "arvanitopoulos"])
def test_every_baseline_returns_no_negative_light_but_its_side_trial_keeps_the_inversions_values(name):
    """A method's layers are clipped at 0, as the network's are and as the result files hold
    them (so benchmarks score every method alike); the side trial reads the raw inversion."""
    from separate.methods import get_method

    rng = np.random.default_rng(3)
    s0 = rng.uniform(0.05, 0.6, (24, 32, 3)).astype(np.float32)
    stokes = optics.stokes_from_polarization(s0, rng.uniform(0.0, 0.9, s0.shape), rng.uniform(0, np.pi, s0.shape))
    shots = np.stack([optics.intensity_from_stokes(stokes, np.radians(a)) for a in (0.0, 45.0, 90.0)]).astype(np.float32)
    run, _ = get_method(name)
    r_hat, t_hat = run(shots, [0.0, 45.0, 90.0], 30.0)
    assert r_hat.dtype == t_hat.dtype == np.float32 and r_hat.min() >= 0 and t_hat.min() >= 0
    if name in ("schechner", "kong", "farid"):
        raw = run(shots, [0.0, 45.0, 90.0], 30.0, trial=True)
        assert min(float(raw[0].min()), float(raw[1].min())) < 0          # this stack makes the inversion go negative
        np.testing.assert_array_equal(np.maximum(raw[1], 0), t_hat)
