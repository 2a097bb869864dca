"""A new user following the README: result files other programs read, and batch commands that say
when nothing was done or where the dataset is."""

import json
import re

import cv2
import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from conftest import stop_capture_before_shot
from urd.cli import app
from urd.separation import FULL_SCALE, write_float_map, write_linear_tiff

SIM = ("--stage", "sim", "--camera", "virtual", "--sim-size", "96x64")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_a_three_channel_map_is_one_rgb_page_that_opencv_reads_as_the_image(tmp_path):
    values = np.random.default_rng(0).random((20, 30, 3)).astype(np.float32)
    write_float_map(tmp_path / "S0.tiff", values, "Stokes S0", "linear")
    with tifffile.TiffFile(tmp_path / "S0.tiff") as tiff:
        assert len(tiff.pages) == 1 and tiff.pages[0].shape == (20, 30, 3)
        assert json.loads(tiff.pages[0].description)["unit"] == "linear"
    read = cv2.imread(str(tmp_path / "S0.tiff"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(read[..., ::-1], values)


def test_a_result_tiff_states_its_full_scale(tmp_path):
    write_linear_tiff(tmp_path / "T.tiff", np.full((4, 5, 3), 1.0, np.float32))
    with tifffile.TiffFile(tmp_path / "T.tiff") as tiff:
        description = json.loads(tiff.pages[0].description)
        assert description["full_scale"] == FULL_SCALE == 2.0 and "65535 = 2" in description["encoding"]
        assert tiff.asarray()[0, 0, 0] == round(65535 / 2)


def test_separate_all_before_ingest_exits_1_naming_the_ingest_command(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM).exit_code == 0
    out = invoke("separate", "--all", "--dataset", root, "--method", "none")
    assert out.exit_code == 1, out.output
    assert "scene_01: skipped: not ingested" in out.stdout and f"run urd ingest {root} first" in out.stderr


def test_a_command_run_inside_a_scene_folder_names_the_dataset_around_it(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM).exit_code == 0
    monkeypatch.chdir(root / "scene_01")
    for args in (["report"], ["verify"], ["separate", "scene_01"]):
        out = invoke(*args)
        assert out.exit_code == 1, out.output
        assert f"lies inside the dataset {root.resolve()} (in scene_01)" in out.stderr and "Make one" not in out.stderr


def test_the_text_report_gives_an_unfinished_captures_resume_command(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    stop_capture_before_shot(monkeypatch)
    assert invoke("capture", root, *SIM).exit_code == 130
    out = invoke("report", root)
    assert out.exit_code == 0 and "INCOMPLETE (1 of 3 shots" in out.stdout
    assert f"resume it with: urd capture {root.resolve()} --stage sim --camera virtual" in out.stdout and "--scene scene_01" in out.stdout


@pytest.mark.slow
def test_the_text_report_says_when_a_scenes_angles_predate_the_calibration(tmp_path):
    root = tmp_path / "ds"
    assert invoke("capture", root, *SIM, "--sim-offset", "3").exit_code == 0           # before the calibration
    out = invoke("calibrate", "offset", root, "--stage", "sim", "--camera", "virtual", "--sim-offset", "3", "--step", "30",
                 "--sim-size", "96x64")
    assert out.exit_code == 0, out.output
    report = invoke("report", root).stdout
    assert "scene_01: " in report and re.search(r"taken with the polarizer offset 0\.000° .* angles are off by \+[23]\.\d{3}°", report)


def test_weights_that_are_a_folder_are_a_usage_error_pointing_at_its_best_pt(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "best.pt").write_bytes(b"")
    out = invoke("separate", "--images", tmp_path / "a.tiff", "--weights", tmp_path / "run")
    assert out.exit_code == 2 and "is a folder, expected a weights file (a run folder: pass its best.pt)" in out.output
