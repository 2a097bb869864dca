"""Calibration records in a dataset: the mounting offset (``calibration.json``) and per-shot
angle errors (the scene manifest's ``calibration`` record and ``angle_calibrated_deg``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.polarizer import OffsetFit, ShotErrors, estimate_shot_errors, fit_offset
from urd import raw as rawio
from urd.dataset import Dataset, Scene, now_iso, provenance, read_json, write_json_atomic
from urd.ingest import load_stack, shot_angles


def sweep_intensities(scene: Scene) -> tuple[list[float], list[float]]:
    """Stage angles (deg) and mean central-crop intensities of a sweep scene's shots."""
    record = scene.load()
    angles, values = [], []
    for shot in sorted(record["shots"], key=lambda s: s["index"]):
        image = rawio.decode(scene.path / shot["file"], half_size=True)
        h, w = image.shape[:2]
        values.append(float(image[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4].mean()))
        angles.append(float(shot["stage_position_deg"]))
    return angles, values


def save_offset(ds: Dataset, fit: OffsetFit, target_angle_deg: float, sweep: Path) -> dict:
    """Write ``calibration.json``; an earlier calibration moves into its ``history``."""
    path = ds.root / "calibration.json"
    old = read_json(path) if path.exists() else None
    record = {"schema": "urd.calibration", "schema_version": 1, "time": now_iso(), **fit.record(),
              "target_angle_deg": target_angle_deg, "sweep": str(sweep.relative_to(ds.root)),
              "history": (old.get("history", []) + [{k: v for k, v in old.items() if k != "history"}]) if old else []}
    write_json_atomic(path, record)
    return record


def calibrate_offset(ds: Dataset, sweep: Scene, target_angle_deg: float) -> dict:
    """Fit the mounting offset to a captured sweep and store it in the dataset."""
    angles, values = sweep_intensities(sweep)
    return save_offset(ds, fit_offset(np.asarray(angles), np.asarray(values), target_angle_deg), target_angle_deg, sweep.path)


def calibrate_shots(scene: Scene, apply: bool = True) -> ShotErrors:
    """Estimate a scene's per-shot angle errors; with ``apply`` store them as calibrated angles."""
    stack, _ = load_stack(scene)
    record = scene.load(verify=False)
    base = shot_angles({**record, "shots": [{**s, "angle_calibrated_deg": None} for s in record["shots"]]})
    result = estimate_shot_errors(stack, base)
    record["calibration"] = {"time": now_iso(), "applied": apply, **result.record()}
    if apply:
        for shot, angle, error in zip(sorted(record["shots"], key=lambda s: s["index"]), base, result.errors_deg):
            shot["angle_calibrated_deg"] = round(angle + error, 4)
    record["provenance"].append(provenance("calibrate shots", {"apply": apply}))
    scene.save(record)
    return result
