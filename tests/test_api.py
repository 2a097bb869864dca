"""The Python API (`urd.api`) and its example script, and the polarization maps against closed forms."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import urd
from acquire.virtual_camera import make_glass_scene
from rig import capture_virtual
from separate import optics
from separate.maps import MAPS, polarization_maps
from urd.core.dataset import Dataset
from urd.core.errors import DatasetError
from urd.ingest import IngestOptions, ingest_scene

EXAMPLE = Path(__file__).resolve().parent.parent / "docs" / "examples" / "separate_scene.py"


@pytest.fixture(scope="module")
def ingested(tmp_path_factory):
    root = tmp_path_factory.mktemp("api") / "ds"
    ds = Dataset.open_or_create(root)
    scene, _ = capture_virtual(ds, size=(384, 256), shake_px=2.0, shake_deg=0.2)
    with scene.lock():
        ingest_scene(scene, IngestOptions())
    return root, scene.name


def test_open_separate_and_get_arrays_back(ingested):
    root, name = ingested
    images, angles = urd.open_dataset(root).scene(name).load_stack()
    layers = urd.separate(images, angles, method="schechner", reference="global")
    assert isinstance(layers, urd.Layers)
    assert layers.transmission.shape == layers.reflection.shape == images.shape[1:]
    s0 = optics.stokes_from_images(images, np.radians(angles))[0]
    both = (layers.transmission > 0) & (layers.reflection > 0)          # elsewhere a layer's negative light was clipped
    assert layers.transmission.min() >= 0 and layers.reflection.min() >= 0 and both.mean() > 0.5
    np.testing.assert_allclose((layers.transmission + layers.reflection)[both], s0[both], atol=1e-3)
    with pytest.raises(DatasetError, match="not an urd dataset"):
        urd.open_dataset(root / "nowhere")
    with pytest.raises(ValueError, match="unknown method"):
        urd.separate(images, angles, method="magic")


@pytest.mark.slow
def test_the_example_script_runs(ingested, tmp_path):
    root, name = ingested
    out = subprocess.run([sys.executable, str(EXAMPLE), str(root), name, str(tmp_path / "maps")],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "reflection holds" in out.stdout and (tmp_path / "maps" / "DoLP.tiff").is_file()


def test_maps_match_the_closed_forms():
    rng = np.random.default_rng(0)
    s0 = rng.uniform(0.1, 0.5, (32, 48, 3)).astype(np.float32)
    dolp = np.float32(0.3)
    aolp = np.radians(np.float32(70.0))
    stokes = optics.stokes_from_polarization(s0, dolp, aolp)
    angles = [0.0, 45.0, 90.0, 135.0]
    shots = np.stack([optics.intensity_from_stokes(stokes, np.radians(a)) for a in angles]).astype(np.float32)
    maps = polarization_maps(shots, angles, 20.0)
    assert set(maps) == set(MAPS)
    np.testing.assert_allclose(maps["S0"], s0, rtol=1e-5)
    np.testing.assert_allclose(maps["DoLP"], 0.3, atol=1e-5)
    np.testing.assert_allclose(maps["AoLP"], 70.0, atol=1e-3)
    np.testing.assert_allclose(maps["S1"], s0 * 0.3 * np.cos(2 * aolp), atol=1e-6)
    assert (maps["phi_perp"] == 20.0).all() and maps["theta"].shape == (32, 48)


def test_maps_of_a_glass_scene_give_the_reference_field():
    glass = make_glass_scene(192, 128, curved=False, theta_center_deg=50.0, phi_perp_deg=30.0)
    angles = [0.0, 45.0, 90.0]
    shots = np.stack([glass.render(np.radians(a)) for a in angles]).astype(np.float32)
    maps = urd.polarization_maps(shots, angles)
    truth = np.degrees(glass.phi_perp)
    assert np.abs(optics.axis_gap_deg(maps["phi_perp"], truth)).mean() < 2.0
    error = np.abs(maps["theta"] - np.degrees(glass.theta))            # θ turns across the pane, per pixel
    assert np.median(error) < 4.0 and np.ptp(np.degrees(glass.theta)) > 10.0


@pytest.mark.slow
def test_separate_scene_exports_the_maps_hashed_with_units(ingested):
    import json

    import tifffile

    from separate.methods import get_method
    from urd.separation import separate_scene

    root, name = ingested
    scene = Dataset.open(root).scene(name)
    run, info = get_method("schechner")
    result = separate_scene(scene, "schechner", run, info, maps=True)
    names = {p.name for p in result.files}
    assert {"S0.tiff", "DoLP.tiff", "AoLP.tiff", "phi_perp.tiff", "theta.tiff", "reference_deg.tiff"} <= names
    with tifffile.TiffFile(scene.results_dir("schechner") / "maps" / "AoLP.tiff") as tif:
        meta = json.loads(tif.pages[0].description)
        aolp = tif.asarray()
    assert meta["unit"].startswith("deg") and "counter-clockwise" in meta["angle_convention"]
    with tifffile.TiffFile(scene.results_dir("schechner") / "maps" / "theta.tiff") as tif:
        assert "angle_convention" not in json.loads(tif.pages[0].description)    # an angle of incidence, not in the image
    assert aolp.dtype == np.float32 and 0.0 <= np.nanmin(aolp) and np.nanmax(aolp) < 180.0
    assert Dataset.open(root).scene(name).verify() == []
    (scene.results_dir("schechner") / "maps" / "DoLP.tiff").write_bytes(b"broken")
    assert any("DoLP.tiff" in problem for problem in Dataset.open(root).scene(name).verify())
    separate_scene(Dataset.open(root).scene(name), "schechner", run, info, force=True, maps=True)
    assert Dataset.open(root).scene(name).verify() == []
    separate_scene(Dataset.open(root).scene(name), "schechner", run, info, force=True)     # no maps this time
    assert not (scene.results_dir("schechner") / "maps").exists()


def test_reports_show_the_ground_truth_figures_the_reference_field_and_the_map_links(ingested, tmp_path):
    from separate.methods import get_method
    from urd.report import report_html, report_text
    from urd.separation import separate_scene

    root, name = ingested
    scene = Dataset.open(root).scene(name)
    if "none" not in scene.methods():
        separate_scene(scene, "none", *get_method("none"))
    if not (scene.results_dir("schechner") / "maps" / "AoLP.tiff").is_file():      # the test above leaves them
        separate_scene(scene, "schechner", *get_method("schechner"), force=True, maps=True)
    text = report_text(root)
    assert "none vs ground truth: R̂" in text and "T̂ " in text and "no separation (S0 as T)" in text
    page = report_html(root, tmp_path / "report").read_text()
    assert "vs ground truth: R̂" in page and "reference φ⊥ used" in page
    assert 'href="' in page and "maps/AoLP.tiff" in page      # the exported maps of the schechner result
