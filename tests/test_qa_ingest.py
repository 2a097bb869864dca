"""Ingest refuses or warns about what the separation cannot use: shots of one scene taken at
different exposures or with different cameras, a scene whose aligned stack is gone, mosaic
frames too small to separate, --half-size with --mosaic, and lossy (JPEG) mosaic frames."""

import inspect
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from rig import capture_virtual
from urd.cli import app
from urd.cli.ingest import ingest
from urd.core import raw as rawio
from urd.core.dataset import Dataset
from urd.core.files import write_json_atomic
from urd.ingest import IngestOptions, ingest_scene, ingest_scenes

EXPOSURE_WARNING = ("warning: scene_01: the shots' exposure times differ (0.01, 0.01, 0.04 s): auto-exposure? the "
                    "separation assumes one exposure; set the camera to manual\n")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture
def raw_folder(tmp_path):
    """Three shots of one small virtual scene, copied into a folder of RAW files."""
    scene, _ = capture_virtual(Dataset.open_or_create(tmp_path / "cap"), size=(96, 64), shake_px=0, shake_deg=0)
    folder = tmp_path / "raw"
    folder.mkdir()
    for i, path in enumerate(scene.raw_paths()):
        shutil.copyfile(path, folder / f"x{i}.dng")
    return folder


def patch_metadata(monkeypatch, **fields):
    """Make `urd.core.raw.metadata` report ``fields`` (name → one value per file x0, x1, x2)."""
    real = rawio.metadata

    def metadata(path):
        meta = real(path)
        index = int(Path(path).stem[-1])
        return {**meta, **{key: values[index] for key, values in fields.items()}}

    monkeypatch.setattr(rawio, "metadata", metadata)


def test_shots_at_different_exposures_are_ingested_with_one_warning_naming_them(tmp_path, raw_folder, monkeypatch):
    patch_metadata(monkeypatch, exposure_s=[0.01, 0.01, 0.04], iso=[100.0, 100.0, 100.0])
    out = invoke("ingest", raw_folder, tmp_path / "ds")
    assert out.exit_code == 0 and "ingested scene_01" in out.stdout, out.output
    assert out.stderr.count("warning:") == 1 and EXPOSURE_WARNING in out.stderr
    shots = Dataset.open(tmp_path / "ds").scene("scene_01").shots()
    assert [s.camera["exposure_s"] for s in shots] == [0.01, 0.01, 0.04]


def test_every_differing_setting_is_named_in_the_one_line(tmp_path, raw_folder, monkeypatch):
    patch_metadata(monkeypatch, exposure_s=[0.01, 0.01, 0.01], iso=[100.0, 400.0, None], aperture=[4.0, 4.0, 5.6])
    out = invoke("ingest", raw_folder, tmp_path / "ds")
    assert out.exit_code == 0 and out.stderr.count("warning:") == 1, out.output
    assert ("scene_01: the shots' ISO speeds differ (100, 400, ?) and apertures differ (f/4, f/4, f/5.6): "
            "auto-exposure?") in out.stderr


def test_shots_of_two_camera_models_are_refused_and_nothing_is_ingested(tmp_path, raw_folder, monkeypatch):
    patch_metadata(monkeypatch, model=["Canon EOS Kiss X4", "Canon EOS Kiss X4", "Canon EOS Kiss X5"])
    out = invoke("ingest", raw_folder, tmp_path / "ds")
    assert out.exit_code == 1, out.output
    assert ("FAILED x0.dng, x1.dng, x2.dng: the shots come from different cameras (Canon EOS Kiss X4, Canon EOS Kiss X4, "
            "Canon EOS Kiss X5)") in out.stderr
    assert not (tmp_path / "ds").exists()


def recorded_cameras(scene, **fields):
    """Set the camera metadata the manifest records for each shot (name → one value per shot)."""
    record = scene.load()
    for i, shot in enumerate(record["shots"]):
        shot["camera"].update({key: values[i] for key, values in fields.items()})
    write_json_atomic(scene.manifest_path, record)
    return scene.reload()


def test_a_captured_scene_is_checked_from_its_manifest_with_one_process_or_several(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    auto, _ = capture_virtual(ds, size=(96, 64), shake_px=0, shake_deg=0, seed=1)
    mixed, _ = capture_virtual(ds, size=(96, 64), shake_px=0, shake_deg=0, seed=2)
    recorded_cameras(auto, exposure_s=[0.01, 0.01, 0.04])
    recorded_cameras(mixed, model=["EOS Kiss X4", "EOS Kiss X4", "EOS Kiss X5"])
    outcome = ingest_scene(auto, IngestOptions())
    assert outcome.state == "ingested" and outcome.notes == [EXPOSURE_WARNING.removeprefix("warning: ").strip()]
    refused = ingest_scenes([mixed], IngestOptions(), jobs=2)
    assert [(o.state, o.error.split(":")[0]) for o in refused] == [("failed", "the shots come from different cameras (EOS Kiss X4, EOS Kiss X4, EOS Kiss X5)")]
    assert not mixed.reload().is_ingested()


def test_a_scene_whose_aligned_shots_are_gone_is_not_called_already_ingested(tmp_path):
    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=(96, 64), shake_px=0, shake_deg=0)
    assert invoke("ingest", tmp_path / "ds").exit_code == 0
    shutil.rmtree(scene.path / "aligned")
    out = invoke("ingest", tmp_path / "ds")
    assert out.exit_code == 1 and "already ingested" not in out.output, out.output
    assert (f"FAILED scene_01: ingested, but its aligned shots are missing or changed (aligned/shot_00.tiff, "
            f"aligned/shot_01.tiff, aligned/shot_02.tiff); decode and align it again with: urd ingest "
            f"{scene.path.resolve()} --redo") in out.stderr
    assert scene.reload().is_ingested()                                 # nothing was changed
    out = invoke("ingest", scene.path.resolve(), "--redo")
    assert out.exit_code == 0 and scene.reload().verify() == []


def write_frame(folder: Path, name: str, frame: np.ndarray, *params: int) -> Path:
    folder.mkdir(exist_ok=True)
    assert cv2.imwrite(str(folder / name), frame, list(params))
    return folder


def test_a_tiff_image_saved_under_a_raw_name_is_refused_not_demosaiced(tmp_path):
    """LibRaw reads any 16-bit TIFF as a Bayer frame with an invented white balance: a grey image
    (a polarization camera's frame, say) renamed .dng would be ingested as a colour photo."""
    import tifffile

    folder = tmp_path / "raw"
    folder.mkdir()
    for k in range(3):
        tifffile.imwrite(folder / f"IMG_{k}.dng", (np.random.default_rng(k).random((64, 96)) * 65535).astype(np.uint16))
    out = CliRunner().invoke(app, ["ingest", str(folder), str(tmp_path / "ds")])
    assert out.exit_code == 1 and "IMG_0.dng is unreadable (not a camera RAW file: no camera, white balance" in out.output
    assert "ingested with --mosaic" in out.output and not (tmp_path / "ds" / "scene_01").exists()
    rawio.decode(capture_virtual(Dataset.open_or_create(tmp_path / "cap"), size=(96, 64))[0].raw_paths()[0])


def test_a_mosaic_frame_too_small_to_separate_is_refused(tmp_path):
    frames = write_frame(tmp_path / "tiny", "t.png", np.full((2, 2), 30000, np.uint16))
    out = invoke("ingest", frames, tmp_path / "ds", "--mosaic", "imx250mzr")
    assert out.exit_code == 1, out.output
    assert "t.png: the 2×2 px frame gives 1×1 px images (one pixel per 2×2 polarizer cell), too small to separate" in out.stderr
    assert not (tmp_path / "ds").exists()
    frames = write_frame(tmp_path / "small", "s.png", np.full((4, 4), 30000, np.uint16))     # 2×2 px: the smallest
    assert invoke("ingest", frames, tmp_path / "ds", "--mosaic", "imx250mzr").exit_code == 0


@pytest.mark.parametrize("flag", ["--half-size", "--no-half-size"])
def test_half_size_with_mosaic_is_a_usage_error(tmp_path, flag):
    frames = write_frame(tmp_path / "frames", "f.png", np.full((8, 8), 30000, np.uint16))
    out = invoke("ingest", frames, tmp_path / "ds", "--mosaic", "imx250mzr", flag)
    assert out.exit_code == 2 and f"{flag}: for RAW shots; --mosaic frames are always demosaiced at half size" in out.stderr
    assert not (tmp_path / "ds").exists()
    assert "demosaiced at half size" in inspect.signature(ingest).parameters["mosaic"].default.help


def test_jpeg_mosaic_frames_are_ingested_with_one_warning(tmp_path):
    frame = np.random.default_rng(0).integers(20, 230, (16, 16), dtype=np.uint8)
    frames = write_frame(tmp_path / "frames", "a.jpg", frame, cv2.IMWRITE_JPEG_QUALITY, 90)
    write_frame(frames, "b.jpeg", frame[::-1], cv2.IMWRITE_JPEG_QUALITY, 90)
    write_frame(frames, "c.png", frame[:, ::-1])
    out = invoke("ingest", frames, tmp_path / "ds", "--mosaic", "imx250mzr")
    assert out.exit_code == 0 and out.stdout.count("ingested scene_") == 3, out.output
    assert out.stderr.count("warning:") == 1
    assert ("warning: 2 frames (a.jpg … b.jpeg): JPEG compression is lossy and mixes neighbouring pixels, which sit "
            "behind different polarizers") in out.stderr


def test_exposure_settings_the_exif_records_as_unknown_are_none_not_libraws_placeholders():
    from conftest import shared_data
    from urd.core.raw import metadata

    record = metadata(shared_data("raw", "canon_eos550d_magiclantern_colorchart.dng"))   # ExposureTime 0/1e6, FNumber 0/10
    assert record["exposure_s"] is None and record["aperture"] is None and record["model"] == "Canon EOS Kiss X4"
