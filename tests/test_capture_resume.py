"""Stopping and resuming `urd capture`: the printed command resumes the scene as it was started,
another camera or stage is refused, Ctrl-C after the last shot leaves a complete scene, a
mounting offset belongs to the stage it was calibrated on, an unusable camera leaves nothing."""

import json
import os
import re
import shlex
import shutil
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from acquire.plan import new_capture_scene, resume_command
from acquire.virtual_camera import VirtualCamera, shot_truth
from conftest import stop_capture_before_shot
from urd.cli import app
from urd.core.dataset import Dataset
from urd.core.progress import TerminalProgress

SIM = ("--stage", "sim", "--camera", "virtual")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def resume_line(stderr):
    match = re.search(r"Resume with: (.+)$", stderr, re.M)
    assert match, stderr
    return match.group(1)


def interrupted_scene(root, monkeypatch, *options):
    """Capture at 96×64 (seed 3, 0/60/120 deg, plus ``options``) stopped before shot 1; the printed resume command."""
    stop_capture_before_shot(monkeypatch, 1)
    out = invoke("capture", root, *SIM, "--sim-size", "96x64", "--seed", "3", "--angles", "0,60,120", *options)
    monkeypatch.undo()
    assert out.exit_code == 130, out.output
    return resume_line(out.stderr)


def test_the_printed_resume_command_resumes_with_the_settings_the_scene_was_started_with(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    command = interrupted_scene(root, monkeypatch, "--sim-shake", "2", "--sim-turn", "3", "--sim-offset", "1.5", "--sim-reversed")
    for option in ("--sim-size 96x64", "--seed 3", "--sim-shake 2", "--sim-turn 3", "--sim-offset 1.5", "--angles 0,60,120",
                   "--scene scene_01", "--sim-reversed"):
        assert option in command
    words = shlex.split(command)
    assert words[:2] == ["urd", "capture"]
    out = invoke(*words[1:])
    assert out.exit_code == 0, out.output
    record = Dataset.open(root).scene("scene_01").load(verify=True)
    assert record["capture"]["complete"] and [s["angle_commanded_deg"] for s in record["shots"]] == [0, 60, 120]
    assert {(s["camera"]["width"], s["camera"]["height"]) for s in record["shots"]} == {(96, 64)}
    assert record["capture"]["camera"]["shake_deg"] == 3.0


def test_resuming_with_another_camera_or_stage_is_refused_and_names_the_command_that_resumes(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    command = interrupted_scene(root, monkeypatch)
    for other in (("--sim-size", "64x48", "--seed", "3"), ("--sim-size", "96x64", "--seed", "3", "--sim-offset", "2")):
        out = invoke("capture", root, *SIM, *other)
        assert out.exit_code == 1, out.output
        assert "scene_01 was captured with" in out.stderr and command in out.stderr and "--new-scene" in out.stderr
    assert "camera width 96 (this one: 64)" in invoke("capture", root, *SIM, "--sim-size", "64x48", "--seed", "3").stderr
    ds = Dataset.open(root)
    assert ds.scene_names() == ["scene_01"] and len(ds.scene("scene_01").shots()) == 1


def test_a_plain_capture_resumes_the_scene_with_its_own_angles(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    interrupted_scene(root, monkeypatch)
    out = invoke("capture", root, *SIM, "--sim-size", "96x64", "--seed", "3", "--tolerance", "0.2")
    assert out.exit_code == 1 and "tolerance 0.5 deg (asked for: 0.2)" in out.stderr
    out = invoke("capture", root, *SIM, "--sim-size", "96x64", "--seed", "3")
    assert out.exit_code == 0, out.output
    scene = Dataset.open(root).scene("scene_01")
    assert scene.status().state == "captured" and [s.angle_commanded_deg for s in scene.shots()] == [0, 60, 120]
    record = (scene.path / "scene.json").read_bytes()
    out = invoke("capture", root, *SIM, "--sim-size", "96x64", "--seed", "3", "--scene", "scene_01")
    assert out.exit_code == 1 and "scene_01 is complete (3 shots); capture another scene" in out.stderr
    assert (scene.path / "scene.json").read_bytes() == record
    truth = {p.name: p.read_bytes() for p in scene.truth_dir().iterdir()}
    shutil.rmtree(scene.truth_dir())                          # as the recovery sets a torn truth folder aside
    out = invoke("capture", root, *SIM, "--sim-size", "96x64", "--seed", "3", "--scene", "scene_01")
    assert out.exit_code == 0, out.output
    assert {p.name: p.read_bytes() for p in scene.truth_dir().iterdir()} == truth    # written again, the same


def test_a_dataset_is_never_made_inside_another(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM, "--sim-size", "96x64").exit_code == 0
    for inside in (root / "scene_01", root / "scene_01" / "raw", root / "elsewhere"):
        out = invoke("capture", inside, *SIM, "--sim-size", "96x64")
        assert out.exit_code == 1 and f"is inside the dataset {root.resolve()}" in out.stderr, out.output
    assert not (root / "elsewhere").exists() and not (root / "scene_01" / "scene_01").exists()
    assert Dataset.open(root).scene_names() == ["scene_01"]
    (tmp_path / "tool").mkdir()
    (tmp_path / "tool" / "dataset.json").write_text('{"name": "another tool\'s dataset"}')
    assert invoke("capture", tmp_path / "tool" / "shoot", *SIM, "--sim-size", "96x64").exit_code == 0
    out = invoke("capture", tmp_path / "other", *SIM, "--sim-size", "96x64", "--scene", "../evil")
    assert out.exit_code == 2 and "expected a scene name like scene_01" in out.stderr
    assert not (tmp_path / "other").exists()


def test_a_real_rigs_resume_command_names_its_address_and_tolerance(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    info = {"stage": {"kind": "ELL14", "port": "/dev/ttyUSB0", "address": "3", "serial": "11400123"},
            "camera": {"kind": "gphoto2", "model": "Canon EOS 550D", "serial": "0123"}}
    scene = new_capture_scene(ds, [0, 45, 90, 135], tolerance_deg=0.2, info=info)
    command = resume_command(ds.root, scene)
    assert command == (f"urd capture {ds.root.resolve()} --stage /dev/ttyUSB0 --camera gphoto2 --angles 0,45,90,135 "
                       "--scene scene_01 --address 3 --tolerance 0.2")


@pytest.mark.parametrize("where", ["after the last shot is recorded", "while the ground truth is written"])
def test_ctrl_c_after_the_last_shot_leaves_a_complete_scene_and_no_resume_command(tmp_path, monkeypatch, where):
    if where == "while the ground truth is written":
        def interrupt(self, folder):
            raise KeyboardInterrupt

        monkeypatch.setattr(VirtualCamera, "write_truth", interrupt)
    else:
        show = TerminalProgress.__call__

        def interrupt(self, done, total, label):
            show(self, done, total, label)
            if label.startswith("capture") and done == total - 1:          # the last shot's record step
                raise KeyboardInterrupt

        monkeypatch.setattr(TerminalProgress, "__call__", interrupt)
    out = invoke("capture", tmp_path / "ds", *SIM, "--sim-size", "96x64")
    assert out.exit_code == 130, out.output
    assert "Resume with" not in out.stderr and "every shot was taken" in out.stderr
    scene = Dataset.open(tmp_path / "ds").scene("scene_01")
    assert scene.status().state == "captured" and len(scene.shots()) == 3


def test_a_mounting_offset_is_applied_only_with_the_stage_it_was_calibrated_on(tmp_path):
    root = tmp_path / "ds"
    out = invoke("calibrate", "offset", root, *SIM, "--sim-offset", "3", "--step", "20")
    assert out.exit_code == 0, out.output
    record = json.loads((root / "calibration.json").read_text())
    assert record["stage"] == {"kind": "ELL14 simulator", "sim_offset_deg": 3.0}
    out = invoke("capture", root, *SIM, "--sim-size", "96x64")
    assert out.exit_code == 1, out.output
    assert "was calibrated on the simulated ELL14 with --sim-offset 3, not on this stage" in out.stderr
    assert Dataset.open(root).scene_names() == []
    printed = re.search(r"calibrate this stage with '([^']+)'", " ".join(out.stderr.split())).group(1)
    assert printed == f"urd calibrate offset {root.resolve()} --stage sim --camera virtual --sim-offset 0"
    out = invoke("capture", root, *SIM, "--sim-size", "96x64", "--sim-offset", "3")
    assert out.exit_code == 0, out.output
    assert re.search(r"^mounting offset: 3\.\d{3} ± \d\.\d{3} deg from .*calibration\.json .*--sim-offset 3\); the stage's "
                     r"sense of rotation is not checked \(urd calibrate offset --check-direction\)$", out.stdout, re.M)
    scene = Dataset.open(root).scene("scene_01")
    for shot in scene.load()["shots"]:
        truth = shot_truth(scene.path / shot["file"])
        assert abs((truth["true_angle_deg"] - shot["angle_commanded_deg"] + 90) % 180 - 90) <= 0.3    # the offset is applied


@pytest.mark.parametrize("command", [("capture",), ("calibrate", "offset")])
def test_an_unusable_camera_is_reported_with_the_virtual_one_before_anything_is_created(tmp_path, command):
    env = {**os.environ, "PATH": os.path.dirname(sys.executable), "COLUMNS": "200"}    # no gphoto2 there
    out = subprocess.run([sys.executable, "-m", "urd.cli", *command, str(tmp_path / "ds"), "--stage", "sim"],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 1 and "gphoto2" in out.stderr and "--camera virtual" in out.stderr
    assert not (tmp_path / "ds").exists()


def test_an_interrupted_calibration_sweep_says_what_it_kept_and_is_never_fitted(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    stop_capture_before_shot(monkeypatch, 2)
    out = invoke("calibrate", "offset", root, *SIM, "--step", "30")
    monkeypatch.undo()
    assert out.exit_code == 130, out.output
    message = " ".join(out.stderr.split())
    assert "calibration sweep interrupted; its 2 shots are kept in" in message and "sweep_01" in message
    assert "run 'urd calibrate offset' again for a new sweep" in message
    assert not (root / "calibration.json").exists()
    out = invoke("calibrate", "offset", root, *SIM, "--step", "30")
    assert out.exit_code == 0, out.output
    assert json.loads((root / "calibration.json").read_text())["sweep"] == "calibration/sweep_02"


@pytest.mark.parametrize("existing", [False, True])
def test_a_sweep_that_took_no_shot_leaves_no_dataset_behind(tmp_path, existing):
    """A calibration sweep that fails before its first shot (the stage times out) into a folder
    that was no dataset leaves no manifest, lock or empty sweep folder there; the user's own files
    stay, and so does a folder the user made."""
    root = tmp_path / "cal"
    if existing:
        root.mkdir()
        (root / "notes.txt").write_text("polarizer target, lamp at 30 cm")
    from acquire.rig import SimSettings
    from urd.calibration import sweep_and_calibrate
    from urd.core.errors import UrdError

    with pytest.raises(UrdError, match="no shot was taken, nothing was kept"):
        sweep_and_calibrate(root, "sim", "virtual", 30.0, 0.0, sim=SimSettings(faults={"mech_timeout": 1.0}, width=64, height=48))
    if existing:
        assert sorted(p.name for p in root.iterdir()) == ["notes.txt"]
    else:
        assert not root.exists()
