"""Cross-validation, the paper's Table 1 (ECCV 2018 §4): every method on held-out synthetic sets.

The sets are made from photos no shipped model saw in training (training drew from
bsds500/train + sunhays80, validation from bsds500/val): ``bsds500-test`` (../shared/data;
skipped where absent, never replaced), scikit-image's bundled photos (``skimage-bundled``,
`separate.synthesis.BUNDLED_PHOTOS`) and any folder the user names (`load_photos`; JPEG, PNG or
TIFF, 8 or 16 bit). Each set is seeded patches through the full synthesis pipeline (DR + NRD +
LCG, ±4° angle errors, sensor noise, the paper's angles; `synthetic_set`), scored as
`separate.bench` scores its benchmark (the ``bsds500-test`` set *is* that benchmark's set): the
methods get the nominal angles 0/45/90 and pick their reference themselves (`cross_validate`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from separate import optics
from separate.bench import SEED, Timed
from separate.scoring import SCORES, attempt, finite_mean
from separate.synthesis import SHARED_NATURAL, AngleMode, SynthesisConfig, Synthesizer, load_image_pool
from urd.core.progress import Progress

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: Photos are reduced to this many pixels on the long side, as `load_image_pool` does.
MAX_SIDE = 512


def to_pool_image(image: np.ndarray, max_side: int = MAX_SIDE) -> np.ndarray:
    """A decoded photo as the synthesizer's pool holds it: (H, W, 3) uint8 RGB.

    The synthesizer crops and resizes 8-bit display-encoded photos and decodes them with
    `separate.optics.photo_to_linear` (v/255)^2.2, so 16-bit values are taken as display-encoded too
    (as 16-bit PNG and TIFF exports of photos are) and rounded to 8 bits, v/257.

    Args:
        image: (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) uint8 or uint16, RGB(A) order; grey
            is repeated into three channels, alpha dropped.
        max_side: the long side is reduced to this (area averaging) when larger.
    """
    if not isinstance(image, np.ndarray):
        raise TypeError(f"expected a numpy array, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] in (1, 3, 4):
        image = image[..., :3] if image.shape[2] != 1 else image[..., 0]
    if image.ndim != 2 and not (image.ndim == 3 and image.shape[2] == 3):
        raise ValueError(f"expected a grey, RGB or RGBA image (H, W[, 1|3|4]), got shape {image.shape}")
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"expected an 8- or 16-bit integer image, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    scale = max_side / max(image.shape[:2])
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(image)


def load_photo(path: Path, max_side: int = MAX_SIDE) -> np.ndarray:
    """Read a JPEG, PNG or TIFF photo (8 or 16 bit, grey, RGB or RGBA) as `to_pool_image` gives it."""
    path = Path(path)
    if path.suffix.lower() not in PHOTO_SUFFIXES:
        raise ValueError(f"expected a photo ending in {', '.join(PHOTO_SUFFIXES)}, got {path.name}")
    if path.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            image = tifffile.imread(path)
        except Exception as exc:  # noqa: BLE001 - tifffile raises many types for unreadable files
            raise ValueError(f"cannot read image {path}: {exc}") from exc
    else:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"cannot read image {path}")
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    try:
        return to_pool_image(image, max_side)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def load_photos(folder: Path, max_side: int = MAX_SIDE) -> list[np.ndarray]:
    """Every photo in ``folder`` (not its subfolders), sorted by name, as `load_photo` reads it."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"expected a folder of photos, got {folder}")
    files = sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in PHOTO_SUFFIXES)
    if not files:
        raise ValueError(f"expected photos ({', '.join(PHOTO_SUFFIXES)}) in {folder}, got none")
    return [load_photo(f, max_side) for f in files]


def photo_pools(images_dir: Path | None = None) -> list[tuple[str, str, list[np.ndarray] | None]]:
    """The held-out photo sets: (name, description, pool or None where the photos are absent)."""
    bsds = SHARED_NATURAL / "bsds500" / "test"
    pools = [
        ("bsds500-test", "BSDS500 test split, 200 photos (../shared/data)", load_image_pool([bsds]) if bsds.is_dir() else None),
        ("skimage-bundled", "scikit-image's bundled photos", load_image_pool(None)),
    ]
    if images_dir is not None:
        pools.append((f"images-{Path(images_dir).name}", f"the photos in {images_dir}", load_photos(Path(images_dir))))
    return pools


def synthetic_set(pool: list[np.ndarray], count: int, size: int, seed: int = SEED) -> dict[str, np.ndarray]:
    """``count`` patches of ``size``² from ``pool`` through the full synthesis pipeline with the
    paper's angles (`separate.synthesis.Synthesizer`, ``AngleMode.CLASSIC``); for bsds500/test
    and the default seed, the same patches as `separate.bench.benchmark_set`."""
    if count < 1 or size < 64:
        raise ValueError(f"expected at least 1 patch of at least 64 px, got {count} of {size} px")
    usable = sum(min(img.shape[:2]) >= size for img in pool)
    if usable < 2:
        raise ValueError(f"expected at least 2 photos of at least {size} px on the short side, got {usable}")
    return Synthesizer(pool, SynthesisConfig(patch=size, angles=AngleMode.CLASSIC), seed=seed).batch(count)


def cross_validate(data: dict[str, np.ndarray], methods: dict[str, Callable], angles_deg: Sequence[float] = optics.PAPER_ANGLES_DEG,
                   progress: Progress | None = None, label: str = "cross-validation") -> list[dict]:
    """Score each method on a synthetic set; rows as `separate.bench.run_benchmark` gives them
    (means of RMSE/PSNR/SSIM of R̂ and T̂, ``seconds_per_patch``, ``psnr_t_per_patch``) plus
    ``psnr_r_per_patch``, ``failed`` (patches the method refused, NaN per patch, left out of
    the means) and ``failure`` (the first refusal's message)."""
    rows, count = [], len(data["obs"])
    done, total = 0, count * len(methods)
    for name, run in methods.items():
        scores: dict[str, list[float]] = {k: [] for k in SCORES}
        failures = []
        timed = Timed(run)
        for obs, r, t in zip(data["obs"], data["r"], data["t"]):
            figures, failure = attempt(timed, obs, angles_deg, (r, t))
            for key, value in figures.items():
                scores[key].append(value)
            failures += [failure] if failure else []
            done += 1
            if progress:
                progress(done, total, label)
        rows.append({"method": name, **{k: finite_mean(v) for k, v in scores.items()},
                     "seconds_per_patch": timed.per_call(),
                     "psnr_t_per_patch": scores["psnr_t"], "psnr_r_per_patch": scores["psnr_r"],
                     "failed": len(failures), "failure": failures[0] if failures else None})
    return rows
