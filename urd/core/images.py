"""Reading image files (not RAW): frames of polarization cameras and ``--images`` inputs.

One transfer rule for every command: integer files (8-bit, 16-bit, 12-bit data stored in 16
bits) are read with the chosen `Transfer`, by default ``linear`` (the sensor codes of
machine-vision and polarization cameras, a raw converter's linear output); ``srgb`` linearizes
photos encoded for display (an ordinary camera's PNG/JPEG, an editor's 8- or 16-bit export) with
the IEC 61966-2-1 curve. Float files are linear. Integer codes are scaled so
that 1.0 is the largest code of their type (255, 65535: 12-bit data stored in 16 bits reaches
4095/65535); float files are taken as they are, 1.0 the white level: a file with more than
`FLOAT_ABOVE_WHITE` of its values above 1.0 is refused (every such pixel would read as clipped),
as is one with as many below `FLOAT_BELOW_BLACK` (another black level). Pixels are read as stored:
a TIFF of several images is refused, and an EXIF orientation is not applied (`exif_orientation`
reads it, so that urd can say so), because the polarizer angles are measured in the stored frame.
"""

from __future__ import annotations

import enum
import os
import struct
from pathlib import Path

import cv2
import numpy as np
import tifffile

from urd.core.errors import DatasetError, RawFormatError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")


class Transfer(str, enum.Enum):
    """How 8-bit codes map to linear light."""

    LINEAR = "linear"
    SRGB = "srgb"


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] → linear [0, 1] (IEC 61966-2-1), float32."""
    x = np.asarray(x, np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


#: Values `linear_to_u16` converts at a time, through one reused temporary that stays in the CPU's cache.
U16_BLOCK = 1 << 16


def linear_to_u16(image: np.ndarray, full_scale: float = 1.0) -> np.ndarray:
    """Linear values → 16-bit codes of urd's linear TIFFs, ``full_scale`` mapping to 65535
    (aligned shots: 1.0; results: 2.0), rounded and clipped. Converted `U16_BLOCK` values at a
    time (a 24 MP shot 0.45-0.8 s → 0.05-0.1 s: a whole-image temporary's first touch of memory
    costs more than the arithmetic)."""
    flat = np.asarray(image).reshape(-1)
    scale = 65535.0 / full_scale
    codes = np.empty(flat.shape, np.uint16)
    buffer = np.empty(min(flat.size, U16_BLOCK), (flat[:0] * scale).dtype)
    for start in range(0, flat.size, U16_BLOCK):
        block = buffer[: min(U16_BLOCK, flat.size - start)]
        np.multiply(flat[start : start + block.size], scale, out=block)
        np.rint(block, out=block)
        np.clip(block, 0, 65535, out=block)
        codes[start : start + block.size] = block
    return codes.reshape(np.shape(image))


def u16_to_linear(codes: np.ndarray, full_scale: float = 1.0, out: np.ndarray | None = None) -> np.ndarray:
    """Inverse of `linear_to_u16`: float32 linear values, into ``out`` when given (no copy)."""
    return np.multiply(codes, np.float32(full_scale / 65535.0), out=out, dtype=np.float32)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] → sRGB-encoded [0, 1] (IEC 61966-2-1), float32; input clipped to [0, 1], NaN → 0."""
    x = np.clip(np.nan_to_num(np.asarray(linear, np.float32)), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def to_display(image: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """H×W×C (C = 1 or 3) or H×W linear float image × ``gain`` → H×W×3 uint8 sRGB (values
    above 1 after the gain clip to 255). Encoded `U16_BLOCK` values at a time, as `linear_to_u16`
    converts (a 2048 px preview 0.10 → 0.06 s); a grey image is encoded once and repeated."""
    x = np.asarray(image, np.float32)
    if x.ndim == 2:
        x = x[..., None]
    flat, gain = x.reshape(-1), np.float32(gain)
    codes = np.empty(flat.shape, np.uint8)
    for start in range(0, flat.size, U16_BLOCK):
        codes[start : start + U16_BLOCK] = np.rint(srgb_encode(flat[start : start + U16_BLOCK] * gain) * 255.0)
    codes = codes.reshape(x.shape)
    return np.repeat(codes, 3, axis=-1) if x.shape[-1] == 1 else codes


def read_raw_codes(path: Path) -> np.ndarray:
    """The file's pixel codes as stored (H×W or H×W×3 in RGB order); RawFormatError if unreadable."""
    path = Path(path)
    if path.is_dir():
        raise DatasetError(f"{path} is a folder, not an image file")
    if not path.is_file():
        raise DatasetError(f"{path}: no such file")
    data, problem, bgr = None, "", True
    if path.suffix.lower() in (".tif", ".tiff"):
        try:
            data, bgr = _read_tiff(path), False
        except RawFormatError:
            raise
        except (OSError, ValueError) as exc:        # e.g. a compression only imagecodecs decodes: OpenCV reads LZW
            problem = f" ({exc})"
    if data is None:
        try:
            data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        except cv2.error as exc:                         # e.g. a header larger than OpenCV's pixel limit
            problem = f" ({str(exc).strip().splitlines()[-1]})"
    if data is None:
        raise RawFormatError(f"{path}: not an image file urd can read{problem}")
    if data.ndim == 3 and data.shape[-1] < 3:           # grey with alpha: the grey
        return data[..., 0]
    if data.ndim == 3 and bgr:
        data = data[..., 2::-1]
    return data


def _read_tiff(path: Path) -> np.ndarray:
    """A one-image TIFF's pixels, H×W or H×W×S (planar files, which store each sample apart,
    put back in pixel order); RawFormatError for a file of several images (pages)."""
    with tifffile.TiffFile(path) as tif:
        pages = sum(not page.is_reduced for page in tif.pages)        # reduced-resolution copies are not images
        if pages > 1:
            raise RawFormatError(f"{path}: a TIFF of {pages} images (pages); give one image per file")
        page = tif.pages[0]
        if page.photometric in (tifffile.PHOTOMETRIC.SEPARATED, tifffile.PHOTOMETRIC.PALETTE):
            raise RawFormatError(f"{path}: a {page.photometric.name.lower().replace('separated', 'CMYK')} TIFF; "
                                 "save it as RGB or grey")
        alpha = (tifffile.EXTRASAMPLE.ASSOCALPHA, tifffile.EXTRASAMPLE.UNASSALPHA)
        if page.samplesperpixel == 2 and not any(extra in alpha for extra in page.extrasamples):
            raise RawFormatError(f"{path}: a TIFF of 2 samples per pixel, neither grey with alpha nor RGB; save it as "
                                 "RGB or grey")
        if page.dtype is not None:                 # a sample format tifffile does not know fails in asarray below
            check_decodable(path, int(np.prod(page.shape)) * page.dtype.itemsize)
        data = page.asarray()
        if page.planarconfig == tifffile.PLANARCONFIG.SEPARATE and page.samplesperpixel > 1:
            data = np.moveaxis(data, 0, -1)
        return data


def available_memory() -> int:
    """Bytes of memory the system can give this process now (Linux's MemAvailable; the physical
    memory where that is not known)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_decodable(path: Path, nbytes: int) -> None:
    """RawFormatError when the pixels a file's header announces (``nbytes`` decoded) would not fit
    in the memory available: a small compressed file can claim gigabytes."""
    if nbytes > available_memory():
        raise RawFormatError(f"{path}: its header announces {nbytes / 2**30:.1f} GiB of pixels, more than the "
                             f"{available_memory() / 2**30:.1f} GiB of memory available")


def stored_tiff_layout(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of a TIFF urd wrote itself (aligned shots, results): one uncompressed image
    whose pixels the file holds. DatasetError otherwise: a compressed file in their place can
    announce more pixels than memory holds (a file received with a dataset is not trusted)."""
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        nbytes = int(np.prod(page.shape)) * (page.dtype.itemsize if page.dtype is not None else 1)
        compression = getattr(page.compression, "name", str(page.compression)).lower()    # an unknown code is an int
        if (len(tif.pages) != 1 or page.compression != tifffile.COMPRESSION.NONE or page.dtype is None
                or nbytes > path.stat().st_size):
            raise DatasetError(f"{path}: not an image as urd writes them (one uncompressed image of a known sample "
                               f"format; {len(tif.pages)} page(s), compression {compression}, "
                               f"{nbytes} bytes of pixels in a file of {path.stat().st_size})")
        return tuple(page.shape), page.dtype


def read_stored_tiff(path: Path) -> np.ndarray:
    """The pixels of a TIFF urd wrote itself, checked first (`stored_tiff_layout`)."""
    stored_tiff_layout(path)
    return tifffile.imread(path)


#: EXIF's orientation tag, and its values: 1 is the pixels as stored; 2-8 ask viewers to mirror or turn them.
ORIENTATION_TAG = 0x0112
ORIENTATIONS = {2: "mirrored", 3: "turned 180°", 4: "mirrored upside down", 5: "mirrored and turned",
                6: "turned 90° clockwise", 7: "mirrored and turned", 8: "turned 90° counter-clockwise"}


def exif_orientation(path: Path) -> int:
    """The EXIF orientation (1-8) of a JPEG or TIFF file; 1 (as stored) where it has none or is another kind."""
    path = Path(path)
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            with tifffile.TiffFile(path) as tif:
                tag = tif.pages[0].tags.get(ORIENTATION_TAG)
                return int(tag.value) if tag is not None else 1
        with open(path, "rb") as file:
            head = file.read(1 << 17)
    except (OSError, ValueError):
        return 1
    if head[:2] != b"\xff\xd8":
        return 1
    pos = 2
    while pos + 4 <= len(head) and head[pos] == 0xFF and head[pos + 1] not in (0xD9, 0xDA):   # to the image data
        length = int.from_bytes(head[pos + 2 : pos + 4], "big")
        if head[pos + 1] == 0xE1 and head[pos + 4 : pos + 10] == b"Exif\0\0":
            return _tiff_orientation(head[pos + 10 : pos + 2 + length])
        pos += 2 + length
    return 1


def _tiff_orientation(tiff: bytes) -> int:
    """The orientation tag of an EXIF block's first image directory (a TIFF header and IFD0); 1 if absent."""
    order = "<" if tiff[:2] == b"II" else ">"
    try:
        (ifd,) = struct.unpack_from(order + "I", tiff, 4)
        (count,) = struct.unpack_from(order + "H", tiff, ifd)
        for k in range(count):
            tag, _, _, value = struct.unpack_from(order + "HHIH", tiff, ifd + 2 + 12 * k)
            if tag == ORIENTATION_TAG:
                return value if value in range(1, 9) else 1
    except struct.error:
        pass
    return 1


#: The share of a float file's values that may lie above 1.0 (the white level): clipped
#: highlights, which urd marks; where more of the picture lies above it, the file has another scale.
FLOAT_ABOVE_WHITE = 0.05
#: Below this a float value is not noise around black (0.0) but light measured from another black
#: level: a file with more than `FLOAT_ABOVE_WHITE` of its values below it is refused.
FLOAT_BELOW_BLACK = -0.05


def to_linear(data: np.ndarray, transfer: Transfer = Transfer.LINEAR) -> np.ndarray:
    """Pixel codes → linear float32 by the module's rule (1.0 = the type's largest code; floats as
    they are, RawFormatError where one is NaN or infinite or more than `FLOAT_ABOVE_WHITE` of them
    exceed 1.0 or lie below `FLOAT_BELOW_BLACK`)."""
    if data.dtype in (np.uint8, np.uint16):
        return codes_to_linear(data, data.dtype, transfer)
    if data.dtype.kind == "f":
        check_float_scale(data)
        return data.astype(np.float32)
    raise RawFormatError(f"expected 8-bit, 16-bit or float pixels, got {data.dtype}")


def check_float_scale(data: np.ndarray, advice: str = "") -> None:
    """RawFormatError unless float pixels are finite and on urd's scale, 0.0 black and 1.0 white:
    at most `FLOAT_ABOVE_WHITE` of them above 1.0 or below `FLOAT_BELOW_BLACK`; ``advice`` is
    added to the message about white."""
    if not np.isfinite(data).all():
        raise RawFormatError(f"{int((~np.isfinite(data)).sum())} NaN or infinite pixel values")
    above = float(np.mean(data > 1.0))
    if above > FLOAT_ABOVE_WHITE:
        raise RawFormatError(f"float pixels are read with 1.0 as white, and {above:.1%} of these exceed it (up to "
                             f"{float(data.max()):g}): scale every shot by one factor so that white is 1.0"
                             + (f" ({advice})" if advice else ""))
    below = float(np.mean(data < FLOAT_BELOW_BLACK))
    if below > FLOAT_ABOVE_WHITE:
        raise RawFormatError(f"float pixels are read with 0.0 as black, and {below:.1%} of these lie below "
                             f"{FLOAT_BELOW_BLACK:g} (down to {float(data.min()):g}): subtract the sensor's black "
                             "level so that black is 0.0")


def codes_to_linear(codes: np.ndarray, dtype: np.dtype, transfer: Transfer = Transfer.LINEAR) -> np.ndarray:
    """Codes of an 8- or 16-bit file, in any numeric array (e.g. interpolated by demosaicing),
    → linear float32 by the module's rule, clipped to [0, 1] (1.0 = ``dtype``'s largest code)."""
    dtype = np.dtype(dtype)
    if dtype not in (np.uint8, np.uint16):
        raise RawFormatError(f"expected codes of 8- or 16-bit pixels, got {dtype}")
    x = np.clip(np.asarray(codes, np.float32) / float(np.iinfo(dtype).max), 0.0, 1.0)
    return srgb_to_linear(x) if Transfer(transfer) is Transfer.SRGB else x


def stored_bits(path: Path) -> int | None:
    """Bits per sample of a PNG, TIFF or JPEG file from its header (JPEG: 8); None when unknown."""
    path = Path(path)
    try:
        if path.suffix.lower() in (".jpg", ".jpeg"):
            return 8
        if path.suffix.lower() == ".png":
            with open(path, "rb") as file:
                head = file.read(25)
            return head[24] if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 25 else None
        if path.suffix.lower() in (".tif", ".tiff"):
            with tifffile.TiffFile(path) as tif:
                return int(tif.pages[0].bitspersample)
    except (OSError, ValueError, IndexError, tifffile.TiffFileError):
        return None
    return None


def read_image(path: Path, transfer: Transfer = Transfer.LINEAR) -> np.ndarray:
    """An image file as linear float32 H×W×3 (grey files repeated into three channels)."""
    return linear_image(read_raw_codes(path), path, transfer)


def linear_image(codes: np.ndarray, path: Path, transfer: Transfer = Transfer.LINEAR) -> np.ndarray:
    """The codes of the file ``path`` (`read_raw_codes`) as linear float32 H×W×3 (grey repeated
    into three channels)."""
    try:
        data = to_linear(codes, transfer)
    except RawFormatError as exc:
        raise RawFormatError(f"{path}: {exc}") from None
    if data.ndim == 2:
        data = np.repeat(data[..., None], 3, axis=2)
    return np.ascontiguousarray(data[..., :3])
