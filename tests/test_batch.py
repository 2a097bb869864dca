"""Whole datasets at once: ``urd separate --all [--jobs N]``, and a kill in the middle of it."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rig import capture_virtual
from urd.core.align import Motion
from urd.core.dataset import Dataset
from urd.ingest import IngestOptions, ingest_scene


def urd(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", "urd.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=900, **kwargs)


@pytest.fixture(scope="module")
def ingested_three_scenes(tmp_path_factory):
    """Three captured and ingested scenes, made once for the module; tests change copies of it."""
    ds = Dataset.open_or_create(tmp_path_factory.mktemp("batch") / "ds")
    for seed in range(3):
        scene, _ = capture_virtual(ds, size=(192, 128), shake_px=1.0, shake_deg=0.1, seed=seed)
        ingest_scene(scene, IngestOptions())
    return ds.root


@pytest.fixture
def three_scenes(ingested_three_scenes, tmp_path):
    """A fresh copy of the three ingested scenes."""
    return Path(shutil.copytree(ingested_three_scenes, tmp_path / "ds", symlinks=True))


def methods_of(root):
    return {name: sorted(json.loads((root / name / "scene.json").read_text()).get("results", {}))
            for name in sorted(p.name for p in root.iterdir() if (p / "scene.json").is_file())}


@pytest.mark.slow
def test_separate_all_with_two_jobs_separates_every_scene_and_skips_done_ones(three_scenes):
    out = urd("separate", "--all", "--jobs", "2", "--method", "schechner", "--dataset", three_scenes)
    assert out.returncode == 0, out.stderr
    assert methods_of(three_scenes) == {f"scene_0{i}": ["schechner"] for i in (1, 2, 3)}
    assert "3 scenes separated with schechner, 0 failed" in out.stdout
    again = urd("separate", "--all", "--method", "schechner", "--dataset", three_scenes)
    assert again.returncode == 0 and again.stdout.count("skipped: has schechner results") == 3
    assert urd("verify", three_scenes).returncode == 0
    refused = urd("separate", "scene_01", "--all", "--dataset", three_scenes)
    assert refused.returncode == 2 and "--all alone" in refused.stderr


@pytest.mark.slow
def test_classical_methods_separate_without_importing_torch(three_scenes):
    """torch costs ~2 s per process; `urd separate` imports it for the networks only."""
    script = ("import sys\nfrom urd.cli import app\n"
              f"try:\n    app(['separate', '--all', '--method', 'schechner', '--dataset', {str(three_scenes)!r}])\n"
              "except SystemExit as exc:\n    assert exc.code in (0, None), exc.code\n"
              "print('torch imported:', 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "3 scenes separated with schechner" in out.stdout and "torch imported: False" in out.stdout


def test_one_failing_scene_is_reported_and_the_others_go_on(three_scenes):
    aligned = sorted((three_scenes / "scene_02" / "aligned").iterdir())[0]
    aligned.write_bytes(aligned.read_bytes()[:-10] + b"0123456789")         # same size, other bytes
    out = urd("separate", "--all", "--method", "none", "--dataset", three_scenes)
    assert out.returncode == 1
    assert "scene_02: failed" in out.stdout and "SHA-256" in out.stdout
    assert methods_of(three_scenes)["scene_01"] == ["none"] and methods_of(three_scenes)["scene_03"] == ["none"]


@pytest.mark.slow
def test_a_kill_during_separate_all_leaves_finished_scenes_intact(three_scenes):
    proc = subprocess.Popen([sys.executable, "-m", "urd.cli", "separate", "--all", "--method", "network", "--dataset",
                             str(three_scenes)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 600
    while time.time() < deadline and not any(methods_of(three_scenes).values()):
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = [name for name, methods in methods_of(three_scenes).items() if methods]
    assert 1 <= len(finished) <= 3
    verify = urd("verify", three_scenes)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    out = urd("separate", "--all", "--method", "network", "--dataset", three_scenes)
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("skipped: has network results") == len(finished)
    assert all(methods == ["network"] for methods in methods_of(three_scenes).values())
    assert not list(three_scenes.glob("*/.staging-*"))


@pytest.mark.slow
def test_ingest_a_dataset_with_two_jobs(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    for seed in range(3):
        capture_virtual(ds, size=(192, 128), shake_px=1.0, shake_deg=0.1, seed=seed)
    out = urd("ingest", ds.root, "--jobs", "2")
    assert out.returncode == 0, out.stderr
    assert [line.split(" (")[0] for line in out.stdout.splitlines()] == [f"ingested scene_0{i}" for i in (1, 2, 3)]
    assert all(Dataset.open(ds.root).scene(f"scene_0{i}").is_ingested() for i in (1, 2, 3))
    assert urd("verify", ds.root).returncode == 0
    again = urd("ingest", ds.root, "--jobs", "2")
    assert again.returncode == 0 and again.stdout.count("already ingested") == 3
    assert not list(ds.root.glob("*/.staging-*"))


def test_ingest_jobs_is_for_a_dataset_not_a_raw_folder(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    out = urd("ingest", raw, tmp_path / "ds", "--jobs", "2")
    assert out.returncode == 2 and "--jobs is for a dataset or scene folder" in " ".join(out.stderr.split())
    assert not (tmp_path / "ds").exists()


def test_results_deleted_by_hand_fail_their_scene_and_stale_results_get_no_maps(three_scenes):
    """``--all`` does not take a scene whose result files are gone for one that is done, and
    ``--all --maps`` adds no maps to results of an earlier alignment (they would not match)."""
    from typer.testing import CliRunner

    from urd.cli import app

    def run(*args):
        return CliRunner().invoke(app, ["separate", "--all", "--dataset", str(three_scenes), "--method", "none", *args])

    assert run().exit_code == 0
    for name in ("R.tiff", "T_preview.png"):
        (three_scenes / "scene_02" / "results" / "none" / name).unlink()
    out = run()
    assert out.exit_code == 1, out.output
    assert "scene_02: failed: its none results lack R.tiff, T_preview.png: see urd verify" in out.output
    assert "scene_01: skipped" in out.output and "scene_03: skipped" in out.output
    scene = Dataset.open(three_scenes).scene("scene_01")
    assert ingest_scene(scene, IngestOptions(redo=True, motion=Motion.TRANSLATION)).error is None   # another alignment
    out = run("--maps")
    assert ("scene_01: skipped: has STALE none results: computed from an earlier alignment (the scene was ingested "
            "again); maps would not match them") in out.output
    assert not (three_scenes / "scene_01" / "results" / "none" / "maps").exists()
    assert (three_scenes / "scene_03" / "results" / "none" / "maps").is_dir()


def test_separate_all_of_a_dataset_without_scenes_says_so_and_fails(tmp_path):
    from typer.testing import CliRunner

    from urd.cli import app

    Dataset.open_or_create(tmp_path / "ds")
    out = CliRunner().invoke(app, ["separate", "--all", "--dataset", str(tmp_path / "ds"), "--method", "none"])
    assert out.exit_code == 1 and "holds no scene yet" in out.output
