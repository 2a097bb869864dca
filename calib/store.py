"""Calibration workflows and their records in a dataset.

The mounting offset comes from a sweep: a scene under ``calibration/sweep_NN`` (this module
owns that folder; `Dataset.new_sweep` creates it) whose shots see a polarized target; the fit
is stored in ``calibration.json`` (`Dataset.save_calibration`, with the history of earlier
fits) and later captures command the stage ``polarizer angle − offset``. Per-shot angle errors
of an ingested scene go into its manifest (`Scene.set_shot_calibration`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.polarizer import ShotErrors, estimate_shot_errors, fit_offset
from urd import raw as rawio
from urd.dataset import Dataset, Scene
from urd.progress import Progress


def sweep_intensities(scene: Scene) -> tuple[list[float], list[float]]:
    """Stage angles (deg) and mean central-crop intensities of a sweep scene's shots."""
    angles, values = [], []
    for shot, path in zip(scene.shots(), scene.raw_paths()):
        image = rawio.decode(path, half_size=True)
        h, w = image.shape[:2]
        values.append(float(image[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4].mean()))
        angles.append(float(shot.stage_position_deg))
    return angles, values


def calibrate_offset(ds: Dataset, sweep: Scene, target_angle_deg: float) -> dict:
    """Fit the mounting offset to a captured sweep and store it in the dataset."""
    angles, values = sweep_intensities(sweep)
    fit = fit_offset(np.asarray(angles), np.asarray(values), target_angle_deg)
    return ds.save_calibration(fit.record(), target_angle_deg, sweep)


def sweep_and_calibrate(root: Path, stage: str, camera: str, step_deg: float, target_angle_deg: float,
                        address: str = "0", sim=None, progress: Progress | None = None) -> dict:
    """The workflow of ``urd calibrate offset``: sweep the polarizer over 180° in front of a
    polarized target, fit Malus's law, store the offset. Returns the calibration record."""
    from acquire.plan import capture_plan_record, run_capture
    from acquire.rig import open_rig

    angles = [float(a) for a in np.arange(0.0, 180.0, step_deg)]
    ds = Dataset.open_or_create(root)
    with ds.lock(), open_rig(stage, camera, address, sim=sim) as rig:
        sweep = ds.new_sweep(capture_plan_record(angles, 0.0, 0.5, rig.info))
        counter = iter(range(1, len(angles) + 1))
        try:
            run_capture(sweep, rig.stage, rig.camera, angles,
                        progress=lambda st: progress and st.kind == "record" and progress(next(counter), len(angles), "sweep"))
        except BaseException:
            sweep.discard_if_empty()
            raise
        return calibrate_offset(ds, sweep, target_angle_deg)


def calibrate_shots(scene: Scene, apply: bool = True) -> ShotErrors:
    """Estimate a scene's per-shot angle errors; with ``apply`` store them as calibrated angles."""
    with scene.lock():
        stack, _ = scene.reload().load_stack()
        base = scene.uncalibrated_angles_deg()
        result = estimate_shot_errors(stack, base)
        calibrated = [angle + error for angle, error in zip(base, result.errors_deg)] if apply else None
        scene.set_shot_calibration(result.record(), calibrated)
    return result
