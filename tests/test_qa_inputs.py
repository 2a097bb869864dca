"""Image files as users bring them to `urd separate --images`: planar and multi-page TIFFs, EXIF
orientation, float files from another black level, the same file twice, JPEGs' transfer, and the
checks that come before any work (the angles' span for the network, --out naming a file)."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from separate import optics
from separate.reference import inspect_stack
from urd.cli import app
from urd.core.errors import RawFormatError
from urd.core.images import exif_orientation, read_image, read_raw_codes


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def polarized_stack(h: int = 96, w: int = 128, dolp: float = 0.05, aolp_deg: float = 30.0, angles=(0, 45, 90)) -> np.ndarray:
    """Shots (N, H, W, 3) of a blocky scene whose light is weakly polarized along one angle."""
    rng = np.random.default_rng(0)
    s0 = np.repeat(np.repeat(0.3 + 0.4 * rng.random((h // 8, w // 8, 3)), 8, 0), 8, 1).astype(np.float32)
    aolp = np.radians(aolp_deg)
    stokes = np.stack([s0, s0 * dolp * np.cos(2 * aolp), s0 * dolp * np.sin(2 * aolp)])
    return np.stack([optics.intensity_from_stokes(stokes, np.radians(a)) for a in angles]).astype(np.float32)


def with_orientation(jpeg: bytes, orientation: int) -> bytes:
    """A JPEG with an EXIF block (little-endian TIFF header, one IFD entry) holding ``orientation``."""
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + b"\x00" * 4
    app1 = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpeg[2:]


def write_shots(folder: Path, stack: np.ndarray, suffix: str = ".png") -> list[Path]:
    paths = []
    for k, shot in enumerate(stack):
        path = folder / f"shot_{k}{suffix}"
        cv2.imwrite(str(path), np.rint(np.clip(shot, 0, 1) * 65535).astype(np.uint16)[..., ::-1])
        paths.append(path)
    return paths


def test_a_planar_tiff_reads_as_the_same_pixels_as_an_interleaved_one(tmp_path):
    rgb = (np.random.default_rng(1).random((20, 30, 3)) * 60000).astype(np.uint16)
    tifffile.imwrite(tmp_path / "chunky.tiff", rgb, photometric="rgb")
    tifffile.imwrite(tmp_path / "planar.tiff", np.moveaxis(rgb, -1, 0).copy(), planarconfig="separate", photometric="rgb")
    assert np.array_equal(read_raw_codes(tmp_path / "planar.tiff"), rgb)
    assert np.array_equal(read_image(tmp_path / "planar.tiff"), read_image(tmp_path / "chunky.tiff"))


def test_a_tiff_of_several_images_is_refused_naming_the_file(tmp_path):
    with tifffile.TiffWriter(tmp_path / "pages.tiff") as tif:
        for _ in range(3):
            tif.write(np.zeros((20, 30), np.uint16))
    with pytest.raises(RawFormatError, match=r"pages\.tiff: a TIFF of 3 images \(pages\); give one image per file"):
        read_image(tmp_path / "pages.tiff")


def test_exif_orientation_is_read_from_jpegs_and_named_but_not_applied(tmp_path):
    stack = polarized_stack(96, 128, dolp=0.3)
    paths = []
    for k, shot in enumerate(stack):
        ok, jpeg = cv2.imencode(".jpg", np.rint(np.clip(shot, 0, 1) * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 98])
        paths.append(tmp_path / f"turned_{k}.jpg")
        paths[-1].write_bytes(with_orientation(jpeg.tobytes(), 6))
    assert [exif_orientation(p) for p in paths] == [6, 6, 6]
    assert read_image(paths[0]).shape == (96, 128, 3)                   # as stored, not turned
    out = invoke("separate", "--images", paths[0], "--images", paths[1], "--images", paths[2], "--method", "schechner",
                 "--transfer", "srgb", "--out", tmp_path / "out")
    assert out.exit_code == 0, out.output
    assert "turned_0.jpg, turned_1.jpg, turned_2.jpg: EXIF asks viewers to show them turned 90° clockwise" in out.output
    assert "are read as linear" not in out.output                    # --transfer given
    assert tifffile.imread(tmp_path / "out" / "T.tiff").shape[:2] == (96, 128)

    plain = tmp_path / "plain.jpg"
    plain.write_bytes(cv2.imencode(".jpg", np.zeros((128, 96, 3), np.uint8))[1].tobytes())
    assert exif_orientation(plain) == 1
    out = invoke("separate", "--images", paths[0], "--images", paths[1], "--images", plain, "--method", "schechner",
                 "--out", tmp_path / "mixed")
    assert out.exit_code == 1
    assert "as stored; viewers show turned_0.jpg turned 90° clockwise" in out.output
    assert "8-bit images (turned_0.jpg, turned_1.jpg, plain.jpg) are read as linear sensor codes" in out.output


def test_a_float_file_measured_from_another_black_level_is_refused(tmp_path):
    shot = np.random.default_rng(2).random((20, 30, 3)).astype(np.float32) - 0.3
    tifffile.imwrite(tmp_path / "offset.tiff", shot, photometric="rgb")
    with pytest.raises(RawFormatError, match=r"offset\.tiff: float pixels are read with 0\.0 as black, and .* lie below -0\.05"):
        read_image(tmp_path / "offset.tiff")
    tifffile.imwrite(tmp_path / "noisy.tiff", np.clip(shot + 0.3, 0, 1) - 0.01, photometric="rgb")   # noise around black passes
    assert read_image(tmp_path / "noisy.tiff").min() < 0


def test_the_same_image_twice_is_refused_before_anything_is_written(tmp_path):
    paths = write_shots(tmp_path, polarized_stack(dolp=0.3))
    out = invoke("separate", "--images", paths[0], "--images", paths[0], "--images", paths[2], "--method", "schechner",
                 "--out", tmp_path / "out")
    assert out.exit_code == 1
    assert "shot_0.png and shot_0.png hold the same image: each polarizer angle needs its own shot" in out.output
    assert not (tmp_path / "out").exists()


def test_angles_the_network_cannot_take_and_an_out_that_is_a_file_are_usage_errors(tmp_path):
    paths = write_shots(tmp_path, polarized_stack(angles=(0, 10, 20)))
    images = [arg for p in paths for arg in ("--images", p)]
    out = invoke("separate", *images, "--angles", "0,10,20", "--out", tmp_path / "out")
    assert out.exit_code == 2
    assert "Invalid value for '--angles'" in out.output and "spanning at least 70 deg" in out.output
    (tmp_path / "afile").write_text("notes")
    out = invoke("separate", *images, "--angles", "0,45,90", "--method", "schechner", "--out", tmp_path / "afile")
    assert out.exit_code == 2 and "afile is a file, not a folder" in out.output
    assert (tmp_path / "afile").read_text() == "notes"


def test_a_given_reference_silences_the_warning_about_the_estimated_one():
    stack = polarized_stack()
    assert any("urd assumes the transmission dominates" in w for w in inspect_stack(stack, [0, 45, 90]).warnings)
    assert not any("urd assumes" in w for w in inspect_stack(stack, [0, 45, 90], 40.0).warnings)


def test_a_file_where_a_scenes_results_go_is_refused_before_the_separation_runs(tmp_path_factory, monkeypatch):
    import urd.separation
    from conftest import ingested_dataset

    root = ingested_dataset(tmp_path_factory, "results-file")
    (root / "scene_01" / "results").write_text("notes")
    monkeypatch.setattr(urd.separation, "separate_inspected", lambda *a, **k: pytest.fail("separated before the check"))
    out = invoke("separate", "scene_01", "--dataset", root, "--method", "schechner")
    assert out.exit_code == 1
    assert "results is a file, not a folder; scene_01's schechner results go there" in out.output
    assert (root / "scene_01" / "results").read_text() == "notes"


@pytest.mark.parametrize("option", [("--angles", "0,60,120"), ("--gap", "5"), ("--motion", "translation")])
def test_raw_only_options_with_mosaic_frames_are_usage_errors(tmp_path, option):
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "f.png"), np.zeros((64, 64), np.uint8))
    out = invoke("ingest", tmp_path / "frames", tmp_path / "ds", "--mosaic", "imx250mzr", *option)
    assert out.exit_code == 2 and f"{option[0]}: for RAW shots" in out.output
    assert not (tmp_path / "ds").exists()


def test_a_scene_whose_aligned_shots_are_gone_says_how_to_make_them_again(tmp_path_factory):
    import shutil

    from conftest import ingested_dataset

    root = ingested_dataset(tmp_path_factory, "aligned-gone")
    shutil.rmtree(root / "scene_01" / "aligned")
    out = invoke("separate", "scene_01", "--dataset", root, "--method", "schechner")
    assert out.exit_code == 1
    assert "listed in the manifest but missing" in out.output and f"urd ingest {root / 'scene_01'} --redo" in " ".join(out.output.split())


def test_shots_mixing_grey_and_colour_are_refused_and_8_bit_pngs_are_named_in_the_transfer_warning(tmp_path):
    paths = write_shots(tmp_path, polarized_stack())
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.rint(polarized_stack()[2].mean(-1) * 65535).astype(np.uint16))
    out = invoke("separate", "--images", paths[0], "--images", paths[1], "--images", grey, "--angles", "0,45,90",
                 "--method", "schechner", "--out", tmp_path / "mixed")
    assert out.exit_code == 1 and "all grey or all colour, got grey grey.png and colour shot_0.png, shot_1.png" in out.stderr
    assert not (tmp_path / "mixed").exists()
    eight = []
    for k, shot in enumerate(polarized_stack()):
        eight.append(tmp_path / f"e{k}.png")
        cv2.imwrite(str(eight[-1]), np.rint(shot * 255).astype(np.uint8)[..., ::-1])
    args = [a for p in eight for a in ("--images", p)] + ["--angles", "0,45,90", "--method", "schechner"]
    out = invoke("separate", *args, "--out", tmp_path / "e")
    assert out.exit_code == 0 and "8-bit images (e0.png, e1.png, e2.png) are read as linear sensor codes" in out.stderr
    out = invoke("separate", *args, "--out", tmp_path / "s", "--transfer", "srgb")
    assert out.exit_code == 0 and "8-bit images" not in out.stderr
    out = invoke("separate", *[a for p in paths for a in ("--images", p)], "--angles", "0,45,90", "--method", "schechner",
                 "--out", tmp_path / "sixteen")
    assert out.exit_code == 0 and "8-bit images" not in out.stderr


def test_a_folder_of_jpegs_is_pointed_to_separate_images(tmp_path):
    (tmp_path / "jpegs").mkdir()
    cv2.imwrite(str(tmp_path / "jpegs" / "a.jpg"), np.zeros((64, 64, 3), np.uint8))
    out = invoke("ingest", tmp_path / "jpegs", tmp_path / "ds")
    assert out.exit_code == 1 and "it holds 1 PNG/TIFF/JPEG images" in out.stderr and "urd separate --images" in out.stderr
