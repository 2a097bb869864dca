"""Baselines, each on synthetic data that meets its own assumptions."""

import subprocess
import sys

import cv2
import numpy as np
import pytest
import skimage.data

from rig import capture_virtual
from separate import metrics, optics
from separate.baselines import arvanitopoulos, farid, kong, li_brown, schechner
from separate.baselines.common import canonical
from separate.methods import METHODS
from separate.synthesis import to_linear
from urd.dataset import Dataset
from urd.ingest import IngestOptions, ingest_scene

ANGLES = [0.0, 45.0, 90.0]


def layers(size=256):
    refl = to_linear(cv2.resize(skimage.data.astronaut(), (size, size), interpolation=cv2.INTER_AREA))
    trans = to_linear(cv2.resize(skimage.data.coffee()[:, 100:500], (size, size), interpolation=cv2.INTER_AREA))
    return refl.astype(np.float32), trans.astype(np.float32)


def shots(refl, trans, theta, phi_perp=np.radians(10.0)):
    return np.stack([optics.render(refl, trans, theta, phi_perp, np.radians(a)) for a in ANGLES]).astype(np.float32)


def test_schechner_recovers_layers_and_angle_with_a_uniform_aoi():
    refl, trans = layers()
    theta = np.radians(37.0)
    stack = shots(refl, trans, theta)
    r_true, t_true = optics.observable_layers(refl, trans, theta)
    i_perp, i_par, _ = canonical(stack, ANGLES)
    estimate = schechner.estimate_theta(i_perp, i_par, np.arange(2.0, 88.0, 0.5))
    assert abs(np.degrees(estimate) - 37.0) <= 2.0
    r_hat, t_hat = schechner.separate(stack, ANGLES)
    assert metrics.psnr(t_hat, t_true) >= 30 and metrics.psnr(r_hat, r_true) >= 30


def test_farid_separates_two_independent_sources_up_to_scale():
    refl, trans = layers()
    stack = shots(refl, trans, np.radians(50.0))
    r_hat, t_hat = farid.separate(stack, ANGLES)
    r_true, t_true = optics.observable_layers(refl, trans, np.radians(50.0))
    assert abs(np.corrcoef(t_hat.ravel(), t_true.ravel())[0, 1]) >= 0.95
    assert abs(np.corrcoef(r_hat.ravel(), r_true.ravel())[0, 1]) >= 0.95


def test_kong_handles_a_varying_angle_of_incidence_better_than_one_global_angle():
    refl, trans = layers()
    theta = np.broadcast_to(np.radians(np.linspace(25, 70, 256))[None, :], (256, 256)).astype(np.float32)
    stack = shots(refl, trans, theta)
    r_true, t_true = optics.observable_layers(refl, trans, theta)
    none = metrics.psnr(r_true + t_true, t_true)
    kong_t = metrics.psnr(kong.separate(stack, ANGLES)[1], t_true)
    global_t = metrics.psnr(schechner.separate(stack, ANGLES)[1], t_true)
    assert kong_t > none + 3 and kong_t > global_t


@pytest.mark.parametrize("module", [li_brown, arvanitopoulos])
def test_single_image_methods_remove_a_blurred_reflection_better_than_nothing(module):
    refl, trans = layers()
    blurred = cv2.GaussianBlur(refl, (0, 0), 4) * 0.5
    image = (trans * 0.7 + blurred).astype(np.float32)
    stack = np.stack([image / 2] * 3)                  # unpolarized: every shot is S0/2
    stack[1] = image / 2                               # (angles still well-posed)
    r_hat, t_hat = module.separate(stack, ANGLES)
    assert metrics.psnr(t_hat, trans * 0.7) > metrics.psnr(image, trans * 0.7) + 0.1
    np.testing.assert_allclose(r_hat + t_hat, image, atol=1e-4)


@pytest.mark.parametrize("method", [m for m in METHODS if m != "network"])
def test_each_method_runs_through_urd_separate(tmp_path, method):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=(256, 192), shake_px=2, shake_deg=0.2, seed=1)
    ingest_scene(scene, IngestOptions())
    out = subprocess.run([sys.executable, "-m", "urd.cli", "separate", "scene_01", "--dataset", str(tmp_path / "ds"),
                          "--method", method], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    entry = scene.load()["results"][method]
    assert len(entry["files"]) == 4 and entry["truth_metrics"]["T"]["psnr_db"] > 10


def test_baseline_parameters_from_the_command_line(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=(128, 96), shake_px=1, shake_deg=0.1, seed=2)
    ingest_scene(scene, IngestOptions())
    base = [sys.executable, "-m", "urd.cli", "separate", "scene_01", "--dataset", str(tmp_path / "ds"), "--method", "kong"]
    out = subprocess.run(base + ["--param", "smoothness=0.5", "--param", "steps=10"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert scene.load()["results"]["kong"]["parameters"] == {"smoothness": 0.5, "steps": 10}
    out = subprocess.run(base + ["--force", "--param", "lambda=3"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 1 and "unknown parameters ['lambda']" in out.stderr and "smoothness" in out.stderr
