"""A compact copy of the training data for a lent GPU machine, where ../shared does not travel.

Writes FOLDER (default .pool, to be ignored by git and named in the device call's ``carry``)
laid out as ../shared/data, holding only what training reads, at the size it reads it:

- natural/bsds500/train: the photos as they are (JPEG, at most 481 px: training reads them whole);
- natural/sunhays80: each photo reduced to 512 px on its long side, as training reduces it
  (`separate.synthesis.load_image_pool`), then JPEG at quality 95;
- polarization/…: the training side of the real no-glass captures (`urd.core.samples`), each shot
  reduced to 512 px as `separate.synthesis.capture_stokes` reduces it and written as a 16-bit PNG
  of its linear values under the capture's own file name (dphr2022-outdoor's 512² 8-bit PNGs
  with the same pixels, the Hagen mosaic as it is).

There, ``mkdir -p ../shared && ln -s "$PWD/FOLDER" ../shared/data`` puts it where urd looks. FOLDER is
removed and written anew on each run; a folder holding anything but a pool is refused.
Prints each part's size and the largest Stokes difference from the full captures (16-bit rounding).

    python tools/gpu_pool.py [--folder .pool]
"""

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np

from separate import synthesis
from urd.core import samples
from urd.core.images import linear_to_u16

from toolargs import Formatter, scratch


def size_mb(folder: Path) -> float:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file()) / 1e6


def copy_natural(out: Path) -> None:
    source = synthesis.SHARED_NATURAL
    shutil.copytree(source / "bsds500" / "train", out / "natural" / "bsds500" / "train")
    target = out / "natural" / "sunhays80"
    target.mkdir(parents=True)
    for photo in sorted((source / "sunhays80").iterdir()):
        bgr = cv2.imread(str(photo), cv2.IMREAD_COLOR)
        if bgr is None:
            continue
        scale = synthesis.POOL_MAX_SIDE / max(bgr.shape[:2])
        if scale < 1:
            bgr = cv2.resize(bgr, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(target / (photo.stem + ".jpg")), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])


def copy_captures(out: Path) -> None:
    for capture in samples.no_glass_captures(split="train"):
        stack, _ = samples.load(capture, max_side=synthesis.POOL_MAX_SIDE)
        for k, path in enumerate(capture.files):
            target = out / "polarization" / path.relative_to(samples.SHARED)
            target.parent.mkdir(parents=True, exist_ok=True)
            if capture.kind != "frames":
                shutil.copy(path, target)
                continue
            whole = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if max(stack.shape[1:3]) == max(whole.shape[:2]):    # read whole: the same pixels, compressed harder
                cv2.imwrite(str(target), whole, [cv2.IMWRITE_PNG_COMPRESSION, 9])
                continue
            codes = linear_to_u16(stack[k])
            cv2.imwrite(str(target), codes[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])


def check(out: Path) -> float:
    """The largest absolute difference of the pool's Stokes stacks from the full captures' (S0 = 1 mean)."""
    worst = 0.0
    pooled = samples.no_glass_captures(out / "polarization", split="train")
    for full, small in zip(samples.no_glass_captures(split="train"), pooled, strict=True):
        a, _ = synthesis.capture_stokes(full)
        b, _ = synthesis.capture_stokes(small)
        worst = max(worst, float(np.abs(a - b).max()))
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--folder", type=Path, default=Path(".pool"),
                        help="the pool's folder, removed and written anew (refused unless this tool made it)")
    args = parser.parse_args()
    if not samples.SHARED.is_dir() or not synthesis.SHARED_NATURAL.is_dir():
        raise SystemExit("expected ../shared/data (natural photos and real captures) beside the project")
    scratch(args.folder)
    copy_natural(args.folder)
    copy_captures(args.folder)
    for part in ("natural", "polarization"):
        print(f"{part}: {size_mb(args.folder / part):.1f} MB")
    print(f"captures' Stokes, largest difference from the full captures: {check(args.folder):.2e} (mean S0 = 1)")


if __name__ == "__main__":
    main()
