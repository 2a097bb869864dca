"""One transfer rule for image files (`urd.core.images`): 8-bit codes follow --transfer, 16-bit and
float files are linear, for `ingest --mosaic` and `separate --images` alike."""

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
import tifffile

from urd.core.dataset import Dataset
from urd.core.errors import RawFormatError
from urd.core.images import (
    Transfer,
    codes_to_linear,
    U16_BLOCK,
    linear_to_u16,
    read_image,
    read_raw_codes,
    srgb_encode,
    srgb_to_linear,
    stored_bits,
    to_display,
    to_linear,
    u16_to_linear,
)
from urd.core.mosaic import ANGLES_DEG, MosaicLayout, build_mosaic

SITE_CODES = (40, 128, 200, 90)          # 8-bit codes at 0/45/90/135°


def srgb_decoded(code: float) -> float:
    """IEC 61966-2-1 by hand, for one 8-bit code."""
    v = code / 255
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def test_integer_codes_follow_the_transfer_and_float_stays_linear():
    u8 = np.array([0, 10, 128, 255], np.uint8)
    np.testing.assert_allclose(to_linear(u8), u8 / 255, rtol=1e-6)
    np.testing.assert_allclose(to_linear(u8, Transfer.SRGB), [srgb_decoded(c) for c in u8], rtol=1e-5)
    assert to_linear(u8, Transfer.SRGB)[2] == pytest.approx(0.21586, abs=1e-5)      # sRGB mid-grey
    u16 = np.array([0, 32768, 65535], np.uint16)
    np.testing.assert_array_equal(to_linear(u16), u16 / np.float32(65535))
    np.testing.assert_allclose(to_linear(u16, Transfer.SRGB), [0.0, srgb_decoded(127.5), 1.0], rtol=1e-4)   # an editor's 16-bit export
    floats = np.array([0.25] * 39 + [1.5], np.float32)               # a highlight above white stays
    np.testing.assert_array_equal(to_linear(floats, Transfer.SRGB), floats)
    with pytest.raises(RawFormatError, match="int32"):
        to_linear(np.array([1], np.int32))


def test_interpolated_codes_follow_their_frames_rule_clipped_to_the_codes_range():
    codes = np.array([-3.0, 127.5, 300.0])
    np.testing.assert_allclose(codes_to_linear(codes, np.uint8, Transfer.SRGB),
                               [0.0, srgb_decoded(127.5), 1.0], rtol=1e-5)
    np.testing.assert_allclose(codes_to_linear(codes, np.uint16), [0.0, 127.5 / 65535, 300 / 65535], rtol=1e-6)
    with pytest.raises(RawFormatError, match="float32"):
        codes_to_linear(codes, np.float32)


def test_separate_images_reads_8_bit_files_by_the_transfer(tmp_path):
    path = tmp_path / "shot.png"
    cv2.imwrite(str(path), np.full((4, 6, 3), 128, np.uint8))
    assert read_image(path).shape == (4, 6, 3)
    np.testing.assert_allclose(read_image(path), 128 / 255, rtol=1e-6)
    np.testing.assert_allclose(read_image(path, Transfer.SRGB), srgb_decoded(128), rtol=1e-5)


@pytest.mark.parametrize("transfer", list(Transfer))
def test_ingest_mosaic_of_an_8_bit_frame_follows_the_transfer_end_to_end(tmp_path, transfer):
    flat = np.stack([np.full((16, 24, 1), code, np.uint8) for code in SITE_CODES])
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), build_mosaic(flat, MosaicLayout.IMX250MZR))
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1"}
    out = subprocess.run([sys.executable, "-m", "urd.cli", "ingest", str(frame), str(tmp_path / "ds"), "--mosaic", "imx250mzr",
                          "--demosaic", "bilinear", "--transfer", transfer.value],
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    scene = Dataset.open(tmp_path / "ds").scene("scene_01")
    stack, angles = scene.load_stack()
    assert angles == list(ANGLES_DEG)
    decode = srgb_decoded if transfer is Transfer.SRGB else (lambda code: code / 255)
    for shot, code in zip(stack, SITE_CODES):
        np.testing.assert_allclose(shot, decode(code), atol=1.0 / 65535)        # 16-bit aligned TIFFs
    manifest = json.loads(scene.manifest_path.read_text())
    assert f'"transfer": "{transfer.value}"' in json.dumps(manifest)


def test_display_encoding_inverts_the_srgb_decoding_and_clips():
    codes = np.arange(256, dtype=np.uint8)
    np.testing.assert_array_equal(np.rint(srgb_encode(srgb_to_linear(codes / 255.0)) * 255), codes)
    grey = np.array([[0.5, 2.0, np.nan]], np.float32)
    shown = to_display(grey, gain=1.0)
    assert shown.shape == (1, 3, 3) and shown.dtype == np.uint8
    np.testing.assert_array_equal(shown[0, :, 0], [188, 255, 0])      # sRGB of linear 0.5 is 0.7354
    np.testing.assert_array_equal(to_display(grey[..., None], gain=0.25)[0, 1], [188, 188, 188])   # 2.0 × 0.25



def test_display_encoding_in_blocks_gives_the_codes_of_the_whole_image_at_once():
    rng = np.random.default_rng(3)
    image = rng.uniform(-0.1, 1.3, (301, 257, 3)).astype(np.float32)      # 3.5 blocks of U16_BLOCK values
    image.flat[::911], image.flat[::1237] = np.nan, np.inf
    for gain in (1.0, 0.7351):
        whole = np.rint(srgb_encode(image * np.float32(gain)) * 255.0).astype(np.uint8)
        np.testing.assert_array_equal(to_display(image, gain), whole)
    grey = image[::-1, :, :1]                                                # strided, one channel
    np.testing.assert_array_equal(to_display(grey), np.rint(srgb_encode(np.repeat(grey, 3, axis=-1)) * 255.0).astype(np.uint8))

@pytest.mark.parametrize("full_scale", [1.0, 2.0])
def test_16_bit_codes_of_linear_tiffs_round_trip_within_half_a_code(full_scale):
    x = np.linspace(-0.1, 1.1 * full_scale, 1001, dtype=np.float32)
    codes = linear_to_u16(x, full_scale)
    assert codes.dtype == np.uint16 and codes[0] == 0 and codes[-1] == 65535          # clipped
    assert linear_to_u16(np.float32(full_scale), full_scale) == 65535
    inside = (x >= 0) & (x <= full_scale)
    back = u16_to_linear(codes, full_scale)
    assert back.dtype == np.float32
    np.testing.assert_array_less(np.abs(back - x)[inside], 0.5 * full_scale / 65535 + 1e-7)
    out = np.empty_like(back)
    assert u16_to_linear(codes, full_scale, out=out) is out
    image = np.random.default_rng(1).uniform(-0.1, 1.1 * full_scale, (3, U16_BLOCK + 7, 3)).astype(np.float32)
    expected = np.clip(np.rint(image.astype(np.float64) * (65535.0 / full_scale)), 0, 65535).astype(np.uint16)
    assert np.abs(linear_to_u16(image, full_scale).astype(np.int32) - expected).max() <= 1     # across the blocks


def test_tiffs_of_other_colour_models_and_huge_headers_are_refused_in_one_line(tmp_path):
    rgb = np.zeros((8, 8, 3), np.uint8)
    tifffile.imwrite(tmp_path / "cmyk.tif", np.zeros((8, 8, 4), np.uint8), photometric="separated")
    tifffile.imwrite(tmp_path / "palette.tif", np.zeros((8, 8), np.uint8), photometric="palette",
                     colormap=np.zeros((3, 256), np.uint16))
    tifffile.imwrite(tmp_path / "two.tif", np.zeros((8, 8, 2), np.uint16), photometric="minisblack", planarconfig="contig")
    tifffile.imwrite(tmp_path / "rgb.tif", rgb)
    for name, message in (("cmyk.tif", "a CMYK TIFF"), ("palette.tif", "a palette TIFF"), ("two.tif", "2 samples per pixel")):
        with pytest.raises(RawFormatError, match=message):
            read_raw_codes(tmp_path / name)
    assert read_raw_codes(tmp_path / "rgb.tif").shape == (8, 8, 3)
    png = bytearray(cv2.imencode(".png", rgb)[1].tobytes())
    png[16:24] = (100000).to_bytes(4, "big") * 2                       # a header claiming 100000 × 100000 px
    (tmp_path / "huge.png").write_bytes(bytes(png))
    with pytest.raises(RawFormatError, match="huge.png: not an image file urd can read"):
        read_raw_codes(tmp_path / "huge.png")
    assert stored_bits(tmp_path / "rgb.tif") == 8 and stored_bits(tmp_path / "huge.png") == 8
    tifffile.imwrite(tmp_path / "deep.tif", np.zeros((8, 8), np.uint16))
    assert stored_bits(tmp_path / "deep.tif") == 16 and stored_bits(tmp_path / "cmyk.tif") == 8


def test_a_compressed_tiff_announcing_more_pixels_than_memory_holds_is_refused_before_decoding(tmp_path, monkeypatch):
    import urd.core.images as images

    tifffile.imwrite(tmp_path / "flat.tif", np.zeros((600, 800, 3), np.uint16), photometric="rgb", compression="zlib")
    assert (tmp_path / "flat.tif").stat().st_size < 100_000                  # 2.9 MB of pixels in a small file
    monkeypatch.setattr(images, "available_memory", lambda: 2_000_000)
    with pytest.raises(RawFormatError, match=r"flat.tif: its header announces 0.0 GiB of pixels, more than"):
        read_raw_codes(tmp_path / "flat.tif")
    monkeypatch.setattr(images, "available_memory", lambda: 3_000_000)
    assert read_raw_codes(tmp_path / "flat.tif").shape == (600, 800, 3)


def test_a_stored_tiff_with_an_unknown_compression_code_is_refused_as_not_urds(tmp_path):
    from urd.core.errors import DatasetError
    from urd.core.images import read_stored_tiff

    path = tmp_path / "R.tiff"
    tifffile.imwrite(path, np.zeros((8, 8, 3), np.uint16), photometric="rgb")
    assert read_stored_tiff(path).shape == (8, 8, 3)
    with tifffile.TiffFile(path) as tif:
        offset = tif.pages[0].tags["Compression"].valueoffset
    data = bytearray(path.read_bytes())
    data[offset:offset + 2] = (54321).to_bytes(2, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="not an image as urd writes them .*compression 54321"):
        read_stored_tiff(path)


def test_a_stored_tiff_is_refused_for_its_compression_alone(tmp_path):
    from urd.core.errors import DatasetError
    from urd.core.images import stored_tiff_layout

    noise = np.random.default_rng(0).integers(0, 65535, (16, 16, 3), dtype=np.uint16)   # does not compress
    tifffile.imwrite(tmp_path / "T.tiff", noise, photometric="rgb", compression="zlib")
    assert (tmp_path / "T.tiff").stat().st_size >= noise.nbytes                         # the size check passes it
    with pytest.raises(DatasetError, match="compression (zlib|adobe_deflate)"):
        stored_tiff_layout(tmp_path / "T.tiff")
