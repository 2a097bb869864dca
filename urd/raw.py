"""RAW decoding with rawpy (LibRaw): linear images and capture metadata.

Output is linear light: no gamma, no auto-brightness, the camera's as-shot white balance, the
black and white levels applied, so 1.0 is the sensor's white level on the green channel. It
works for every format LibRaw reads (DNG, ARW, CR2, NEF, ...). A RAW container that is not a
Bayer (or other colour-filter-array) camera image, such as a film scanner's stack, is rejected.
"""

from __future__ import annotations

import enum
from pathlib import Path

import numpy as np
import rawpy

from urd.errors import RawFormatError

RAW_SUFFIXES = (".dng", ".arw", ".cr2", ".cr3", ".nef", ".nrw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".kdc", ".3fr", ".iiq", ".x3f")


class Demosaic(enum.Enum):
    """Demosaicing algorithm (LibRaw's names). LINEAR is fastest; AHD is LibRaw's default."""

    LINEAR = "linear"
    AHD = "ahd"
    DHT = "dht"

    def rawpy_value(self) -> rawpy.DemosaicAlgorithm:
        return getattr(rawpy.DemosaicAlgorithm, self.name)


def _open(path: Path) -> rawpy.RawPy:
    path = Path(path)
    if not path.is_file():
        raise RawFormatError(f"{path}: no such file")
    try:
        raw = rawpy.imread(str(path))
    except rawpy.LibRawError as exc:
        raise RawFormatError(f"{path}: not a RAW file rawpy can read ({type(exc).__name__}: {exc})") from exc
    try:
        raw.unpack()
    except rawpy.LibRawError as exc:
        raw.close()
        raise RawFormatError(f"{path}: corrupt or truncated RAW data ({type(exc).__name__}: {exc})") from exc
    if raw.raw_type != rawpy.RawType.Flat or raw.raw_pattern is None:
        raw.close()
        raise RawFormatError(f"{path}: not a colour-filter-array camera image (LibRaw reports a {raw.raw_type.name} raw)")
    return raw


def decode(path: Path, half_size: bool = False, demosaic: Demosaic = Demosaic.LINEAR) -> np.ndarray:
    """Decode a RAW file to a linear float32 H×W×3 image (camera white balance, [0, ~1]).

    ``half_size`` skips demosaicing and returns one pixel per 2×2 CFA tile (half width and
    height, ~4× faster).
    """
    with _open(path) as raw:
        try:
            rgb = raw.postprocess(
                gamma=(1, 1), no_auto_bright=True, use_camera_wb=True, output_bps=16, user_flip=0,
                half_size=half_size, demosaic_algorithm=demosaic.rawpy_value(),
                output_color=rawpy.ColorSpace.sRGB,
            )
        except rawpy.LibRawError as exc:
            raise RawFormatError(f"{path}: corrupt or truncated RAW data ({type(exc).__name__}: {exc})") from exc
    image = rgb.astype(np.float32)
    image *= 1.0 / 65535.0
    return image


def metadata(path: Path) -> dict:
    """Capture metadata for manifests: camera, exposure (s), ISO, aperture, time, sizes, levels."""
    with _open(path) as raw:
        other = raw.other
        sizes = raw.sizes
        record = {
            "exposure_s": float(other.shutter_speed) or None,
            "iso": float(other.iso_speed) or None,
            "aperture": float(other.aperture) or None,
            "focal_length_mm": float(other.focal_length) or None,
            "time": other.timestamp.isoformat() if other.timestamp and other.timestamp.year > 1970 else None,
            "width": int(sizes.width),
            "height": int(sizes.height),
            "black_level": [int(v) for v in raw.black_level_per_channel],
            "white_level": int(raw.white_level),
            "camera_whitebalance": [float(v) for v in raw.camera_whitebalance],
            "cfa": raw.color_desc.decode(),
        }
    record.update(_tiff_make_model(path))
    return record


def _tiff_make_model(path: Path) -> dict:
    """Make and model from a TIFF-based RAW (DNG, ARW, CR2, NEF); empty for other containers."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            return {key: str(tags[code].value).strip("\x00 ") for key, code in (("make", 271), ("model", 272)) if code in tags}
    except Exception:  # noqa: BLE001 - any non-TIFF container simply has no such tags
        return {}


def description(path: Path) -> str:
    """The ImageDescription text of a TIFF-based RAW ('' when none)."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages[0].tags.get(270)
            return str(tag.value) if tag else ""
    except Exception:  # noqa: BLE001
        return ""
