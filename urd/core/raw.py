"""RAW decoding with rawpy (LibRaw): linear images and capture metadata.

Output is linear light: black and white levels applied, the camera's as-shot white balance
(green = 1), bilinear demosaicing and the camera → linear sRGB matrix, with no gamma, no
brightening and no clipping, so 1.0 is the sensor's white level on the green channel. urd does
these steps itself on rawpy's CFA data rather than calling LibRaw's ``postprocess``: every step
is then exactly linear in the sensor values, which the polarization fits rely on (LibRaw's
output is not: angle fits on it are biased by degrees). Formats: whatever LibRaw reads (DNG,
ARW, CR2, NEF, ...). A RAW container that is not a colour-filter-array camera image, such as a
film scanner's stack, is rejected.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import rawpy

from urd.core.errors import RawFormatError
from urd.core.mosaic import demosaic_bilinear

RAW_SUFFIXES = (".dng", ".arw", ".cr2", ".cr3", ".nef", ".nrw", ".raf", ".orf", ".rw2", ".pef", ".srw", ".kdc", ".3fr", ".iiq", ".x3f")


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
    wb = raw.camera_whitebalance
    if (wb[0] == 0 or wb[2] == 0) and not _has_colour_matrix(raw) and "make" not in _tiff_tags(path):
        raw.close()                                  # LibRaw reads any TIFF as a Bayer frame, and invents these
        raise RawFormatError(f"{path}: not a camera RAW file: no camera, white balance or colour matrix (an image "
                             "saved under a RAW name?); polarization-camera frames are ingested with --mosaic")
    return raw


def _has_colour_matrix(raw: rawpy.RawPy) -> bool:
    """Whether LibRaw knows the camera → sRGB matrix of ``raw``'s camera (all zeros where not)."""
    return bool(np.abs(np.asarray(raw.color_matrix)[:, :3]).any())


def decode(path: Path, half_size: bool = False) -> np.ndarray:
    """Decode a RAW file to a linear float32 H×W×3 image (camera white balance; sRGB primaries
    where LibRaw has the camera's colour matrix, else the camera's own RGB: `metadata`'s ``colour``).

    ``half_size`` averages each 2×2 CFA tile into one pixel instead of demosaicing (half the
    width and height, several times faster).
    """
    with _open(path) as raw:
        raw_codes = raw.raw_image_visible.copy()
        colours = raw.raw_colors_visible
        desc = raw.color_desc.decode()
        pattern = raw.raw_pattern
        black = np.asarray(raw.black_level_per_channel, np.float32)
        white = float(raw.white_level)
        wb = np.asarray(raw.camera_whitebalance, np.float32)
        if not np.all(wb[:3] > 0):
            wb = np.asarray(raw.daylight_whitebalance, np.float32)
        rgb_cam = np.asarray(raw.color_matrix, np.float32)[:, :3]
    if len(desc) != 4 or set(desc) - set("RGB") or pattern is None or pattern.shape != (2, 2):
        raise RawFormatError(f"{path}: unsupported colour filter array {desc!r} (urd decodes 2×2 RGB patterns)")
    wb = np.where(wb > 0, wb, wb[1]) / wb[1]
    gain = (wb / (white - black)).astype(np.float32)
    letters = tuple("".join(desc[pattern[r, c]] for c in range(2)) for r in range(2))
    h, w = raw_codes.shape[0] // 2 * 2, raw_codes.shape[1] // 2 * 2
    uniform_black = np.unique(black[np.unique(colours)]).size == 1
    if half_size or not uniform_black:
        linear = (raw_codes[:h, :w].astype(np.float32) - black[colours[:h, :w]]) * gain[colours[:h, :w]]
        image = _half_size(linear, letters) if half_size else demosaic_bilinear(linear, letters)
    else:
        # OpenCV's bilinear Bayer interpolation is linear and per channel, so it may run on the
        # raw codes with their (uniform) black pedestal, which passes through unchanged
        rgb = cv2.cvtColor(raw_codes[:h, :w], getattr(cv2, f"COLOR_Bayer{letters[0]}{letters[1]}2RGB"))
        image = rgb.astype(np.float32)
        image -= black[0]
        image *= np.array([gain[0], gain[1], gain[2]], np.float32)
    if np.abs(rgb_cam).sum() > 0 and not np.allclose(rgb_cam, np.eye(3), atol=1e-3):
        image = image @ rgb_cam.T
    return np.ascontiguousarray(image, dtype=np.float32)


def _half_size(linear: np.ndarray, letters: tuple[str, str]) -> np.ndarray:
    """One RGB pixel per 2×2 CFA tile (greens averaged)."""
    h, w = linear.shape
    image = np.zeros((h // 2, w // 2, 3), np.float32)
    counts = np.zeros(3, np.float32)
    for r in range(2):
        for c in range(2):
            k = "RGB".index(letters[r][c])
            image[..., k] += linear[r::2, c::2]
            counts[k] += 1
    return image / counts


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
            "colour": "linear sRGB" if _has_colour_matrix(raw) else
                      "camera RGB (LibRaw has no colour matrix for this camera)",
        }
    record.update(_tiff_tags(path))
    return record


#: EXIF exposure settings whose value 0 means "not recorded": LibRaw then reports 1 s and f/1.0.
UNRECORDED_EXIF = {"ExposureTime": "exposure_s", "FNumber": "aperture"}


def _tiff_tags(path: Path) -> dict:
    """Make and model from a TIFF-based RAW (DNG, ARW, CR2, NEF), and None for the exposure
    settings its EXIF records as 0 (unknown); empty for other containers."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tags = tif.pages[0].tags
            found = {key: str(tags[code].value).strip("\x00 ") for key, code in (("make", 271), ("model", 272)) if code in tags}
            exif = tags[34665].value if 34665 in tags and isinstance(tags[34665].value, dict) else {}
    except Exception:  # noqa: BLE001 - any non-TIFF container simply has no such tags
        return {}
    for name, key in UNRECORDED_EXIF.items():
        value = exif.get(name)
        if isinstance(value, tuple) and len(value) == 2 and value[0] == 0:
            found[key] = None
    return found


def description(path: Path) -> str:
    """The ImageDescription text of a TIFF-based RAW ('' when none)."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages[0].tags.get(270)
            return str(tag.value) if tag else ""
    except Exception:  # noqa: BLE001
        return ""
