"""Capture on the simulated rig: end to end, resume after faults, bad input."""

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest
import rawpy
import serial

from acquire.ell14 import Ell14
from acquire.plan import Step, new_capture_scene, plan_capture, run_capture
from acquire.sim_ell14 import FAULTS, SimulatedEll14
from acquire.virtual_camera import VirtualCamera, make_glass_scene, shot_truth
from conftest import mounted_tmpfs
from urd.core.dataset import Dataset
from urd.core.errors import UrdError

ROOT = Path(__file__).resolve().parent.parent


def urd(*args, cwd=None, preexec=None):
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env, cwd=cwd, preexec_fn=preexec)


def test_plan_lists_small_steps_and_skips_done_shots():
    steps = plan_capture([0, 45, 90], done={1})
    assert steps[0] == Step("home") and steps[-1] == Step("finish")
    assert [s.kind for s in steps[1:6]] == ["move", "verify", "trigger", "store", "record"]
    assert sorted({s.index for s in steps if s.index is not None}) == [0, 2]


@pytest.mark.parametrize("angles,count", [("0,45,90", 3), ("0,45,90,135", 4)])
def test_cli_capture_on_the_simulated_rig(tmp_path, angles, count):
    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--angles", angles,
              "--sim-size", "96x64", "--sim-offset", "2.0")
    assert out.returncode == 0, out.stderr
    scene = Dataset.open(tmp_path / "ds").scene("scene_01")
    record = scene.load(verify=True)
    assert record["capture"]["complete"] is True
    files = sorted((scene.path / "raw").glob("*.dng"))
    assert len(files) == count == len(record["shots"])
    for shot, path in zip(record["shots"], files):
        with rawpy.imread(str(path)) as raw:
            assert raw.raw_image.shape == (64, 96)
        assert path.stat().st_mode & 0o777 == 0o644                 # like every other output
        truth = shot_truth(path)
        assert truth["shot"] == shot["index"]
        assert truth["true_angle_deg"] == pytest.approx(shot["angle_commanded_deg"] + 2.0, abs=0.01)
    assert (scene.path / "truth" / "T_obs.tiff").is_file()


def capture_until_complete(ds, name, sim, angles, attempts=40, retries=2):
    """Run (and resume) one capture until it completes; return the error messages seen. A
    vanished device answers no retry, so ``retries=0`` guards the same with a third of the waits."""
    scene = new_capture_scene(ds, angles, name=name)
    cam = VirtualCamera(make_glass_scene(64, 48), sim.true_angle_deg, shake_px=0, seed=1)
    errors = []
    for _ in range(attempts):
        sim.sim_revive()
        with serial.Serial(sim.port_name, 9600, timeout=0.05) as port:
            stage = Ell14(port, timeout_s=0.15, move_timeout_s=0.4, retries=retries)
            try:
                return scene, run_capture(scene, stage, cam, angles).load(), errors
            except UrdError as exc:
                errors.append(str(exc))
    raise AssertionError(f"capture never completed: {errors[-3:]}")


@pytest.mark.slow
@pytest.mark.parametrize("kind", FAULTS)
def test_fault_injection_never_loses_duplicates_or_mislabels_shots(tmp_path, kind):
    angles = [0.0, 45.0, 90.0, 135.0]
    ds = Dataset.open_or_create(tmp_path / kind)
    prob = {"vanish": 0.05, "mech_timeout": 0.15}.get(kind, 0.25)
    faults = 8 if kind == "vanish" else 20             # a vanished device waits out its time-outs: ~1 s a fault
    with SimulatedEll14(sim_faults={kind: prob}, seed=3) as sim:
        captures = 0
        while sum(e["fault"] == kind for e in sim.log) < faults:
            captures += 1
            scene, record, errors = capture_until_complete(ds, f"scene_{captures:02d}", sim, angles,
                                                           retries=0 if kind == "vanish" else 2)
            assert all(("ELL14" in e or "stage reads" in e) for e in errors), errors
            record = scene.load(verify=True)       # every file present, hashes intact
            assert [s["index"] for s in record["shots"]] == [0, 1, 2, 3]
            dngs = sorted((scene.path / "raw").glob("*.dng"))
            assert len(dngs) == 4
            moves = [e for e in sim.log if e["command"][1:3] == "ma" and (e["reply"] or "").startswith("PO")]
            for shot in record["shots"]:
                truth = shot_truth(scene.path / shot["file"])
                assert truth["shot"] == shot["index"]
                assert truth["true_angle_deg"] == pytest.approx(shot["angle_commanded_deg"], abs=0.01)
                assert any(abs(m["true_angle_deg"] - truth["true_angle_deg"]) < 1e-9 for m in moves)
        assert sum(e["fault"] == kind for e in sim.log) >= faults


@pytest.mark.slow
def test_cli_reports_a_device_fault_and_resumes(tmp_path):
    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "64x48",
              "--sim-faults", "mech_timeout=1.0")
    assert out.returncode == 1 and "status 2: mechanical time-out" in out.stderr
    assert "no scene was kept" in out.stderr                     # the fault came before the first shot
    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "64x48")
    assert out.returncode == 0, out.stderr
    assert Dataset.open(tmp_path / "ds").scene("scene_01").load()["capture"]["complete"]


def test_interrupted_capture_resumes_without_retaking_done_shots(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    with SimulatedEll14() as sim:
        scene = new_capture_scene(ds, [0, 45, 90])
        cam = VirtualCamera(make_glass_scene(64, 48), sim.true_angle_deg, seed=2)
        with serial.Serial(sim.port_name, 9600, timeout=0.05) as port:
            stage = Ell14(port, timeout_s=0.15, move_timeout_s=0.4, retries=0)
            sim.sim_faults = {}
            calls = []

            def progress(step):
                calls.append(step)
                if step.kind == "record" and step.index == 1:
                    sim.sim_force("vanish")

            with pytest.raises(UrdError):
                run_capture(scene, stage, cam, [0, 45, 90], progress=progress)
            first = scene.load()
            assert [s["index"] for s in first["shots"]] == [0, 1] and not first["capture"]["complete"]
            sim.sim_revive()
            record = run_capture(scene, stage, cam, [0, 45, 90]).load()
        assert [s["sha256"] for s in record["shots"][:2]] == [s["sha256"] for s in first["shots"]]
        assert len(cam.triggers) == 3 and record["capture"]["complete"]


@pytest.mark.slow
def test_bad_inputs_fail_clearly(tmp_path, scripted_peer):
    out = urd("capture", tmp_path / "ds", "--stage", "/dev/ttyNOPE9", "--camera", "virtual")
    assert out.returncode == 1 and "cannot open serial port /dev/ttyNOPE9" in out.stderr
    silent = scripted_peer([])
    out = urd("capture", tmp_path / "ds", "--stage", silent.port_name)
    assert out.returncode == 1 and "did not answer" in out.stderr
    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "polaroid")
    assert out.returncode == 2 and "expected one of gphoto2, virtual, got 'polaroid'" in out.stderr
    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--angles", "0,180,90")
    assert out.returncode == 2 and "each polarizer direction once" in out.stderr
    with SimulatedEll14(sim_device_type=0x06) as sim, serial.Serial(sim.port_name, 9600, timeout=0.05) as port:
        with pytest.raises(UrdError, match="not an ELL14"):
            Ell14(port).info()


def test_full_disk_leaves_no_shot_that_looks_complete(tmp_path):
    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))

    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "256x192", preexec=limit)
    assert out.returncode == 1 and "cannot write shot 0" in out.stderr and "disk full" in out.stderr
    assert not (tmp_path / "ds" / "scene_01").exists()    # no half-written shot, no empty scene


def test_read_only_dataset_folder(tmp_path):
    with mounted_tmpfs(tmp_path / "ro", "ro,size=1m", "a read-only tmpfs") as ro:
        out = urd("capture", ro / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "64x48")
        assert out.returncode == 1 and "cannot create dataset folder" in out.stderr


def test_the_virtual_cameras_polarizer_turns_with_the_camera():
    """A shot turned by the shake sees the scene through the polarizer at its angle in the
    camera's frame less the turn (the polarizer sits in front of the lens)."""
    import cv2
    import numpy as np

    cam = VirtualCamera(make_glass_scene(128, 96, curved=False, phi_perp_deg=90.0), lambda: 0.0, shake_px=0, shake_deg=5.0, seed=4)
    turn = -cam.shake(1)[1, 0]                                # sin of the turn: the scene turns counter-clockwise by it
    turn_deg = float(np.degrees(np.arcsin(turn)))
    assert abs(turn_deg) > 0.5 and cam.scene_angle_deg(30.0, 1) == pytest.approx(30.0 - turn_deg, abs=1e-4)
    shot = cam.render(30.0, 1)

    def warped(angle_deg):
        return cv2.warpAffine((cam.scene.render(np.radians(angle_deg)) * cam.gain).astype(np.float32), cam.shake(1),
                              (128, 96), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    assert np.abs(shot - warped(30.0 - turn_deg)).max() < 1e-6
    assert np.abs(shot - warped(30.0)).max() > 1e-3                 # a polarizer fixed to the scene would see this
