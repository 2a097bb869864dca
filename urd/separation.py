"""Run a separation method on a scene (or on image files) and store its results.

Outputs go to ``results/METHOD/`` of a scene (or a chosen folder): ``R.tiff`` and ``T.tiff``,
linear 16-bit RGB with full scale 2.0 (value = DN / 65535 × 2, since R + T = S0 reaches twice
a single shot's white level), and ``R_preview.png`` / ``T_preview.png``, 8-bit sRGB at most 2048 px
long, scaled by one common white point. The scene manifest's ``results`` record names the method, its
parameters, the weights' SHA-256 for the network, the files with their hashes, and PSNR/SSIM
against the virtual camera's ground truth when the scene has one.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import tifffile

from separate import metrics
from urd.dataset import Scene, atomic_path, file_record, now_iso, provenance
from urd.errors import DatasetError
from urd.ingest import load_stack

FULL_SCALE = 2.0
PREVIEW_SIDE = 2048


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] → sRGB-encoded [0, 1] (IEC 61966-2-1 transfer function)."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def write_linear_tiff(path: Path, image: np.ndarray, overwrite: bool = False) -> None:
    """Linear H×W×3 → 16-bit TIFF with full scale `FULL_SCALE`, atomically (row blocks, so
    the conversion needs little memory)."""
    data = np.empty(image.shape, np.uint16)
    for y in range(0, image.shape[0], 512):
        block = image[y : y + 512] * (65535.0 / FULL_SCALE)
        data[y : y + 512] = np.clip(np.rint(block), 0, 65535)
    with atomic_path(path, overwrite) as tmp:
        tifffile.imwrite(tmp, data, photometric="rgb")


def write_preview(path: Path, image: np.ndarray, white: float, overwrite: bool = False, max_side: int = PREVIEW_SIDE) -> None:
    """Linear H×W×3 → 8-bit sRGB PNG at most ``max_side`` px long, ``white`` mapping to 255."""
    scale = min(1.0, max_side / max(image.shape[:2]))
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    rgb = np.rint(srgb_encode(image / white) * 255).astype(np.uint8)
    with atomic_path(path, overwrite) as tmp:
        if not cv2.imwrite(str(tmp), rgb[..., ::-1]):
            raise DatasetError(f"cannot write {path}")


def read_image(path: Path) -> np.ndarray:
    """Read an image file as linear float32 H×W×3: 16-bit and float TIFF/PNG are taken as
    linear (16-bit scaled by 1/65535); 8-bit files are taken as sRGB and linearized."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such file")
    data = tifffile.imread(path) if path.suffix.lower() in (".tif", ".tiff") else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise DatasetError(f"{path}: not an image file urd can read")
    if data.ndim == 3 and path.suffix.lower() not in (".tif", ".tiff"):
        data = data[..., 2::-1]
    if data.ndim == 2:
        data = np.repeat(data[..., None], 3, axis=2)
    if data.dtype == np.uint8:
        x = data.astype(np.float32) / 255.0
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)
    if data.dtype == np.uint16:
        return data.astype(np.float32) / 65535.0
    return data[..., :3].astype(np.float32)


def truth_metrics(scene: Scene, r_hat: np.ndarray, t_hat: np.ndarray) -> dict | None:
    """PSNR/SSIM of R̂, T̂ and of no separation against the scene's ground truth, if any.

    Figures are computed 5% inside the border (aligned shots are padded there), with peak 1;
    SSIM on the central 2048×2048 pixels at most.
    """
    truth = scene.path / "truth"
    if not (truth / "T_obs.tiff").is_file():
        return None
    r_true, t_true = tifffile.imread(truth / "R_obs.tiff"), tifffile.imread(truth / "T_obs.tiff")
    h, w = t_true.shape[:2]
    crop = (slice(h // 20, h - h // 20), slice(w // 20, w - w // 20))
    cy, cx = h // 2, w // 2
    centre = (slice(max(crop[0].start, cy - 1024), min(crop[0].stop, cy + 1024)),
              slice(max(crop[1].start, cx - 1024), min(crop[1].stop, cx + 1024)))
    out = {}
    for name, est, ref in (("R", r_hat, r_true), ("T", t_hat, t_true), ("T_no_separation", r_hat + t_hat, t_true)):
        out[name] = {"psnr_db": round(float(metrics.psnr(est[crop], ref[crop])), 3),
                     "ssim": round(metrics.ssim(np.clip(est[centre], 0, 1), np.clip(ref[centre], 0, 1)), 4)}
        del est
    return out


def write_results(folder: Path, r_hat: np.ndarray, t_hat: np.ndarray, overwrite: bool) -> list[Path]:
    """Write the four result files into ``folder``; return their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    step = max(1, int(np.sqrt(r_hat.size / 3 / 1e6)))                 # percentile of ~1 M samples
    white = float(np.percentile(r_hat[::step, ::step] + t_hat[::step, ::step], 99.5)) or 1.0
    paths = [folder / "R.tiff", folder / "T.tiff", folder / "R_preview.png", folder / "T_preview.png"]
    write_linear_tiff(paths[0], r_hat, overwrite)
    write_linear_tiff(paths[1], t_hat, overwrite)
    write_preview(paths[2], r_hat, white, overwrite)
    write_preview(paths[3], t_hat, white, overwrite)
    return paths


def separate_scene(scene: Scene, method: str, run: Callable[[np.ndarray, list[float]], tuple[np.ndarray, np.ndarray]],
                   info: dict, force: bool = False) -> dict:
    """Separate an ingested scene with ``run`` and record the results in its manifest."""
    folder = scene.path / "results" / method
    if folder.exists():
        if not force:
            raise DatasetError(f"{folder} exists; pass --force to replace these results")
        shutil.rmtree(folder)
    images, angles = load_stack(scene)
    r_hat, t_hat = run(images, angles)
    del images                                            # the largest array: free it before writing
    paths = write_results(folder, r_hat, t_hat, overwrite=False)
    record = scene.load(verify=False)
    entry = {"time": now_iso(), "method": method, "angles_deg": angles, **info,
             "full_scale": FULL_SCALE, "files": [file_record(scene.path, p) for p in paths],
             "truth_metrics": truth_metrics(scene, r_hat, t_hat)}
    record.setdefault("results", {})[method] = entry
    record["provenance"].append(provenance(f"separate {method}", info.get("parameters", {})))
    scene.save(record)
    return entry
