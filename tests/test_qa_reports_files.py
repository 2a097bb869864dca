"""QA of the report and file helpers: a full disk while writing an HTML report or a shot names
the file, staging folders a killed report left are removed, a lock file or manifest replaced by
a folder is reported as such, and an error line never continues a progress line."""

import errno
import fcntl
import os
import re
import sys
import time

import numpy as np
import pytest
import typer

import urd.core.files
import urd.report_html
from acquire.plan import new_capture_scene, run_capture
from urd.cli.common import run_guarded
from urd.core.dataset import Dataset
from urd.core.errors import DatasetError, DiskFullError, ManifestError
from urd.core.files import read_json
from urd.core.progress import TerminalProgress
from urd.report_html import SceneView, write_html_report


def _scenes() -> list[SceneView]:
    """One small scene of three shots (32×24 px, linear)."""
    shot = np.full((24, 32, 3), 0.25, np.float32)
    return [SceneView("scene_01", "ingested", [(0.0, shot), (45.0, shot), (90.0, shot)], None, None, [], [])]


def _no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_full_disk_while_writing_a_report_names_the_report_folder(tmp_path, monkeypatch):
    monkeypatch.setattr(urd.report_html, "write_image", _no_space)
    out = tmp_path / "report"
    with pytest.raises(DiskFullError, match=r"^disk full: .*report \(nothing was changed; free some space"):
        write_html_report(_scenes(), out, "t")
    assert list(tmp_path.iterdir()) == []                  # neither report nor staging folder


def test_a_report_removes_the_staging_folders_killed_runs_left(tmp_path):
    out = tmp_path / "report"
    stale, live = tmp_path / ".report.staging-k1ll3d00", tmp_path / ".report.staging-l1ve0000"
    others = [tmp_path / ".report.staging-x", tmp_path / ".other.staging-k1ll3d00", tmp_path / ".report.old-k1ll3d00"]
    for folder in [stale, live, *others]:
        (folder / "img").mkdir(parents=True)
        os.utime(folder, (time.time() - 60, time.time() - 60))
    held = os.open(live, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(held, fcntl.LOCK_EX)                   # a run still writing it
        write_html_report(_scenes(), out, "t")
    finally:
        os.close(held)
    assert (out / "index.html").is_file()
    assert not stale.exists() and live.exists() and all(folder.exists() for folder in others)


def test_full_disk_while_capturing_names_the_shot(tmp_path, monkeypatch):
    class Stage:
        def info(self):
            return {}

        def home(self):
            pass

        def move_to(self, angle_deg):
            return angle_deg

    class Camera:
        def capture(self, folder, index):
            raise OSError("1572864 requested and 466552 written")          # numpy's short write: no errno

    monkeypatch.setattr(urd.core.files, "MIN_FREE_BYTES", 1 << 62)      # every disk is full
    scene = new_capture_scene(Dataset.open_or_create(tmp_path / "ds"), [0, 45, 90])
    with pytest.raises(DiskFullError, match=r"^disk full: .*raw/shot_00_000\.0deg \(nothing was changed"):
        run_capture(scene, Stage(), Camera(), [0, 45, 90])


def test_a_lock_file_replaced_by_a_folder_is_named(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    (ds.root / ".urd.lock").mkdir()
    with pytest.raises(DatasetError, match=r"lock file .*\.urd\.lock is a folder, not a regular file; .*Remove it"):
        with ds.lock():
            pass


def test_a_manifest_replaced_by_a_folder_is_named(tmp_path):
    scene = new_capture_scene(Dataset.open_or_create(tmp_path / "ds"), [0, 45, 90])
    scene.manifest_path.unlink()
    scene.manifest_path.mkdir()
    with pytest.raises(ManifestError, match=r"scene\.json: is a folder, not a file .*from a backup"):
        read_json(scene.manifest_path)
    assert "is a folder, not a file" in scene.reload().status().problem


@pytest.mark.parametrize("raised, said", [(DatasetError("cannot write R.tiff"), "Error: cannot write R.tiff"),
                                          (KeyboardInterrupt(), "Error: interrupted; ")])
def test_an_error_starts_a_line_of_its_own_after_a_progress_line(capsys, raised, said):
    bar = TerminalProgress(sys.stderr)                     # handed to the work inside a callback, as separate does

    def work():
        bar(1, 1, "separate (network)")
        raise raised

    with pytest.raises(typer.Exit):
        run_guarded(work)
    assert re.search(r"1/1 0:00 done  \n" + re.escape(said), capsys.readouterr().err)


def test_an_error_without_a_progress_line_prints_no_blank_line(capsys):
    def work(progress):
        raise DatasetError("cannot write R.tiff")

    with pytest.raises(typer.Exit):
        run_guarded(work, progress=TerminalProgress(sys.stderr))
    assert capsys.readouterr().err.startswith("Error: cannot write R.tiff")
