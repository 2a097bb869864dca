"""A dataset from someone else (docs/dataset.md, "Threat model") whose manifests or result files
hold values of the wrong type, shape or range, or names with terminal escapes: the scene is
reported broken or damaged, naming the file and the field, and commands go on with the other
scenes; nothing reaches the terminal unescaped."""

import html
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from rig import capture_virtual, separated_virtual_scene
from urd.cli import app
from urd.core.dataset import Dataset
from urd.core.files import sha256_file

ESC = "\x1b]0;PWNED\x07\x1b[2K"


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Two 96×64 scenes ingested with results of 'none' and ground truth, and RAW files of a
    third capture the dataset does not hold (``new_raw`` beside it)."""
    ds = Dataset.open_or_create(tmp_path_factory.mktemp("base") / "ds")
    for seed in (1, 2):
        separated_virtual_scene(ds, seed)
    other, _ = capture_virtual(Dataset.open_or_create(ds.root.parent / "other"), size=(96, 64), shake_px=1.0,
                               shake_deg=0.1, seed=3)
    shutil.copytree(other.path / "raw", ds.root.parent / "new_raw")
    return ds.root


@pytest.fixture
def root(base, tmp_path):
    """A copy of `base` for one test to damage."""
    return Path(shutil.copytree(base, tmp_path / "ds", symlinks=True))


def edit(root, change, scene="scene_01"):
    """Apply ``change`` to the manifest of ``scene`` (a dict edited in place)."""
    path = root / scene / "scene.json"
    record = json.loads(path.read_text())
    change(record)
    path.write_text(json.dumps(record))


def put_result_file(root, name, values, scene="scene_01", method="none"):
    """Write ``values`` as the result file ``name`` of ``method`` and list it with its hash."""
    path = root / scene / "results" / method / name
    layout = {"photometric": "minisblack", "planarconfig": "contig"} if values.ndim == 3 else {}
    tifffile.imwrite(path, values, **layout)
    rec = {"file": f"results/{method}/{name}", "size": path.stat().st_size, "sha256": sha256_file(path)}

    def listed(record):
        files = record["results"][method]["files"]
        record["results"][method]["files"] = [f for f in files if f["file"] != rec["file"]] + [rec]

    edit(root, listed, scene)


def page(report):
    """The report's index.html as text (entities decoded)."""
    return html.unescape((report / "index.html").read_text(encoding="utf-8"))


def scene_section(text, name):
    """The part of the page about scene ``name``."""
    return text.split(f"<h2>{name}</h2>")[1].split('<section class="card scene"')[0]


def sim_stage(faults):
    return {"kind": "ELL14", "port": "sim", "address": "0", "serial": "12345678", "firmware": "17",
            "pulses_per_rev": 143360, "simulated": {"offset_deg": 0.0, "jitter_deg": 0.0, "faults": faults, "seed": 0}}


def unfinished(record, **capture):
    record["capture"].update(complete=False, **capture)


#: Manifest edits: name → (the edit of scene_01's manifest, what the error says of it).
EDITS = {
    "psnr a list": (lambda r: r["results"]["none"]["truth_metrics"]["T"].update(psnr_db=[1]),
                    "results.none.truth_metrics.T: field 'psnr_db' has type list"),
    "stage a text": (lambda r: unfinished(r, stage="x"), "capture: field 'stage' has type str"),
    "virtual camera without width": (
        lambda r: unfinished(r, stage=sim_stage({}), camera={"kind": "virtual", "model": "urd virtual camera", "height": 64,
                                                            "shake_px": 1.0, "shake_deg": 0.1, "seed": 1}),
        "capture.camera: missing field 'width'"),
    "faults a list": (lambda r: unfinished(r, stage=sim_stage([1])), "capture.stage.simulated: field 'faults' has type list"),
    "fault probability a text": (lambda r: unfinished(r, stage=sim_stage({"timeout": "x"})),
                                 "capture.stage.simulated.faults: field 'timeout' has type str"),
    "unfinished without angles": (lambda r: (unfinished(r), r["capture"].pop("angles_deg")),
                                  "capture: missing field 'angles_deg' of an unfinished capture"),
    "shot hash a list": (lambda r: r["ingest"].update(shot_hashes=[[1]]), "ingest.shot_hashes[0]: expected a SHA-256"),
    "exposure a list": (lambda r: r["shots"][0]["camera"].update(exposure_s=[1]),
                        "shots[0].camera: field 'exposure_s' has type list"),
    "calibration errors of another count": (
        lambda r: r.update(calibration={"time": "t", "applied": False, "errors_deg": [0.1, 0.2],
                                        "uncertainty_deg": [0.1, 0.1]}),
        "calibration.errors_deg: expected one value per shot (3), got 2"),
    "aligned shots of another count": (lambda r: r["ingest"]["aligned"].append(r["ingest"]["aligned"][0]),
                                       "ingest.aligned: expected one aligned shot per shot (3), got 4"),
    "null byte in a file name": (lambda r: r["shots"][0].update(file="raw/shot\u0000.dng"),
                                 r"'raw/shot\x00.dng' holds a control character"),
    "escape in a method name": (lambda r: r["results"].update({f"net{ESC}": r["results"]["none"]}),
                                r"results: method name: 'net\x1b]0;PWNED\x07\x1b[2K' holds a control character"),
    "escape in a stage port": (lambda r: unfinished(r, stage={**sim_stage({}), "port": f"sim{ESC}"}),
                               r"capture.stage: field 'port': 'sim\x1b]0;PWNED\x07\x1b[2K' holds a control character"),
}


@pytest.mark.parametrize("name", EDITS)
def test_a_manifest_field_of_the_wrong_type_is_a_broken_scene_named_in_reports(root, tmp_path, name):
    change, named = EDITS[name]
    edit(root, change)
    text = invoke("report", root)
    assert text.exit_code == 0 and text.exception is None, text.output
    assert "scene_01: BROKEN" in text.output and named in text.output, text.output
    assert "scene_02: 3 shots at 0,45,90 deg, aligned" in text.output and "\x1b" not in text.output
    verify = invoke("verify", root)
    assert verify.exit_code == 1 and isinstance(verify.exception, SystemExit), verify.output
    assert named in verify.output and "scene_02: ok" in verify.output and "\x1b" not in verify.output
    report = invoke("report", root, "--html", tmp_path / "report")
    assert report.exit_code == 0, report.output
    assert named in scene_section(page(tmp_path / "report"), "scene_01")
    assert (tmp_path / "report" / "img" / "s001-scene_02" / "m00_none_T.jpg").is_file()


@pytest.mark.parametrize("name, jobs", [("exposure a list", "1"), ("exposure a list", "2"), ("null byte in a file name", "1"),
                                        ("shot hash a list", "1")])
def test_ingest_redo_goes_on_with_the_other_scenes(root, name, jobs):
    change, named = EDITS[name]
    edit(root, change)
    out = invoke("ingest", root, "--redo", "--jobs", jobs)
    assert out.exit_code == 1 and isinstance(out.exception, SystemExit), out.output
    assert named in out.output and "ingested scene_02" in out.output, out.output


def test_ingest_of_new_raw_files_goes_on_past_a_scene_with_odd_hashes(base, root):
    edit(root, EDITS["shot hash a list"][0])
    out = invoke("ingest", base.parent / "new_raw", root)
    assert out.exit_code == 0 and out.exception is None, out.output
    assert "ingested scene_03" in out.output


def valid_calibration(**fields):
    return {"schema": "urd.calibration", "schema_version": 1, "time": "2026-01-01T00:00:00+00:00", "offset_deg": 0.0,
            "uncertainty_deg": 0.1, "target_angle_deg": 0.0, "history": [], **fields}


def test_a_calibration_whose_stage_is_not_an_object_stops_a_capture_with_one_line(root):
    (root / "calibration.json").write_text(json.dumps(valid_calibration(stage="x")))
    out = invoke("capture", root, "--stage", "sim", "--camera", "virtual", "--sim-size", "96x64")
    assert out.exit_code == 1 and isinstance(out.exception, SystemExit), out.output
    assert "calibration.json: field 'stage' has type str, expected dict" in out.output
    assert not (root / "scene_03").exists()


def test_a_calibration_stage_with_an_escape_is_refused(root):
    stage = {"kind": "ELL14", "serial": f"1{ESC}", "address": "0"}
    (root / "calibration.json").write_text(json.dumps(valid_calibration(stage=stage)))
    out = invoke("report", root)
    assert out.exit_code == 0 and "holds a control character" in out.output and "\x1b" not in out.output, out.output


def test_a_calibration_sweep_without_stage_angles_is_shown_with_a_note(root, tmp_path):
    (root / "calibration.json").write_text(json.dumps(valid_calibration(sweep="scene_01")))
    edit(root, lambda r: r["shots"][1].update(stage_position_deg=None))
    out = invoke("report", root, "--html", tmp_path / "report")
    assert out.exit_code == 0, out.output
    calibration = page(tmp_path / "report").split('id="calibration">')[1].split("</section>")[0]
    assert "shot 1 records no stage angle (stage_position_deg)" in calibration


#: Result files of scene_01 replaced: name → (file, its values, what the note says).
RESULT_FILES = {
    "an infinite reference": ("reference_deg.tiff", np.array([[1.0, np.inf], [2.0, 3.0]], np.float32), "got NaN or infinite"),
    "a NaN reference": ("reference_deg.tiff", np.array([[1.0, np.nan], [2.0, 3.0]], np.float32), "got NaN or infinite"),
    "a 4-channel reference": ("reference_deg.tiff", np.zeros((4, 6, 4), np.float32), "got float32 of shape (4, 6, 4)"),
    "a 1-D reference": ("reference_deg.tiff", np.zeros(6, np.float32), "got float32 of shape (6,)"),
    "an 8-bit confidence": ("confidence.tiff", np.zeros((64, 96), np.uint8), "got uint8 of shape (64, 96)"),
    "a 4-channel R": ("R.tiff", np.zeros((64, 96, 4), np.uint16), "got uint16 of shape (64, 96, 4)"),
}


@pytest.mark.parametrize("name", RESULT_FILES)
def test_a_result_file_of_another_layout_is_left_out_of_the_report_with_a_note(root, tmp_path, name):
    file, values, named = RESULT_FILES[name]
    put_result_file(root, file, values)
    out = invoke("report", root, "--html", tmp_path / "report")
    assert out.exit_code == 0, out.output
    section = scene_section(page(tmp_path / "report"), "scene_01")
    assert f"none: {root / 'scene_01/results/none' / file}: expected" in section and named in section
    assert (tmp_path / "report" / "img" / "s000-scene_01" / "shot_00.jpg").is_file()
    assert (tmp_path / "report" / "img" / "s001-scene_02" / "m00_none_T.jpg").is_file()


@pytest.mark.parametrize("name", ["an infinite reference", "a 4-channel reference", "a 1-D reference"])
def test_maps_from_a_damaged_reference_field_is_one_error_line_naming_the_file(root, name):
    file, values, named = RESULT_FILES[name]
    put_result_file(root, file, values)
    out = invoke("separate", "scene_01", "--dataset", root, "--maps", "--method", "none")
    assert out.exit_code == 1 and isinstance(out.exception, SystemExit), out.output
    assert out.output.startswith(f"Error: {root / 'scene_01/results/none' / file}: expected") and named in out.output


def test_polarization_maps_refuse_a_reference_that_is_neither_an_angle_nor_a_field():
    from separate.maps import polarization_maps

    images = np.random.default_rng(0).uniform(0.2, 0.8, (3, 8, 8, 3)).astype(np.float32)
    for reference, error in ((np.zeros(4), ValueError), (np.zeros((4, 4, 4)), ValueError),
                             (np.full((4, 4), np.nan), ValueError), (np.array(["a"]), TypeError)):
        with pytest.raises(error, match="reference_deg"):
            polarization_maps(images, [0, 45, 90], reference)
    assert polarization_maps(images, [0, 45, 90], np.full((4, 4), 10.0))["phi_perp"].shape == (8, 8)


def test_aligned_shots_of_four_channels_are_left_out_of_the_report_with_a_note(root, tmp_path):
    def four_channels(record):
        for rec in record["ingest"]["aligned"]:
            path = root / "scene_01" / rec["file"]
            tifffile.imwrite(path, np.zeros((64, 96, 4), np.uint16))
            rec.update(size=path.stat().st_size, sha256=sha256_file(path))

    edit(root, four_channels)
    out = invoke("report", root, "--html", tmp_path / "report")
    assert out.exit_code == 0, out.output
    section = scene_section(page(tmp_path / "report"), "scene_01")
    assert "shots not shown: scene_01: the aligned shots are of shape (64, 96, 4)" in section
    assert (tmp_path / "report" / "img" / "s001-scene_02" / "shot_00.jpg").is_file()


def test_a_scene_folder_linked_outside_is_shown_broken_naming_the_link(root, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.move(root / "scene_02", outside / "scene_02")
    (root / "scene_02").symlink_to(outside / "scene_02", target_is_directory=True)
    out = invoke("report", root, "--html", tmp_path / "report")
    assert out.exit_code == 0, out.output
    section = scene_section(page(tmp_path / "report"), "scene_02")
    assert f"not shown: {root / 'scene_02'} is a symbolic link" in section
    assert not (tmp_path / "report" / "img" / "s001-scene_02").exists()
    assert f"{root / 'scene_02'} is a symbolic link" in out.output             # the text report says so too
    assert (tmp_path / "report" / "img" / "s000-scene_01" / "shot_00.jpg").is_file()


def test_raw_metadata_and_folder_names_reach_the_terminal_escaped(root):
    from urd.core.manifest import printable
    from urd.ingest import exposure_warning

    assert printable(f"a{ESC}b\u202e") == r"a\x1b]0;PWNED\x07\x1b[2Kb\u202e"
    warning = exposure_warning([{"model": f"cam{ESC}", "exposure_s": 0.01}, {"model": f"cam{ESC}", "exposure_s": 0.02}])
    assert "exposure times differ" in warning
    with pytest.raises(Exception, match="different cameras") as raised:
        exposure_warning([{"model": f"a{ESC}"}, {"model": "b"}])
    assert "\x1b" not in str(raised.value) and r"a\x1b]0;PWNED" in str(raised.value)
    shutil.copytree(root / "scene_01", root / f"kitchen{ESC}")
    for args in (("verify", root), ("report", root)):
        out = invoke(*args)
        assert r"kitchen\x1b]0;PWNED" in out.output and "\x1b" not in out.output, out.output
