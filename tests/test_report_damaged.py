"""``urd report --html`` on damaged datasets and in awkward report folders: a damaged scene or
calibration is shown with a note while the rest of the report is written, ``--force`` replaces
only what urd's report wrote, and folders inside the dataset or read-only are refused with one
clear line."""

from __future__ import annotations

import html
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from conftest import mounted_tmpfs
from urd.cli import app

pytestmark = pytest.mark.usefixtures("wide_terminal")
SIM = ("--stage", "sim", "--camera", "virtual", "--sim-size", "96x64")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def separated(tmp_path_factory) -> Path:
    """A dataset of two 96×64 scenes, captured, ingested and separated with schechner."""
    root = tmp_path_factory.mktemp("damaged") / "ds"
    for args in (["capture", root, *SIM], ["capture", root, *SIM], ["ingest", root],
                 ["separate", "--all", "--dataset", root, "--method", "schechner"]):
        result = invoke(*args)
        assert result.exit_code == 0, result.output
    return root


@pytest.fixture
def dataset(separated, tmp_path) -> Path:
    """A copy of `separated` for one test to damage."""
    return Path(shutil.copytree(separated, tmp_path / "ds"))


def _page(report: Path) -> str:
    """The report's index.html as text (entities decoded)."""
    return html.unescape((report / "index.html").read_text(encoding="utf-8"))


@pytest.mark.parametrize("damage, problem", [("missing", "listed in the manifest but missing"),
                                             ("changed", "SHA-256 or size does not match the manifest")])
def test_a_scene_with_a_damaged_aligned_shot_is_shown_with_a_note(dataset, tmp_path, damage, problem):
    shot = dataset / "scene_01" / "aligned" / "shot_00.tiff"
    if damage == "missing":
        shot.unlink()
    else:
        shot.write_bytes(shot.read_bytes()[:200])
    result = invoke("report", dataset, "--html", tmp_path / "report")
    assert result.exit_code == 0, result.output                      # as for damaged result files
    page = _page(tmp_path / "report")
    assert f"shots not shown: {shot}: {problem}" in page
    assert "Separation (1 method)" in page.split("<h2>scene_01</h2>")[1].split("<h2>scene_02</h2>")[0]
    assert (tmp_path / "report" / "img" / "s001-scene_02" / "shot_00.jpg").is_file()


def test_damaged_results_and_a_damaged_shot_give_the_same_exit_status(dataset, tmp_path):
    (dataset / "scene_01" / "results" / "schechner" / "R.tiff").write_bytes(b"not a tiff")
    results = invoke("report", dataset, "--html", tmp_path / "results")
    (dataset / "scene_02" / "aligned" / "shot_01.tiff").unlink()
    shots = invoke("report", dataset, "--html", tmp_path / "shots")
    assert results.exit_code == shots.exit_code == 0, shots.output
    assert "shots not shown" in _page(tmp_path / "shots") and "schechner: " in _page(tmp_path / "results")


def test_stale_results_of_another_size_are_left_out_with_a_note(dataset, tmp_path):
    assert invoke("ingest", dataset / "scene_01", "--redo", "--half-size").exit_code == 0
    result = invoke("report", dataset, "--html", tmp_path / "report")
    assert result.exit_code == 0, result.output
    page = _page(tmp_path / "report")
    assert ("schechner: not shown: its results are 96×64 px, the shots 48×32 px; separate it again: urd separate "
            f"scene_01 --dataset {dataset} --method schechner --force") in page
    assert (tmp_path / "report" / "img" / "s000-scene_01" / "shot_00.jpg").is_file()          # the new shots
    assert not list((tmp_path / "report" / "img" / "s000-scene_01").glob("m00_*"))
    assert (tmp_path / "report" / "img" / "s001-scene_02" / "m00_schechner_T.jpg").is_file()


@pytest.mark.parametrize("damage, note, offset", [
    ("sweep", "cannot be shown: ", "179.999° ± "),
    ("record", "the calibration cannot be read: ", "<dt>polarizer offset</dt><dd>unknown</dd>")])
def test_a_damaged_calibration_is_shown_with_a_note(dataset, tmp_path, damage, note, offset):
    assert invoke("calibrate", "offset", dataset, "--stage", "sim", "--camera", "virtual", "--step", "30").exit_code == 0
    if damage == "sweep":
        (dataset / "calibration" / "sweep_01" / "scene.json").unlink()
    else:
        (dataset / "calibration.json").write_text("{")
    result = invoke("report", dataset, "--html", tmp_path / "report")
    assert result.exit_code == 0, result.output
    page = _page(tmp_path / "report")
    calibration = page.split('<section class="card" id="calibration">')[1].split("</section>")[0]
    assert note in calibration and offset in calibration and "<svg" not in calibration
    assert (tmp_path / "report" / "img" / "s001-scene_02" / "shot_00.jpg").is_file()


def test_force_refuses_a_report_folder_holding_files_urd_did_not_write(separated, tmp_path):
    report = tmp_path / "report"
    assert invoke("report", separated, "--html", report).exit_code == 0
    (report / "mynotes.txt").write_text("mine")
    (report / "sub").mkdir()
    (report / "sub" / "keep.txt").write_text("also mine")
    for extra in ("mynotes.txt", "sub"):
        result = invoke("report", separated, "--html", report, "--force")
        assert result.exit_code == 1
        assert f"Error: {report}: holds {report / extra}, which urd's report did not write" in result.stderr
        assert (report / "sub" / "keep.txt").read_text() == "also mine" and (report / "index.html").is_file()
        (report / "mynotes.txt").unlink(missing_ok=True)
    shutil.rmtree(report / "sub")
    assert invoke("report", separated, "--html", report, "--force").exit_code == 0
    assert sorted(p.name for p in report.iterdir()) == [".urd-report-contents", "img", "index.html"]


def test_a_report_folder_inside_the_dataset_is_refused(dataset):
    result = invoke("report", dataset, "--html", dataset / "scene_06")
    assert result.exit_code == 1
    assert f"Error: {dataset / 'scene_06'} is inside the dataset {dataset}" in result.stderr
    assert not (dataset / "scene_06").exists()
    assert invoke("verify", dataset).exit_code == 0


def test_a_read_only_report_folder_is_named_in_one_clear_line(separated, tmp_path):
    with mounted_tmpfs(tmp_path / "ro", "ro,size=1m", "a read-only tmpfs") as folder:
        result = invoke("report", separated, "--html", folder / "report")
    assert result.exit_code == 1
    error = result.stderr.strip()
    assert error == (f"Error: cannot write the report folder {folder / 'report'} (Read-only file system); "
                     "choose another folder for the report, or make its parent writable")
