"""What a new user trips on after `urd demo` (issue 43): maps that keep their stated ranges and
come without a network pass, errors that name the option, progress that shows waits, hints."""

import json
import shutil

import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

import urd
from separate import optics
from separate.maps import DARK_S0, MAPS, polarization_maps
from conftest import ingested_dataset, mounted_tmpfs
from urd.cli import app
from urd.core.dataset import Dataset

pytestmark = pytest.mark.usefixtures("wide_terminal")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def separated(tmp_path_factory):
    """A dataset with one captured, ingested 256×192 scene (scene_01), separated by the network."""
    root = ingested_dataset(tmp_path_factory, "second-look")
    result = invoke("separate", "scene_01", "--dataset", root)
    assert result.exit_code == 0, result.output
    return root


def noisy_dark_stack(seed: int = 0) -> tuple[np.ndarray, list[float]]:
    """Shots of a 40%-polarized scene whose left half is nearly black, with sensor noise."""
    rng = np.random.default_rng(seed)
    angles = [0.0, 45.0, 90.0]
    s0 = np.full((16, 32, 3), 0.6, np.float32)
    s0[:, :16] = 0.002
    stokes = np.stack([s0, 0.4 * s0, np.zeros_like(s0)])
    shots = np.stack([optics.intensity_from_stokes(stokes, np.radians(a)) for a in angles])
    return (shots + rng.normal(0, 0.003, shots.shape)).astype(np.float32), angles


# ---------------------------------------------------------------- 1. maps


def test_dolp_stays_in_its_range_and_dark_pixels_are_marked():
    shots, angles = noisy_dark_stack()
    maps = polarization_maps(shots, angles, 0.0)
    dolp, aolp = maps["DoLP"], maps["AoLP"]
    assert np.isnan(dolp[:, :16]).all() and np.isnan(aolp[:, :16]).all()    # S0 within the noise
    assert not np.isnan(dolp[:, 16:]).any()
    assert np.nanmax(dolp) <= 1.0 and np.nanmin(dolp) >= 0.0
    np.testing.assert_allclose(dolp[:, 16:], 0.4, atol=0.05)
    assert "NaN" in MAPS["DoLP"][1] and str(DARK_S0) in MAPS["DoLP"][1] and "[0, 1]" in MAPS["DoLP"][1]


def test_maps_of_a_separated_scene_come_without_the_network(separated, monkeypatch, tmp_path):
    import separate.methods
    import urd.separation

    separated = shutil.copytree(separated, tmp_path / "separated")        # other tests add maps to the shared one

    def no_network(*args, **kwargs):
        raise AssertionError("the network was run")

    monkeypatch.setattr(separate.methods, "get_method", no_network)
    monkeypatch.setattr(urd.separation, "separate_inspected", no_network)
    before = Dataset.open(separated).scene("scene_01").result("network")
    result = invoke("separate", "scene_01", "--dataset", separated, "--maps")
    assert result.exit_code == 0, result.output
    assert "added the polarization maps" in result.output and "not separated again" in result.output
    scene = Dataset.open(separated).scene("scene_01")
    after = scene.result("network")
    assert {name for name in after.files} == {name for name in before.files} | {f"{m}.tiff" for m in MAPS}
    assert after.files["R.tiff"].read_bytes() == before.files["R.tiff"].read_bytes()
    assert scene.verify() == []                                              # stored with their hashes
    records = json.loads(scene.manifest_path.read_text())["results"]["network"]["files"]
    assert {"results/network/maps/DoLP.tiff", "results/network/R.tiff"} <= {r["file"] for r in records}
    assert all(len(r["sha256"]) == 64 for r in records)
    with tifffile.TiffFile(after.files["confidence.tiff"]) as tif:
        described = json.loads(tif.pages[0].description)
        assert described["quantity"].startswith("reflection presence") and described["unit"] == "1 (a fraction)"
        assert 0 <= tif.asarray().min() and tif.asarray().max() <= 1
    with tifffile.TiffFile(after.files["DoLP.tiff"]) as tif:
        assert "NaN" in json.loads(tif.pages[0].description)["quantity"]
        dolp = tif.asarray()
    assert np.nanmax(dolp) <= 1.0
    phi = tifffile.imread(after.files["phi_perp.tiff"])
    assert np.isfinite(phi).all()
    again = invoke("separate", "scene_01", "--dataset", separated, "--maps")   # maps there already: nothing replaced
    assert again.exit_code == 1 and "already have maps" in again.output and "--force" in again.output


def test_all_maps_adds_maps_to_separated_scenes(separated, monkeypatch):
    import urd.batch

    assert invoke("separate", "--all", "--method", "none", "--dataset", separated).exit_code == 0
    monkeypatch.setattr(urd.batch, "_prepare", lambda *a, **k: pytest.fail("a scene was separated again"))
    result = invoke("separate", "--all", "--method", "none", "--dataset", separated, "--maps")
    assert result.exit_code == 0, result.output
    assert "scene_01: maps added: to the none results (not separated again)" in result.output
    assert "0 scenes separated with none, maps added to 1, 0 failed" in result.output
    assert "maps" in {p.parent.name for p in Dataset.open(separated).scene("scene_01").result("none").files.values()}
    invoke("separate", "scene_01", "--dataset", separated, "--maps")              # network maps there (added, or already)
    result = invoke("separate", "--all", "--method", "network", "--dataset", separated, "--maps")
    assert result.exit_code == 0, result.output
    assert "scene_01: skipped: has network results with maps" in result.output


def test_polarization_maps_settle_the_side_without_the_network(monkeypatch):
    import separate.methods

    real = separate.methods.get_method

    def classical_only(name, *args, **kwargs):
        assert name != "network", "polarization_maps ran the network"
        return real(name, *args, **kwargs)

    monkeypatch.setattr(separate.methods, "get_method", classical_only)
    shots, angles = noisy_dark_stack()
    maps = urd.polarization_maps(shots, angles)
    assert set(maps) == set(MAPS)


# ---------------------------------------------------------------- 2. one error style


@pytest.mark.parametrize(("args", "option", "says"), [
    (("--method", "schechnr"), "--method", "expected one of arvanitopoulos, ceilnet"),
    (("--reference", "sideways"), "--reference", "expected 'auto', 'global' or an angle"),
    (("--precision", "fp16"), "--precision", "fp32 or bf16, got 'fp16'"),
    (("--tile", "100"), "--tile", "at least 320 px"),
])
def test_usage_errors_name_the_option(separated, args, option, says):
    result = invoke("separate", "scene_01", "--dataset", separated, *args)
    assert result.exit_code == 2
    assert f"Error: Invalid value for '{option}': " in result.output and says in result.output


def test_a_missing_scene_is_named_with_the_scenes_there(separated):
    result = invoke("separate", "scene_09", "--dataset", separated)
    assert result.exit_code == 2
    assert "Error: Invalid value for 'SCENE': no scene 'scene_09'" in result.output and "scenes: scene_01" in result.output


def test_bounds_speak_urd_not_pydantic(separated):
    result = invoke("separate", "--all", "--jobs", "0", "--dataset", separated)
    assert result.exit_code == 2
    assert "Error: Invalid value for '--jobs': expected at least 1, got 0" in result.output
    assert "Input should be" not in result.output
    result = invoke("calibrate", "offset", "--stage", "sim", "--step", "90")
    assert result.exit_code == 2 and "Invalid value for '--step': expected between 1 and 45, got 90" in result.output


def test_options_that_do_not_go_together_are_a_usage_error(separated):
    result = invoke("separate", "scene_01", "--dataset", separated, "--jobs", "2")
    assert result.exit_code == 2 and "Error: --jobs is for --all" in result.output and "Invalid value" not in result.output


def test_failures_exit_1_in_the_same_voice(separated):
    result = invoke("separate", "scene_01", "--dataset", separated)          # results there already
    assert result.exit_code == 1 and result.output.startswith("Error: ") and "--force" in result.output


def test_an_unwritable_output_folder_fails_before_the_network(tmp_path, monkeypatch):
    import urd.separation

    monkeypatch.setattr(urd.separation, "separate_inspected", lambda *a, **k: pytest.fail("the method ran"))
    shots, _ = noisy_dark_stack()
    files = []
    for k, shot in enumerate(shots):
        files += ["--images", tmp_path / f"shot_{k}.tiff"]
        tifffile.imwrite(tmp_path / f"shot_{k}.tiff", (np.clip(shot, 0, 1) * 65535).astype(np.uint16))
    (tmp_path / "a-file").write_text("not a folder")
    result = invoke("separate", *files, "--method", "schechner", "--out", tmp_path / "a-file" / "out")
    assert result.exit_code == 1
    assert "Error: cannot write into the output folder" in result.output and "nothing was separated" in result.output


def test_a_full_disk_is_said_as_such_with_the_file(tmp_path):
    with mounted_tmpfs(tmp_path / "small", "size=96k", "a small tmpfs") as small:
        files = []
        for k, angle in enumerate((0, 45, 90)):
            shot = np.random.default_rng(k).integers(0, 65535, (128, 160, 3), dtype=np.uint16)
            tifffile.imwrite(tmp_path / f"shot_{angle}.tiff", shot)
            files += ["--images", tmp_path / f"shot_{angle}.tiff"]
        result = invoke("separate", *files, "--method", "schechner", "--out", small / "out")
        assert result.exit_code == 1
        assert "Error: disk full: " + str(small / "out") in result.output
        assert "requested and" not in result.output and "Write Error" not in result.output


# ---------------------------------------------------------------- 3. progress that tells the truth


def test_the_driver_reports_its_waits_and_retries(scripted_peer):
    import serial

    from acquire.ell14 import Ell14

    info = b"0IN0E1140051720231701016800023000\r\n"
    peer = scripted_peer([(b"0in", info), (b"0gp", b""), (b"0gp", b"0PO00008C00\r\n")])    # the first reply is lost
    waits, retries = [], []
    with serial.Serial(peer.port_name, 9600, timeout=0.1) as port, Ell14(port, timeout_s=0.5) as stage:
        stage.info()
        stage.on_wait, stage.on_retry = lambda: waits.append(1), retries.append
        assert stage.position() == pytest.approx(90.0)
    peer.check()
    assert retries == ["no reply within 0.5 s to 'gp'; sending it again (retry 1 of 2)"]
    assert len(waits) >= 4                                  # the bar is redrawn while the lost reply is waited out


def test_the_capture_bar_runs_through_waits_and_shows_retries():
    from acquire.plan import _shown

    class Stage:
        on_wait = on_retry = None

    calls, lines = [], []
    stage = Stage()
    with _shown(stage, lambda *args: calls.append(args), 5, "capture scene_01", lines.append) as show:
        stage.on_wait()
        stage.on_retry("no reply within 10 s to 'ma00008C00'; sending it again (retry 1 of 2)")
        stage.on_wait()
        show(None)
    assert calls == [(0, 5, "capture scene_01")] * 3 + [(1, 5, "capture scene_01")]   # drawn from the start, during waits
    assert lines == ["stage: no reply within 10 s to 'ma00008C00'; sending it again (retry 1 of 2)"]
    assert stage.on_wait is None and stage.on_retry is None


# ---------------------------------------------------------------- 4. hints


def test_ingest_of_frames_without_mosaic_names_the_option(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    tifffile.imwrite(frames / "frame_0001.tiff", np.zeros((8, 8), np.uint16))
    result = invoke("ingest", frames, tmp_path / "ds")
    assert result.exit_code == 1
    assert "no RAW files" in result.output and "--mosaic imx250mzr|imx250myr|wen2019" in result.output


@pytest.mark.slow
def test_each_demo_run_gets_a_fresh_dataset_and_says_so(tmp_path):
    folder = tmp_path / "urd-demo"
    first = invoke("demo", folder, "--size", "256x192")
    assert first.exit_code == 0, first.output
    assert "exists" not in first.output and Dataset.open(folder).scene_names() == ["scene_01"]
    second = invoke("demo", folder, "--size", "256x192")
    assert second.exit_code == 0, second.output
    assert f"{folder} exists (an earlier run): this run writes a fresh dataset, {folder}-2" in second.output
    assert Dataset.open(folder).scene_names() == ["scene_01"]                 # nothing piled up
    assert Dataset.open(tmp_path / "urd-demo-2").scene_names() == ["scene_01"]


def test_skips_for_the_shared_data_say_what_it_is():
    from conftest import shared_data

    with pytest.raises(pytest.skip.Exception) as skipped:
        shared_data("no-such-set")
    reason = str(skipped.value)
    assert "no-such-set is not present" in reason and "third-party research data" in reason
    assert "urd does not ship it" in reason


# ---------------------------------------------------------------- 5. the report for a newcomer


def test_the_report_explains_itself_names_the_best_method_and_previews_the_maps(separated, tmp_path):
    import re

    import cv2

    invoke("separate", "scene_01", "--dataset", separated, "--maps")          # maps there (added, or already)
    if "none" not in Dataset.open(separated).scene("scene_01").methods():
        assert invoke("separate", "scene_01", "--dataset", separated, "--method", "none").exit_code == 0
    result = invoke("report", separated, "--html", tmp_path / "report")
    assert result.exit_code == 0, result.output
    page = (tmp_path / "report" / "index.html").read_text()
    howto = page[page.index("Reading this page"):]
    assert howto.index("<b>Each scene</b>") < howto.index("k = 1 /")                 # what a row is before the maths
    assert "<b>Reflection presence</b> is a hint" in howto and "transmitted objects" in howto
    truth = Dataset.open(separated).scene("scene_01")
    psnr = {m: truth.result(m).truth_metrics["T"]["psnr_db"] for m in ("network", "none")}
    best = max(psnr, key=psnr.get)
    assert f"Against the ground truth, <b>{best}</b> recovers T̂ with {psnr[best]:.2f} dB PSNR (best of 2 methods" in page
    assert "<th>best T̂ vs ground truth</th>" in page and f"<td>{best}, {psnr[best]:.2f} dB</td>" in page
    previews = re.findall(r'<a href="([^"]+_map_DoLP\.png)">DoLP</a>', page)
    assert any("_network_map_DoLP.png" in p for p in previews)
    preview = cv2.imread(str(tmp_path / "report" / previews[0]))
    assert preview is not None and preview.shape[2] == 3                           # a PNG a browser shows
    assert "maps/DoLP.tiff" in page                                                # the data stays linked
    phi = re.search(r'<img src="([^"]+_phi_t\.jpg)" width="(\d+)"', page)
    assert phi is not None and int(phi.group(2)) <= 320 // 3                        # the φ⊥ map is small


def test_help_gives_each_command_its_whole_summary():
    import typer

    result = invoke("--help")
    commands = result.output[result.output.index("Commands:"):]
    assert result.exit_code == 0 and "..." not in commands and "…" not in commands
    words = " ".join(commands.split())
    for name, command in typer.main.get_command(app).commands.items():
        first = command.get_short_help_str(limit=1000)
        assert " ".join(first.split()) in words, name
    sub = invoke("calibrate", "--help")
    assert "..." not in sub.output.split("Commands:")[1] and "mounting offset." in " ".join(sub.output.split())


def test_the_api_example_prints_the_angle_of_incidence_over_the_frame_not_a_corner_pixel():
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    for text in ((root / "docs" / "api.md").read_text(), (root / "docs" / "examples" / "separate_scene.py").read_text()):
        assert "theta'][0, 0]" not in text and "np.median(theta)" in text


# ---------------------------------------------------------------- 6. one owner per room


def test_hardware_and_calibration_do_not_import_each_other():
    import ast
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    contracts = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert {"type": "independence", "modules": ["acquire", "calib"]}.items() <= next(
        c for c in contracts if c["type"] == "independence").items()
    for package, other in (("acquire", "calib"), ("calib", "acquire")):
        for path in (root / package).glob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else []
                assert not any(n == other or n.startswith(other + ".") for n in names), f"{path.name} imports {other}"
