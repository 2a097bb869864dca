"""The dataset core's guarantees, one test per failure found in the seams between commands
(issue: typed Scene API): staged re-runs, no empty scenes, incomplete captures, idempotent
ingest, integrity and confinement, validation, locking, unreadable files."""

import json
import os
import shutil
import subprocess
import sys
import time

import pytest
import tifffile

from acquire.plan import capture_scene
from acquire.rig import SimSettings
from rig import capture_virtual
from separate.methods import get_method
from urd import ingest as ingest_mod
from urd.core.dataset import Dataset
from urd.core.errors import CaptureInterrupted, DatasetBusyError, DatasetError, ManifestError
from urd.core.files import write_json_atomic
from urd.ingest import IngestOptions, ingest_folder, ingest_scene
from urd.report import report_text, verify
from urd.separation import separate_scene


def urd(*args, cwd=None, env=None):
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd, env={**os.environ, "COLUMNS": "200", **(env or {})})


def named_files_exist(scene):
    record = scene.load(verify=False)
    files = [s["file"] for s in record["shots"]] + [f["file"] for f in record.get("ingest", {}).get("aligned", [])]
    files += [f["file"] for r in record.get("results", {}).values() for f in r["files"]]
    return all((scene.path / f).is_file() for f in files)


def ingested_scene(tmp_path, size=(192, 128), seed=1):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=size, shake_px=2, shake_deg=0.2, seed=seed)
    assert ingest_scene(scene, IngestOptions()).error is None
    return ds, scene


# 1. --redo and --force stage new outputs and swap them in only on success

def test_interrupted_redo_and_force_keep_the_old_outputs_named_and_present(tmp_path, monkeypatch):
    ds, scene = ingested_scene(tmp_path)
    before = scene.load()["ingest"]["aligned"]

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ingest_mod, "align", interrupt)
    with pytest.raises(KeyboardInterrupt):
        ingest_scene(scene, IngestOptions(redo=True))
    assert scene.load()["ingest"]["aligned"] == before and named_files_exist(scene)
    monkeypatch.undo()
    assert ingest_scene(scene, IngestOptions(redo=True)).error is None          # a re-run redoes it
    assert named_files_exist(scene) and not list(scene.path.glob(".staging-*"))

    run, info = get_method("none")
    separate_scene(scene, "none", run, info)
    old = scene.load()["results"]["none"]["files"]

    def broken(images, angles, reference_deg=None):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        separate_scene(scene, "none", broken, info, force=True)
    assert scene.load()["results"]["none"]["files"] == old and named_files_exist(scene)
    separate_scene(scene, "none", run, info, force=True)
    assert named_files_exist(scene)


# 2. a capture that fails before its first shot leaves no scene; a broken scene stops nothing

@pytest.mark.slow
def test_failed_start_leaves_no_scene_and_a_broken_scene_stops_no_command(tmp_path):
    out = urd("capture", tmp_path / "ds", "--stage", "/dev/ttyNOPE9", "--camera", "virtual")
    assert out.returncode == 1 and "cannot open serial port" in out.stderr
    out = urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "gphoto2", env={"PATH": "/nonexistent"})
    assert out.returncode == 1 and "gphoto2" in out.stderr
    assert not (tmp_path / "ds").exists()                   # the stage and the camera are checked before anything is made
    Dataset.open_or_create(tmp_path / "ds")
    (tmp_path / "ds" / "scene_01").mkdir()                  # an empty folder left by an older urd
    assert urd("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "96x64").returncode == 0
    out = urd("report", tmp_path / "ds")
    assert out.returncode == 0 and "scene_01: BROKEN" in out.stdout and "scene_02: 3 shots" in out.stdout
    out = urd("ingest", tmp_path / "ds")
    assert "ingested scene_02" in out.stdout and "scene_01" in out.stderr
    assert Dataset.open(tmp_path / "ds").scene("scene_02").status().state == "ingested"


# 3. an interrupted capture is incomplete, says how to resume, and a plain capture resumes it

def test_interrupted_capture_is_incomplete_and_resumes(tmp_path):
    sim = SimSettings(width=96, height=64, shake_px=0, shake_deg=0)

    def stop_after_first_shot(done, total, label):
        if done == 6:                                    # home + the five steps of shot 0
            raise KeyboardInterrupt

    with pytest.raises(CaptureInterrupted, match=r"Resume with: urd capture .* --stage sim --camera virtual "
                                                 r"--angles 0,45,90,135 --scene scene_01"):
        capture_scene(tmp_path / "ds", "sim", "virtual", [0, 45, 90, 135], sim=sim, progress=stop_after_first_shot)
    ds = Dataset.open(tmp_path / "ds")
    scene = ds.scene("scene_01")
    assert scene.status().state == "incomplete" and len(scene.shots()) == 1
    outcome = ingest_scene(scene, IngestOptions())
    assert outcome.state == "incomplete" and "--camera virtual --angles 0,45,90,135 --scene scene_01" in outcome.error
    assert "INCOMPLETE (1 of 4 shots" in report_text(tmp_path / "ds")
    stale = scene.path / "raw" / ".shot-leftover.dng"
    stale.write_bytes(b"half a shot")
    lines = []
    capture_scene(tmp_path / "ds", "sim", "virtual", [0, 45, 90, 135], sim=sim, announce=lines.append)
    assert any("resuming the incomplete capture" in line for line in lines)
    assert ds.scene_names() == ["scene_01"] and scene.reload().status().state == "captured"
    assert len(scene.shots()) == 4 and not stale.exists()


# 4. ingest is idempotent by content hash

def test_ingesting_the_same_raw_files_twice_makes_no_duplicate_scene(tmp_path):
    cap = Dataset.open_or_create(tmp_path / "cap")
    source, _ = capture_virtual(cap, size=(128, 96), shake_px=0, shake_deg=0, seed=2)
    raw_dir = tmp_path / "raw"
    shutil.copytree(source.path / "raw", raw_dir)
    ds = Dataset.open_or_create(tmp_path / "ds")
    first = ingest_folder(raw_dir, ds, IngestOptions())
    assert [o.state for o in first.outcomes] == ["ingested"]
    again = ingest_folder(raw_dir, ds, IngestOptions())
    assert [(o.state, o.name) for o in again.outcomes] == [("skipped", "scene_01")]
    own = ingest_folder(ds.root / "scene_01" / "raw", ds, IngestOptions())
    assert [o.state for o in own.outcomes] == ["skipped"] and ds.scene_names() == ["scene_01"]
    out = urd("ingest", raw_dir, ds.root)
    assert out.returncode == 0 and "already ingested as scene_01" in out.stdout


# 5. integrity: hashes checked before use, paths confined to the scene

@pytest.mark.slow
def test_tampered_files_are_refused_and_manifest_paths_stay_inside_the_scene(tmp_path):
    ds, scene = ingested_scene(tmp_path)
    aligned = scene.path / scene.load()["ingest"]["aligned"][1]["file"]
    data = tifffile.imread(aligned)
    data[5, 5] ^= 1
    tifffile.imwrite(aligned, data, photometric="rgb")
    out = urd("separate", "scene_01", "--dataset", ds.root, "--method", "none")
    assert out.returncode == 1 and "shot_01.tiff: SHA-256 or size does not match" in out.stderr
    problems = verify(ds.root)
    assert any("shot_01.tiff" in p for p in problems["scene_01"])
    out = urd("verify", ds.root)
    assert out.returncode == 1 and "shot_01.tiff" in out.stderr
    record = scene.load(verify=False)
    for bad in ("/etc/passwd", "../../outside.dng", "raw/../../x.dng"):
        record["shots"][0]["file"] = bad
        write_json_atomic(scene.manifest_path, record)
        with pytest.raises(ManifestError, match="leaves the scene folder") as info:
            scene.load()
        assert "root:" not in str(info.value)
    out = urd("report", ds.root)
    assert "BROKEN" in out.stdout and "root:" not in out.stdout + out.stderr


# 6. every nested field is validated on load, naming file and field

def test_nested_fields_and_schema_versions_are_validated(tmp_path):
    ds, scene = ingested_scene(tmp_path)
    good = scene.load()
    record = json.loads(json.dumps(good))
    del record["ingest"]["aligned"]
    write_json_atomic(scene.manifest_path, record)
    with pytest.raises(ManifestError, match=r"scene.json: ingest: missing field 'aligned'"):
        scene.load()
    for version, message in ((0, "expected 1 to 1"), (99, "newer urd")):
        record = {**good, "schema_version": version}
        write_json_atomic(scene.manifest_path, record)
        with pytest.raises(ManifestError, match=message):
            scene.load()
    write_json_atomic(scene.manifest_path, good)
    write_json_atomic(ds.calibration_path, {"schema": "urd.calibration", "schema_version": 1, "time": "t",
                                             "offset_deg": "abc", "uncertainty_deg": 0.1, "target_angle_deg": 0,
                                             "history": []})
    with pytest.raises(ManifestError, match=r"calibration.json: field 'offset_deg' has type str"):
        ds.calibration()
    out = urd("report", ds.root)                         # the scenes are still listed, the calibration said unreadable
    assert out.returncode == 0 and "polarizer offset unreadable (" in out.stdout and "offset_deg" in out.stdout
    assert "scene_01: 3 shots" in out.stdout and "Unknown format" not in out.stdout + out.stderr
    out = urd("verify", ds.root)
    assert out.returncode == 1 and "calibration: " in out.stderr and "offset_deg" in out.stderr


# 7. two writers: the second is told who holds the dataset

def test_a_second_writer_is_told_the_dataset_is_busy(tmp_path):
    ds, scene = ingested_scene(tmp_path)
    code = ("import sys, time; from urd.core.dataset import Dataset\n"
            "with Dataset(sys.argv[1]).lock():\n    print('locked', flush=True)\n    time.sleep(30)\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(ds.root)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(DatasetBusyError, match=rf"busy \(held by pid {holder.pid}\)"):
            with ds.lock():
                pass
        out = urd("separate", "scene_01", "--dataset", ds.root, "--method", "none")
        assert out.returncode == 1 and f"busy (held by pid {holder.pid})" in out.stderr
    finally:
        holder.kill()
        holder.wait()
    with ds.lock():
        with ds.lock():                                   # re-entrant in one process
            pass


# 8. unreadable files are named as such

def test_an_empty_or_non_raw_file_is_reported_as_unreadable(tmp_path):
    cap = Dataset.open_or_create(tmp_path / "cap")
    source, _ = capture_virtual(cap, size=(128, 96), shake_px=0, shake_deg=0, seed=3)
    raw_dir = tmp_path / "raw"
    shutil.copytree(source.path / "raw", raw_dir)
    shots = sorted(raw_dir.iterdir())
    shots[1].write_bytes(b"")
    shots[2].write_text("this is not a RAW file")
    t0 = time.time()                                  # the unreadable files' times: near the good shot's
    for i, path in enumerate(shots[1:], start=1):
        os.utime(path, (t0 + i, t0 + i))
    report = ingest_folder(raw_dir, Dataset.open_or_create(tmp_path / "ds"), IngestOptions())
    (failure,) = report.outcomes
    assert failure.state == "failed" and "wrong shot count" not in failure.error
    assert f"{shots[1].name} is unreadable (empty file)" in failure.error and shots[2].name in failure.error


def test_no_dataset_error_for_a_scene_without_manifest_names_the_problem(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    (ds.root / "scene_01").mkdir()
    with pytest.raises(DatasetError, match="has no scene.json"):
        ds.scene("scene_01")
    assert [s.status().state for s in ds.scenes()] == ["broken"]


def test_datasets_written_under_either_schema_name_open(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    record = json.loads(ds.manifest_path.read_text())
    assert record["schema"] == "urd.dataset"
    for name in ("urd.dataset", "urd.core.dataset"):          # the second: urd 0.1 wrote it for a while
        write_json_atomic(ds.manifest_path, {**record, "schema": name}, overwrite=True)
        assert Dataset.open(tmp_path / "ds").root == ds.root
    write_json_atomic(ds.manifest_path, {**record, "schema": "urd.scene"}, overwrite=True)
    with pytest.raises(ManifestError, match="field 'schema' is 'urd.scene', expected 'urd.dataset'"):
        Dataset.open(tmp_path / "ds")
