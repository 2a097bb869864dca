"""Data safety (issue: DATA-SAFETY 1-6): re-runs interrupted or killed at every step of the
staged swap, recovery of what killed runs left, full hashing in verify, the virtual camera's
ground truth, hostile manifests and model cards, and what ``ingest --redo`` supersedes."""

import functools
import io
import itertools
import json
import os
import shutil
import subprocess
import sys

import pytest
import tifffile

from rig import capture_virtual
from separate.methods import get_method
from urd.core.dataset import Dataset, Scene
from urd.core.errors import DatasetError, ManifestError, WeightsError
from urd.core.files import write_json_atomic
from urd.ingest import IngestOptions, ingest, ingest_scene
from urd.report import report_text, verify
from urd.separation import separate_scene

SCENE = "scene_01"


class Killed(BaseException):
    """A simulated SIGKILL: the dataset was copied as it stood at that step; nothing the
    interrupted process does afterwards counts."""


def ingested_dataset(root, seed=1):
    """A dataset with one ingested virtual-camera scene and results of the method 'none';
    returns (scene, camera)."""
    ds = Dataset.open_or_create(root)
    scene, cam = capture_virtual(ds, size=(192, 128), shake_px=2, shake_deg=0.2, seed=seed)
    assert ingest_scene(scene, IngestOptions()).error is None
    run, info = get_method("none")
    separate_scene(scene, "none", run, info)
    return scene, cam


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    root = tmp_path_factory.mktemp("base") / "ds"
    ingested_dataset(root)
    return root


def redo(root):
    """``urd ingest SCENE --redo --motion translation``: another alignment than the first."""
    from urd.core.align import Motion

    report = ingest(root / SCENE, root, IngestOptions(redo=True, motion=Motion.TRANSLATION))
    assert [o.state for o in report.outcomes] == ["ingested"], report.outcomes


def force(root):
    """``urd separate SCENE --method none --force``."""
    run, info = get_method("none")
    separate_scene(Dataset.open(root).scene(SCENE), "none", run, info, force=True)


OPERATIONS = {"ingest --redo": redo, "separate --force": force}


def on_step(monkeypatch, k, action):
    """Call ``action`` before the k-th (from 0) file replace or rename of this process: each
    file put in place and each manifest save goes through one of them."""
    counter = itertools.count()
    for name in ("replace", "rename"):
        real = getattr(os, name)

        def step(*args, _real=real, **kwargs):
            if next(counter) == k:
                action()
            return _real(*args, **kwargs)

        monkeypatch.setattr(os, name, step)
    return counter


def snapshot(root, to):
    """Copy the dataset at ``root`` as it stands (files another thread renames meanwhile are
    left out, as a kill would find them gone)."""
    def copy_present(src, dst):
        try:
            shutil.copy2(src, dst)
        except FileNotFoundError:
            pass

    shutil.copytree(root, to, symlinks=True, copy_function=copy_present)


def kill(work, killed):
    """Copy ``work`` to ``killed`` as it stands and stop: what a SIGKILL leaves."""
    snapshot(work, killed)
    raise Killed


def count_steps(monkeypatch, root, operation):
    counter = on_step(monkeypatch, -1, lambda: None)
    operation(root)
    monkeypatch.undo()
    return next(counter)


def named_files(root):
    record = Scene(root / SCENE).load(verify=False)
    files = [s["file"] for s in record["shots"]] + [f["file"] for f in record.get("ingest", {}).get("aligned", [])]
    return files + [f["file"] for r in record.get("results", {}).values() for f in r["files"]]


def assert_intact(root):
    """`urd verify` passes: every named file exists and hashes right."""
    assert verify(root) == {SCENE: []}


def assert_clean(root):
    """Intact, every named file under its final name, no staging folder left."""
    assert_intact(root)
    assert not [name for name in named_files(root) if name.startswith(".staging-")]
    assert not list((root / SCENE).glob(".staging-*"))


# 1, 2. interrupt or kill at every step of the swap: the dataset stays consistent, the next run completes

@pytest.mark.slow
@pytest.mark.parametrize("operation", OPERATIONS)
def test_an_interrupt_at_any_step_of_a_rerun_leaves_a_consistent_dataset(tmp_path, monkeypatch, base, operation):
    run = OPERATIONS[operation]
    steps = count_steps(monkeypatch, shutil.copytree(base, tmp_path / "count"), run)
    assert steps >= 4
    for k in range(steps):
        work = shutil.copytree(base, tmp_path / f"step{k}")

        def interrupt():
            raise KeyboardInterrupt

        on_step(monkeypatch, k, interrupt)
        with pytest.raises(KeyboardInterrupt):
            run(work)
        monkeypatch.undo()
        assert_intact(work)
        run(work)
        assert_clean(work)


@pytest.mark.slow
@pytest.mark.parametrize("operation", OPERATIONS)
def test_a_kill_at_any_step_of_a_rerun_leaves_a_consistent_dataset_the_next_run_completes(tmp_path, monkeypatch, base,
                                                                                          operation):
    run = OPERATIONS[operation]
    steps = count_steps(monkeypatch, shutil.copytree(base, tmp_path / "count"), run)
    assert steps >= 2                                        # the file steps are seen: the kills below happen
    for k in range(steps):
        work, killed = shutil.copytree(base, tmp_path / f"work{k}"), tmp_path / f"killed{k}"

        on_step(monkeypatch, k, functools.partial(kill, work, killed))
        with pytest.raises(Killed):
            run(work)
        monkeypatch.undo()
        assert_intact(killed)
        run(killed)
        assert_clean(killed)


@pytest.mark.slow
def test_remove_stale_keeps_the_staged_files_a_killed_swap_left_named(tmp_path, monkeypatch, base):
    steps = count_steps(monkeypatch, shutil.copytree(base, tmp_path / "count"), force)
    assert steps >= 2
    pending = 0
    for k in range(steps):
        work, killed = shutil.copytree(base, tmp_path / f"work{k}"), tmp_path / f"killed{k}"

        on_step(monkeypatch, k, functools.partial(kill, work, killed))
        with pytest.raises(Killed):
            force(work)
        monkeypatch.undo()
        if any(name.startswith(".staging-") for name in named_files(killed)):
            pending += 1
            Scene(killed / SCENE).remove_stale()             # what a resumed capture calls first
            assert_intact(killed)
    assert pending                                          # some kill left a swap committed, not finished


def test_staging_folders_and_temporary_files_a_kill_left_go_on_the_next_lock(tmp_path, base):
    root = shutil.copytree(base, tmp_path / "ds")
    scene = root / SCENE
    leftovers = [scene / ".staging-k1ll3d/results/none/R.tiff", scene / ".staging-abc/shot_00.tiff",
                 root / ".staging-xyz/scene.json", scene / ".scene.a1b2c3d4.tmp.json",
                 scene / "results" / "none" / ".R.tiff.4242.link"]
    for path in leftovers:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"left by a killed run")
    with Dataset.open(root).lock():
        pass
    assert not [p for p in leftovers if p.exists()]
    assert not list(scene.glob(".staging-*")) and not list(root.glob(".staging-*"))
    assert_intact(root)


def test_a_refused_swap_changes_nothing_and_says_what_to_do(tmp_path, base):
    root = shutil.copytree(base, tmp_path / "ds")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (root / SCENE / "results" / "schechner").symlink_to(outside, target_is_directory=True)
    run, info = get_method("none")
    before = Scene(root / SCENE).load()
    with pytest.raises(DatasetError, match=r"results/schechner is a symbolic link.*Nothing was changed.*replace it"):
        separate_scene(Dataset.open(root).scene(SCENE), "schechner", run, info)
    assert Scene(root / SCENE).load() == before and not list(outside.iterdir())
    (root / SCENE / "results" / "schechner").unlink()
    assert_clean(root)
    separate_scene(Dataset.open(root).scene(SCENE), "schechner", run, info)
    assert_clean(root)


# 3. verify hashes in full; the hash cache is neither trusted by verify nor fooled by kept times

def flip_keeping_size_and_mtime(path):
    stat = path.stat()
    with open(path, "r+b") as fh:
        fh.seek(-100, os.SEEK_END)
        byte = fh.read(1)
        fh.seek(-100, os.SEEK_END)
        fh.write(bytes([byte[0] ^ 0xFF]))
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns


def test_verify_and_separate_catch_bytes_flipped_with_size_and_mtime_kept(tmp_path, base):
    root = shutil.copytree(base, tmp_path / "ds")
    scene = Dataset.open(root).scene(SCENE)
    assert_intact(root)                                    # fills the hash cache
    shot = root / SCENE / "aligned" / "shot_01.tiff"
    flip_keeping_size_and_mtime(shot)
    assert any("shot_01.tiff" in p for p in verify(root)[SCENE])
    run, info = get_method("none")
    with pytest.raises(ManifestError, match="shot_01.tiff: SHA-256 or size does not match"):
        separate_scene(scene, "none", run, info, force=True)
    cache = root / SCENE / ".urd-hashes.json"                # a cache claiming the file is intact
    stat = shot.stat()
    digest = next(f["sha256"] for f in scene.load(verify=False)["ingest"]["aligned"] if f["file"].endswith("shot_01.tiff"))
    forged = {"aligned/shot_01.tiff": [stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino, digest]}
    write_json_atomic(cache, forged)
    assert any("shot_01.tiff" in p for p in verify(root)[SCENE])


# 4. the virtual camera's ground truth: complete or absent, hashed, written again

def kill_in_truth(monkeypatch, root, nth):
    """Write the ``nth`` truth image half, copy the dataset as it stands, stop (a kill)."""
    real = tifffile.imwrite
    counter = itertools.count()
    killed = root.parent / "killed"

    def imwrite(path, data, **kwargs):
        if next(counter) == nth:
            buffer = io.BytesIO()
            real(buffer, data, **kwargs)
            with open(path, "wb") as fh:
                fh.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
            snapshot(root, killed)
            raise Killed
        return real(path, data, **kwargs)

    monkeypatch.setattr(tifffile, "imwrite", imwrite)
    return killed


@pytest.mark.parametrize("nth", [0, 1, 3])
def test_a_kill_while_writing_ground_truth_stops_no_separation_and_the_truth_is_written_again(tmp_path, monkeypatch, nth):
    scene, cam = ingested_dataset(tmp_path / "ds")
    shutil.rmtree(scene.truth_dir())
    killed = kill_in_truth(monkeypatch, scene.path.parent, nth)
    with pytest.raises(Killed):
        cam.write_truth(scene.truth_dir())
    monkeypatch.undo()
    force(killed)                                          # separation goes on without the truth
    problems = verify(killed)[SCENE]                       # and verify names the lost truth, nothing else
    assert len(problems) == 1 and "no ground truth: a capture was stopped while writing it" in problems[0]
    again = Dataset.open(killed).scene(SCENE)
    assert not again.truth_dir().exists()                  # so resuming the capture writes it again
    cam.write_truth(again.truth_dir())
    run, info = get_method("none")
    assert separate_scene(again, "none", run, info, force=True).truth_metrics is not None
    assert_clean(killed)


def test_ground_truth_is_hashed_and_checked(tmp_path):
    scene, _ = ingested_dataset(tmp_path / "ds")
    flip_keeping_size_and_mtime(scene.truth_dir() / "T_obs.tiff")
    assert any("T_obs.tiff" in p for p in verify(scene.path.parent)[SCENE])
    run, info = get_method("none")
    with pytest.raises(ManifestError, match="T_obs.tiff: SHA-256 or size does not match .*the ground truth feeds only "
                                            "the figures against it: move .*truth away to separate without them"):
        separate_scene(scene, "none", run, info, force=True)
    (scene.truth_dir() / "T_obs.tiff").unlink()
    with pytest.raises(ManifestError, match="T_obs.tiff: listed in the manifest but missing; the ground truth feeds only"):
        separate_scene(scene, "none", run, info, force=True)


def test_unreadable_ground_truth_of_an_older_urd_is_named(tmp_path):
    scene, _ = ingested_dataset(tmp_path / "ds")
    truth = scene.truth_dir()
    (truth / "truth.json").write_text(json.dumps({"gain": 1.0}))          # as older urd wrote it: no hashes
    (truth / "R_obs.tiff").write_bytes((truth / "R_obs.tiff").read_bytes()[:300])
    run, info = get_method("none")
    with pytest.raises(DatasetError, match=r"R_obs.tiff cannot be read.*move .*truth away"):
        separate_scene(scene, "none", run, info, force=True)


# 5. hostile manifests and model cards

def test_a_deeply_nested_manifest_is_a_broken_scene_not_a_crash(tmp_path, base):
    root = shutil.copytree(base, tmp_path / "ds")
    good = Dataset.open(root).new_scene("test", {})
    manifest = root / SCENE / "scene.json"
    manifest.write_text("[" * 100_000 + "]" * 100_000)
    assert "nested" in verify(root)[SCENE][0] and verify(root)[good.name] == []
    assert f"{SCENE}: BROKEN" in report_text(root)
    with Dataset.open(root).lock():
        pass
    out = subprocess.run([sys.executable, "-m", "urd.cli", "verify", str(root)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 1 and "Traceback" not in out.stderr and "scene.json: nested" in out.stderr
    record = {"schema": "urd.scene", "deep": json.loads("[" * 500 + "]" * 500)}
    manifest.write_text(json.dumps(record))
    with pytest.raises(ManifestError, match="nested more than"):
        Scene(root / SCENE).load()


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf"), 1e308])
@pytest.mark.parametrize("field", ["angle_commanded_deg", "angle_measured_deg", "capture.angles_deg"])
def test_non_finite_and_absurd_angles_are_refused(tmp_path, base, field, value):
    root = shutil.copytree(base, tmp_path / "ds")
    scene = Scene(root / SCENE)
    record = scene.load(verify=False)
    if field == "capture.angles_deg":
        record["capture"]["angles_deg"][1] = value
    else:
        record["shots"][0][field] = value
    scene.manifest_path.write_text(json.dumps(record))
    with pytest.raises(ManifestError, match=field.split(".")[-1]):
        scene.reload().load()


def test_a_negative_shot_index_is_refused(tmp_path, base):
    root = shutil.copytree(base, tmp_path / "ds")
    scene = Scene(root / SCENE)
    record = scene.load(verify=False)
    record["shots"][0]["index"] = -1
    write_json_atomic(scene.manifest_path, record)
    with pytest.raises(ManifestError, match=r"shots\[0\]: field 'index' is -1"):
        scene.reload().load()


@pytest.mark.parametrize("card", ["{not json", "[1, 2]", "[" * 100_000])
def test_a_malformed_model_card_is_named(tmp_path, card):
    from separate.infer import WEIGHTS_DIR, load_model

    weights = tmp_path / "mine.pt"
    shutil.copyfile(WEIGHTS_DIR / "ceilnet.pt", weights)
    (tmp_path / "mine.json").write_text(card)
    with pytest.raises(WeightsError, match=r"model card .*mine.json .*move it away"):
        load_model(weights)


# 6. ingest --redo supersedes what was computed from the old alignment, and only on success

def test_a_redo_whose_alignment_fails_keeps_the_aligned_shots_results_and_calibration(tmp_path, base, monkeypatch):
    import dataclasses

    import urd.ingest

    root = shutil.copytree(base, tmp_path / "ds")
    scene = Dataset.open(root).scene(SCENE)
    calibrated = [a + e for a, e in zip(scene.uncalibrated_angles_deg(), (0.4, -0.3, 0.2))]
    scene.set_shot_calibration({"errors_deg": [0.4, -0.3, 0.2], "uncertainty_deg": [0.05] * 3}, calibrated)
    before = {p.name: p.read_bytes() for p in (root / SCENE / "aligned").iterdir()}
    manifest = json.loads(scene.manifest_path.read_text())
    real_align = urd.ingest.align
    monkeypatch.setattr(urd.ingest, "align", lambda *args: dataclasses.replace(real_align(*args), ok=False,
                                                                               reason="ECC correlation 0.2 below 0.6"))
    report = ingest(root / SCENE, root, IngestOptions(redo=True))
    [outcome] = report.outcomes
    assert outcome.state == "failed" and "ECC correlation 0.2" in outcome.error
    assert "the earlier aligned shots and results are kept" in outcome.error
    scene = Dataset.open(root).scene(SCENE)
    assert {p.name: p.read_bytes() for p in (root / SCENE / "aligned").iterdir()} == before
    after = json.loads(scene.manifest_path.read_text())
    failed = after["provenance"].pop()
    assert after == manifest and scene.status().calibrated                 # the attempt is all that was added
    assert failed["step"] == "ingest failed, the earlier alignment kept" and "ECC correlation 0.2" in failed["parameters"]["error"]
    assert_clean(root)


def test_ingest_redo_marks_results_stale_and_removes_the_shot_calibration(tmp_path, base):
    root = shutil.copytree(base, tmp_path / "ds")
    scene = Dataset.open(root).scene(SCENE)
    calibrated = [a + e for a, e in zip(scene.uncalibrated_angles_deg(), (0.4, -0.3, 0.2))]
    scene.set_shot_calibration({"errors_deg": [0.4, -0.3, 0.2], "uncertainty_deg": [0.05] * 3}, calibrated)
    assert scene.status().calibrated
    redo(root)
    assert "STALE" in report_text(root) and "nominal angles" in report_text(root)
    scene.reload()
    status = scene.status()
    assert status.stale == ("none",) and not status.calibrated
    assert any(w.startswith("STALE") and "--force" in w for w in scene.result("none").warnings)
    assert [s.angle_calibrated_deg for s in scene.shots()] == [None] * 3
    from urd.batch import targets

    assert targets(Dataset.open(root), "none", force=False)[1][0].detail == \
        "has STALE none results: computed from an earlier alignment (the scene was ingested again); --force replaces them"
    with pytest.raises(DatasetError, match=r"already has STALE none results \(computed from an earlier alignment \(the "
                                           r"scene was ingested again\)\) .*pass --force"):
        scene.check_no_results("none")
    superseded = [p for p in scene.provenance() if p["step"] == "supersede"]
    assert superseded and superseded[-1]["parameters"]["calibration"]["errors_deg"] == [0.4, -0.3, 0.2]
    assert_clean(root)
    force(root)
    assert Dataset.open(root).scene(SCENE).status().stale == ()
