"""Polarizer calibration: offset sweep, per-shot angle errors, application to the Stokes fit."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import tifffile

from acquire.virtual_camera import shot_truth
from calib.polarizer import _solve_angles, check_direction, estimate_shot_errors, fit_offset
from calib.store import calibrate_shots
from separate.methods import get_method
from conftest import shared_data
from rig import capture_virtual
from separate import optics
from urd.core.dataset import Dataset
from urd.core.errors import CalibrationError
from urd.ingest import IngestOptions, ingest_scene
from urd.separation import separate_scene


def urd(*args):
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True, timeout=600)


def test_malus_fit_recovers_a_known_offset():
    stage = np.arange(0, 180, 10.0)
    target, offset = 30.0, 12.5
    light = 0.2 + 0.5 * np.cos(np.radians(stage + offset - target)) ** 2
    fit = fit_offset(stage, light + np.random.default_rng(0).normal(0, 1e-3, stage.size), target)
    assert fit.offset_deg == pytest.approx(offset, abs=0.15) and fit.uncertainty_deg < 0.1
    assert abs(fit.offset_deg - offset) < 4 * fit.uncertainty_deg
    assert fit.modulation == pytest.approx(0.25 / 0.45, abs=0.005)     # (max − min)/(max + min) of the light
    assert 0.5e-3 < fit.residual_rms < 2e-3                           # the 1e-3 noise
    with pytest.raises(CalibrationError, match="no Malus modulation"):
        fit_offset(stage, np.full(stage.size, 0.5))


def test_blocks_holding_a_pixel_clipped_in_any_shot_stay_out_of_the_shot_error_fit():
    import cv2

    rng = np.random.default_rng(3)
    h, w = 256, 384
    s0 = cv2.GaussianBlur(rng.uniform(0.3, 0.8, (h, w, 3)).astype(np.float32), (0, 0), 6)
    aolp = cv2.GaussianBlur(rng.uniform(0, np.pi, (h, w)).astype(np.float32), (0, 0), 20)[..., None]
    stokes = np.stack([s0, 0.4 * s0 * np.cos(2 * aolp), 0.4 * s0 * np.sin(2 * aolp)])
    nominal = [0, 36, 72, 108, 144]
    stack = np.stack([optics.intensity_from_stokes(stokes, np.radians(a)) for a in nominal]).astype(np.float32)
    glints = rng.random((h, w)) < 0.008                       # specular glints clipped in two shots: 0.8% of pixels
    for k in (1, 3):
        stack[k][glints] = 1.0
    found = estimate_shot_errors(stack, nominal)
    np.testing.assert_allclose(found.errors_deg, 0.0, atol=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("offset", [7.3, 131.0])
def test_offset_sweep_on_the_virtual_rig_then_capture_uses_it(tmp_path, offset):
    out = urd("calibrate", "offset", tmp_path / "ds", "--stage", "sim", "--camera", "virtual",
              "--sim-offset", offset, "--target-angle", 20)
    assert out.returncode == 0, out.stderr
    record = json.loads((tmp_path / "ds" / "calibration.json").read_text())
    assert abs((record["offset_deg"] - offset + 90) % 180 - 90) < 0.2
    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-offset", offset,
              "--sim-size", "96x64")
    assert out.returncode == 0, out.stderr
    scene = Dataset.open(tmp_path / "ds").scene("scene_01")
    for shot in scene.load()["shots"]:
        true = shot_truth(scene.path / shot["file"])["true_angle_deg"]
        assert abs((true - shot["angle_commanded_deg"] + 90) % 180 - 90) < 0.2


def test_four_angles_leave_one_direction_unobservable_and_five_determine_all():
    rng = np.random.default_rng(1)
    stokes = np.stack([rng.uniform(1, 2, 4000), rng.uniform(-0.5, 0.5, 4000), rng.uniform(-0.5, 0.5, 4000)])
    for count in (4, 5, 6):
        nominal = np.radians(np.arange(count) * 180.0 / count)
        errors = np.radians(rng.uniform(-4, 4, count))
        errors -= errors.mean()
        found, _, unobservable = _solve_angles(optics.stokes_matrix(nominal + errors) @ stokes, nominal)
        if count == 4:
            # a different set of angles explains the noiseless images exactly
            assert np.abs(found - nominal - errors).max() > np.radians(0.1)
            assert unobservable is not None
            assert np.linalg.norm(found - nominal) < np.linalg.norm(errors)     # never worse than nominal
        else:
            assert unobservable is None
            np.testing.assert_allclose(found - nominal, errors, atol=1e-6)


@pytest.mark.slow
def test_per_shot_errors_on_the_virtual_rig_and_their_effect_on_the_stokes_fit(tmp_path, capsys):
    ds = Dataset.open_or_create(tmp_path / "ds")
    angles = (0, 30, 60, 90, 120, 150)
    scene, cam = capture_virtual(ds, angles=angles, size=(768, 512), shake_px=4, shake_deg=0.5, seed=11, jitter_deg=2.0)
    ingest_scene(scene, IngestOptions())
    separate_scene(scene, "none", *get_method("none"))
    separated = shutil.copytree(scene.path.parent, tmp_path / "separated")      # for the command line below
    before = (scene.path / "scene.json").read_bytes()
    dry = calibrate_shots(scene, apply=False)
    assert (scene.path / "scene.json").read_bytes() == before                 # --no-apply: the manifest as it was
    result = calibrate_shots(scene)
    assert result.errors_deg == dry.errors_deg
    assert scene.reload().status().stale == ("none",)          # separated at the nominal angles
    record = scene.load()
    true = np.array([shot_truth(scene.path / s["file"])["scene_angle_deg"] for s in record["shots"]])   # aligned frame
    uncalibrated = np.array(scene.uncalibrated_angles_deg())          # the stage's angles, turned with the camera
    stage_truth = np.array([shot_truth(scene.path / s["file"])["true_angle_deg"] for s in record["shots"]])
    np.testing.assert_allclose(uncalibrated - scene.stage_angles_deg(), true - stage_truth, atol=0.05)   # the turns
    true_err = true - uncalibrated
    assert np.abs(true_err).max() > 1.0                               # the jitter is real
    assert np.abs(np.array(result.errors_deg) - (true_err - true_err.mean())).max() < 0.5
    # Stokes with the calibrated angles is closer to the truth (the same stack fitted with the true
    # angles, so that only the angles differ) than with the nominal ones
    stack, calibrated = scene.reload().load_stack()
    truth = optics.stokes_from_images(stack, np.radians(true))
    rows = {}
    for name, used in (("nominal", uncalibrated), ("calibrated", np.array(calibrated))):
        used = used + (true - used).mean()            # the common rotation is the offset calibration's job
        est = optics.stokes_from_images(stack, np.radians(used))
        rows[name] = float(np.sqrt(np.mean((est[1:] - truth[1:]) ** 2)))
    with capsys.disabled():
        print(f"\nS1,S2 RMS error vs truth: nominal angles {rows['nominal']:.5f}, calibrated {rows['calibrated']:.5f}")
    assert rows["calibrated"] < 0.7 * rows["nominal"]
    from typer.testing import CliRunner

    from urd.cli import app

    out = CliRunner().invoke(app, ["calibrate", "shots", str(separated / "scene_01")])     # said where a user looks
    said = " ".join(out.output.split())
    assert out.exit_code == 0 and "the shots moved between frames (up to" in said and "calibrate from a tripod" in said
    assert f"results of none are now stale (separated at other angles than the calibrated ones); renew them with: urd " \
           f"separate scene_01 --dataset {separated} --method none --force" in said
    again = " ".join(CliRunner().invoke(app, ["calibrate", "shots", str(separated / "scene_01")]).output.split())
    assert "now stale" not in again                                  # stale before: not said again


def test_angles_the_images_do_not_determine_are_refused_and_nothing_is_stored(tmp_path):
    """The virtual camera's default scene at 384×256, shaken by a pixel and up to half a degree, is
    polarized too weakly for the noise and the registration's error: the fit slid all six angles
    to one (105°) and stored them, and the scene could not be separated. (From a tripod,
    ``--sim-shake 0``, the same scene calibrates.)"""
    from typer.testing import CliRunner

    from urd.cli import app

    root = str(tmp_path / "ds")
    out = CliRunner().invoke(app, ["capture", root, "--stage", "sim", "--camera", "virtual", "--sim-size", "384x256",
                                   "--sim-shake", "1", "--angles", "0,30,60,90,120,150"])
    assert out.exit_code == 0, out.output
    assert CliRunner().invoke(app, ["ingest", root]).exit_code == 0
    manifest = tmp_path / "ds" / "scene_01" / "scene.json"
    before = manifest.read_bytes()
    out = CliRunner().invoke(app, ["calibrate", "shots", "scene_01", "--dataset", root])
    assert out.exit_code == 1 and "do not determine the shots' angles: the fit moves them by up to" in out.stderr
    assert manifest.read_bytes() == before


def test_three_angles_cannot_be_calibrated(tmp_path):
    with pytest.raises(CalibrationError, match="at least 4 angles"):
        estimate_shot_errors(np.zeros((3, 64, 64, 1)), [0, 45, 90])


@pytest.mark.parametrize("name", ["glass", "liquid", "painting"])
def test_real_division_of_time_captures(name, capsys):
    folder = shared_data("polarization", "lapray2018-nir", name)
    stack = np.stack([tifffile.imread(folder / f"nir_{a}.tif").astype(np.float32) / 65535 for a in (0, 45, 90, 135)])
    result = estimate_shot_errors(stack[..., None], [0, 45, 90, 135])
    with capsys.disabled():
        print(f"\nlapray2018 {name}: per-shot errors {np.round(result.errors_deg, 2)} ± {np.round(result.uncertainty_deg, 2)} deg")
    assert np.all(np.abs(result.errors_deg) < 4.0)          # the paper's ±4° budget
    assert result.unobservable is not None                  # 4 angles: one combination unseen


def sweep_fit(target_deg: float, offset_deg: float, direction: float):
    """The fit of a noiseless sweep of a fully polarized target at ``target_deg`` through a polarizer
    at offset + direction · stage angle (deg)."""
    stage = np.arange(0.0, 180.0, 10.0)
    return fit_offset(stage, np.cos(np.radians(offset_deg + direction * stage - target_deg)) ** 2, target_deg)


def test_two_sweeps_tell_the_stages_sense_of_rotation_which_one_cannot():
    ccw, cw = sweep_fit(10.0, 7.0, 1.0), sweep_fit(10.0, 7.0, -1.0)
    assert ccw.residual_rms < 1e-9 and cw.residual_rms < 1e-9               # one sweep fits either sense exactly
    assert check_direction(ccw, 10.0, sweep_fit(55.0, 7.0, 1.0), 55.0) == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(CalibrationError, match="turns the polarizer clockwise as the camera sees it: .* differ by 90.00 deg"):
        check_direction(cw, 10.0, sweep_fit(55.0, 7.0, -1.0), 55.0)
    with pytest.raises(CalibrationError, match="turns by 85.0 deg between the sweeps"):
        check_direction(ccw, 10.0, sweep_fit(95.0, 7.0, 1.0), 95.0)
    with pytest.raises(CalibrationError, match="which neither sense of rotation explains"):
        check_direction(ccw, 10.0, sweep_fit(55.0, 37.0, 1.0), 55.0)


@pytest.mark.slow
def test_the_direction_check_on_the_virtual_rig_records_a_counter_clockwise_stage_and_refuses_a_reversed_one(tmp_path):
    out = urd("calibrate", "offset", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-offset", 7,
              "--target-angle", 10, "--check-direction", 55)
    assert out.returncode == 0, out.stderr
    assert "sense of rotation: counter-clockwise, as urd takes it" in out.stdout
    record = json.loads((tmp_path / "ds" / "calibration.json").read_text())
    assert record["direction"]["target_angle_deg"] == 55.0 and abs(record["direction"]["difference_deg"]) < 0.1
    assert record["direction"]["sweep"] == "calibration/sweep_02"
    out = urd("calibrate", "offset", tmp_path / "rev", "--stage", "sim", "--camera", "virtual", "--sim-offset", 7,
              "--target-angle", 10, "--check-direction", 55, "--sim-reversed")
    assert out.returncode == 1 and "the stage turns the polarizer clockwise as the camera sees it" in out.stderr
    assert not (tmp_path / "rev" / "calibration.json").exists()
    assert sorted(p.name for p in (tmp_path / "rev" / "calibration").iterdir()) == ["sweep_01", "sweep_02"]   # kept to look at


def test_a_target_turn_that_cannot_tell_the_sense_is_refused_before_any_sweep(tmp_path):
    out = urd("calibrate", "offset", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--target-angle", 0,
              "--check-direction", 90)
    assert out.returncode == 1 and "turns by 90.0 deg between the sweeps" in out.stderr
    assert not (tmp_path / "ds" / "calibration").exists()


def test_a_turn_about_the_frames_centre_is_no_shift(tmp_path):
    import cv2

    from calib.store import shot_motion
    from urd.core.files import write_json_atomic

    scene, _ = capture_virtual(Dataset.open_or_create(tmp_path / "ds"), size=(640, 480), shake_px=0, shake_deg=0)
    ingest_scene(scene, IngestOptions())
    record = scene.load()
    turn = cv2.getRotationMatrix2D((320.0, 240.0), 0.02, 1.0)       # a warp turning about the centre, not about (0, 0)
    record["ingest"]["alignment"][1].update(warp=turn.tolist(), turn_deg=-0.02)
    record["ingest"]["alignment"][2].update(warp=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], turn_deg=0.0)
    write_json_atomic(scene.manifest_path, record)
    shift, turned = shot_motion(scene.reload())
    assert shift < 1e-6 and turned == pytest.approx(0.02)
