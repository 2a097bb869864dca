"""QA of the HTML report: badges coloured by the scene's state, captured shot counts, what an
unfinished scene shows and no empty folders, the Scenes table and the viewer on narrow and
large views, links to files in folders with #, % or ?, a cyclic AoLP preview, scenes captured
before the current calibration, and the calibration card, empty dataset and reference-field
legend wording."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from acquire.plan import new_capture_scene, resume_command
from urd.cli import app
from urd.core.dataset import Dataset, OffsetCalibration, Scene
from urd.report import report_html, scene_view
from urd.report_assets import CSS
from urd.report_html import CalibrationView, ResultView, SceneView, write_html_report
from urd.report_images import map_preview

SIM = ("--stage", "sim", "--camera", "virtual", "--sim-size", "96x64")


def _invoke(*args) -> None:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """scene_01 separated (schechner), scene_02 captured and not ingested, scene_03 incomplete
    (planned, no shot taken yet); all captured with offset 0°."""
    root = tmp_path_factory.mktemp("qa-html") / "ds"
    _invoke("capture", root, *SIM)
    _invoke("ingest", root)
    _invoke("separate", "--all", "--dataset", root, "--method", "schechner")
    _invoke("capture", root, *SIM)
    new_capture_scene(Dataset.open(root), [0.0, 45.0, 90.0])
    return root


def _shot(value: float = 0.25) -> np.ndarray:
    return np.full((24, 32, 3), value, np.float32)


def _view(name: str, state: str, shots: int = 0, **fields) -> SceneView:
    return SceneView(name, f"{state} scene", [(45.0 * k, _shot()) for k in range(shots)], None, None, [], [],
                     state=state, **fields)


def _page(index: Path) -> str:
    return index.read_text(encoding="utf-8")


def _toc_rows(page: str) -> dict[str, list[str]]:
    """The Scenes table: scene name → its cells (HTML)."""
    body = page[page.index("<tbody>"):page.index("</tbody>")]
    return {re.search(r">([^<]+)</a>", row).group(1): re.findall(r"<td>(.*?)</td>", row)
            for row in re.findall(r"<tr>(.*?)</tr>", body)}


# 1. badges


def test_badges_are_coloured_by_the_scene_state(tmp_path):
    states = ["separated", "ingested", "captured", "incomplete", "alignment failed", "broken", "something else"]
    page = _page(write_html_report([_view(f"s{i}", state) for i, state in enumerate(states)], tmp_path / "r", "t"))
    badges = dict((text, cls) for cls, text in re.findall(r'<span class="badge ([^"]+)">([^<]+) scene</span>', page))
    assert badges == {"separated": "separated", "ingested": "ingested", "captured": "captured",
                      "incomplete": "incomplete", "alignment failed": "broken", "broken": "broken",
                      "something else": "other"}


def test_scene_views_carry_the_scene_state(dataset):
    ds = Dataset.open(dataset)
    assert [scene_view(scene).state for scene in ds.scenes()] == ["separated", "captured", "incomplete"]


# 2. shot counts


def test_the_scenes_table_counts_the_captured_shots(tmp_path):
    scenes = [_view("aligned", "ingested", shots=3), _view("raw", "captured", captured_deg=[0.0, 45.0, 90.0]),
              _view("part", "incomplete", captured_deg=[0.0, 30.0])]
    rows = _toc_rows(_page(write_html_report(scenes, tmp_path / "r", "t")))
    assert {name: cells[2] for name, cells in rows.items()} == {"aligned": "3", "raw": "3", "part": "2"}


# 3. unfinished scenes


def test_an_unfinished_scene_shows_its_angles_and_the_command_that_continues(dataset, tmp_path):
    ds = Dataset.open(dataset)
    views = {scene.name: scene_view(scene) for scene in ds.scenes()}
    assert views["scene_01"].next_step == ""
    assert views["scene_02"].next_step == f"urd ingest {dataset.resolve()}"
    assert views["scene_02"].captured_deg == [0.0, 45.0, 90.0]
    assert views["scene_03"].next_step == resume_command(dataset, ds.scene("scene_03"))
    page = _page(write_html_report(list(views.values()), tmp_path / "r", "t"))
    scene_02 = page[page.index("<h2>scene_02</h2>"):page.index("<h2>scene_03</h2>")]
    assert "3 captured, at φ = 0.0°, 45.0°, 90.0°; no aligned images yet" in scene_02
    assert f"To continue: <code>urd ingest {dataset.resolve()}</code>" in scene_02
    assert "To continue: <code>urd capture " in page[page.index("<h2>scene_03</h2>"):]
    assert [p.name for p in (tmp_path / "r" / "img").iterdir()] == ["s000-scene_01"]     # no empty folders


# 4. the Scenes table on a phone


def test_the_scenes_table_scrolls_within_its_card(tmp_path):
    page = _page(write_html_report([_view("s", "ingested", shots=3)], tmp_path / "r", "t"))
    assert '<nav class="card toc"><h2>Scenes</h2><div class="scroll"><table>' in page
    assert re.search(r"nav\.toc \.scroll \{[^}]*overflow-x: auto", CSS)


# 5. links to files in awkward folders


def test_links_to_map_files_are_percent_encoded(tmp_path):
    maps = tmp_path / "data #1 100% ?" / "maps"
    maps.mkdir(parents=True)
    tiff = maps / "DoLP.tiff"
    tifffile.imwrite(tiff, np.full((24, 32), 0.5, np.float32))
    result = ResultView("m#1", _shot(0.1), _shot(0.15), {}, exports=[tiff])
    scene = SceneView("s", "separated", [], None, None, [result], [])
    out = tmp_path / "r"
    page = _page(write_html_report([scene], out, "t"))
    hrefs = re.findall(r'(?:href|src|<option value)="((?!data:)[^"#][^"]*)"', page)
    assert any("%23" in h and "%25" in h and "%3F" in h for h in hrefs)
    for href in hrefs:
        assert "#" not in href and "?" not in href, href
        assert (out / unquote(href)).is_file(), href


# 6. the full-resolution viewer


def test_the_viewer_centres_the_image_safely_under_an_opaque_bar():
    viewer = re.search(r"#viewer \{([^}]*)\}", CSS).group(1)
    assert "align-items: center" not in viewer
    assert re.search(r"#viewer \.holder \{[^}]*margin: 0 auto", CSS)
    bar = re.search(r"#viewer \.bar \{([^}]*)\}", CSS).group(1)
    assert re.search(r"background: #[0-9a-f]{6};", bar)


# 7. AoLP preview


def test_the_aolp_preview_is_cyclic():
    rgb, span = map_preview("AoLP", np.array([[0.0, 0.5, 90.0, 179.5, np.nan]], np.float32))
    near_zero, near_180, right_angle = (rgb[0, k].astype(int) for k in (0, 3, 2))
    assert np.abs(near_zero - near_180).max() <= 8 and np.abs(near_zero - right_angle).max() > 100
    assert rgb[0, 4].tolist() == [0, 0, 0] and "hue" in span


# 8. scenes captured before the current calibration


def test_a_scene_captured_with_another_offset_is_flagged(dataset):
    scene = Dataset.open(dataset).scene("scene_01")
    stale = OffsetCalibration(2.5, 0.2, None, 0.0, "t", None, 0)
    note = ("its shots were taken with the polarizer offset 0.000° while the dataset's calibration says "
            "2.500° ± 0.200°, so its angles are off by +2.500°")
    assert note in scene_view(scene, calibration=stale).notes
    close = OffsetCalibration(0.1, 0.2, None, 0.0, "t", None, 0)
    assert not [n for n in scene_view(scene, calibration=close).notes if "polarizer offset" in n]
    other = OffsetCalibration(2.5, 0.2, None, 0.0, "t", None, 0, {"kind": "ELL14 simulator", "sim_offset_deg": 8.0})
    assert not [n for n in scene_view(scene, calibration=other).notes if "polarizer offset" in n]   # another stage's


def test_the_report_flags_scenes_captured_before_the_calibration(dataset, tmp_path):
    ds = Dataset.open(shutil.copytree(dataset, tmp_path / "ds"))
    ds.save_calibration({"offset_deg": 4.0, "uncertainty_deg": 0.3}, 0.0,
                        ds.new_sweep({"angles_deg": [0.0, 90.0], "offset_deg": 0.0, "tolerance_deg": 0.5}))
    page = _page(report_html(ds.root, tmp_path / "r"))
    note = "while the dataset&#x27;s calibration says 4.000° ± 0.300°, so its angles are off by +4.000°"
    assert page.count(note) == 2              # scene_03, planned without the rig, records no stage: no offset to compare


# 9. wording


def test_the_calibration_residual_keeps_its_significant_digits(tmp_path):
    grid = [0.0, 90.0]
    cal = CalibrationView([], [], grid, [0.0, 1.0], 10.0, 0.5, residual_rms=3.83e-05)
    page = _page(write_html_report([], tmp_path / "r", "t", calibration=cal))
    assert "<dd>3.83e-05 (0.0038% of the modulation)</dd>" in page


def test_an_empty_dataset_says_no_scenes_yet(tmp_path):
    page = _page(write_html_report([], tmp_path / "r", "t"))
    assert "no scenes yet" in page and "<table>" not in page


def test_a_wrapping_reference_field_is_labelled_mod_180(tmp_path):
    field = np.linspace(139.1, 185.6, 24 * 32, dtype=np.float32).reshape(24, 32)
    result = ResultView("m", _shot(0.1), _shot(0.15), {}, reference_field=field)
    page = _page(write_html_report([SceneView("s", "separated", [], None, None, [result], [])], tmp_path / "r", "t"))
    ticks = re.search(r'aria-label="φ⊥[^"]*".*?<div class="ticks">(.*?)</div>', page).group(1)
    assert re.findall(r"<span>(.*?)</span>", ticks) == ["139.1°", "φ⊥, wraps at 180°", "5.6°"]


def test_a_scene_ingested_from_raw_files_gets_no_offset_note(dataset, tmp_path):
    ds = Dataset.open(shutil.copytree(dataset, tmp_path / "ds"))
    scene = ds.scene("scene_01")
    record = scene.load(verify=False)
    del record["capture"]["stage"]                        # as `urd ingest RAW_FOLDER` records it: the angles it was given
    (scene.path / "scene.json").write_text(json.dumps(record))
    stale = OffsetCalibration(2.5, 0.2, None, 0.0, "t", None, 0)
    assert not [n for n in scene_view(Scene(scene.path), calibration=stale).notes if "polarizer offset" in n]


def test_the_report_holds_one_scenes_views_at_a_time(tmp_path):
    """A dataset's report makes each scene's view when it writes it and lets it go: its memory
    does not grow with the number of scenes (12 scenes of 1536×1024: 2.0 → 0.46 GB peak)."""
    import gc
    import weakref
    from collections.abc import Sequence

    made, alive = [], []

    class Views(Sequence):
        def __len__(self):
            return 4

        def __getitem__(self, index):
            if not 0 <= index < len(self):
                raise IndexError(index)
            gc.collect()
            alive.append(sum(ref() is not None for ref in made))
            view = _view(f"scene_{index + 1:02d}", "ingested", shots=3)
            made.append(weakref.ref(view))
            return view

    write_html_report(Views(), tmp_path / "r", "t")
    assert alive == [0, 0, 0, 0]                          # the views made before are gone
    assert _page(tmp_path / "r" / "index.html").count('<section class="card scene"') == 4


def test_map_previews_say_their_ranges_units():
    values = np.linspace(0.0, 2.0, 64, dtype=np.float32).reshape(8, 8)
    assert map_preview("phi_perp", values)[1].endswith(" deg") and map_preview("theta", values)[1].endswith(" deg")
    assert map_preview("S0", values)[1].endswith("(linear, 1.0 = sensor white)")
    assert map_preview("AoLP", values)[1] == "0 to 180 deg as hue, cyclic"
