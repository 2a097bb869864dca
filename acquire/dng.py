"""Write a minimal, real DNG: one uncompressed Bayer CFA image that LibRaw (rawpy) opens.

The camera space is linear sRGB: ColorMatrix1 is the XYZ → linear-sRGB matrix under D65, so a
decoder's colour conversion is the identity and white-balanced output equals the scene.
"""

from __future__ import annotations

import datetime as _dt
from fractions import Fraction
from pathlib import Path

import numpy as np
import tifffile

#: XYZ (D65) → linear sRGB, IEC 61966-2-1.
XYZ_TO_SRGB = (3.2406, -1.5372, -0.4986, -0.9689, 1.8758, 0.0415, 0.0557, -0.2040, 1.0570)
#: CFA colour codes per layout, in reading order of the 2×2 tile (0 = R, 1 = G, 2 = B).
CFA_CODES = {"RGGB": (0, 1, 1, 2), "BGGR": (2, 1, 1, 0), "GRBG": (1, 0, 2, 1), "GBRG": (1, 2, 0, 1)}


def _rationals(values) -> list[int]:
    """Numerator, denominator of each value (signed or not), for TIFF (S)RATIONAL tags."""
    out = []
    for v in values:
        f = Fraction(v).limit_denominator(100000)
        out += [f.numerator, f.denominator]
    return out


def write_dng(
    path: Path,
    cfa: np.ndarray,
    black_level: int,
    white_level: int,
    as_shot_neutral: tuple[float, float, float],
    pattern: str = "RGGB",
    exposure_s: float = 1 / 125,
    iso: int = 100,
    time: _dt.datetime | None = None,
    make: str = "urd",
    model: str = "virtual camera",
    description: str = "",
) -> None:
    """Write ``cfa`` (H×W uint16 mosaic, ``pattern`` layout) as a DNG at ``path``.

    Args:
        black_level, white_level: sensor levels in DN.
        as_shot_neutral: camera RGB of a neutral object (1 for green); the inverse is the
            white balance a decoder applies.
        exposure_s, iso, time: EXIF-style metadata, stored in IFD 0 as TIFF/EP allows.
        description: free text (ImageDescription).
    """
    if cfa.dtype != np.uint16 or cfa.ndim != 2 or cfa.shape[0] % 2 or cfa.shape[1] % 2:
        raise ValueError(f"expected an even-sized H×W uint16 mosaic, got {cfa.dtype} {cfa.shape}")
    if pattern not in CFA_CODES:
        raise ValueError(f"expected a CFA pattern in {sorted(CFA_CODES)}, got {pattern!r}")
    stamp = (time or _dt.datetime.now()).strftime("%Y:%m:%d %H:%M:%S")
    tags = [
        (271, 2, None, make, True),
        (272, 2, None, model, True),
        (33421, 3, 2, (2, 2), True),                       # CFARepeatPatternDim
        (33422, 1, 4, CFA_CODES[pattern], True),           # CFAPattern
        (50706, 1, 4, (1, 4, 0, 0), True),                 # DNGVersion
        (50707, 1, 4, (1, 1, 0, 0), True),                 # DNGBackwardVersion
        (50708, 2, None, f"{make} {model}", True),         # UniqueCameraModel
        (50714, 4, 1, int(black_level), True),             # BlackLevel
        (50717, 4, 1, int(white_level), True),             # WhiteLevel
        (50721, 10, 9, _rationals(XYZ_TO_SRGB), True),     # ColorMatrix1
        (50728, 5, 3, _rationals(as_shot_neutral), True),  # AsShotNeutral
        (50778, 3, 1, 21, True),                           # CalibrationIlluminant1 = D65
        (33434, 5, 1, _rationals([exposure_s]), True),     # ExposureTime
        (34855, 3, 1, int(iso), True),                     # ISOSpeedRatings
    ]
    tifffile.imwrite(
        path, cfa, photometric=32803, compression=None, extratags=tags, datetime=stamp,
        description=description or None, subfiletype=0, metadata=None,
    )
