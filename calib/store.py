"""Calibration workflows and their records in a dataset.

The mounting offset comes from a sweep: a scene under ``calibration/sweep_NN`` (this module
owns that folder; `Dataset.new_sweep` creates it) whose shots see a polarized target; the fit
is stored in ``calibration.json`` (`Dataset.save_calibration`, with the history of earlier
fits) and later captures command the stage ``polarizer angle − offset``. The offset belongs to
the stage it was measured on: the calibration records that stage's identity
(`acquire.rig.stage_identity`, under ``stage``), and a capture with another stage is refused
(`offset_for_stage`). Per-shot angle errors of an ingested scene go into its manifest
(`Scene.set_shot_calibration`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib.polarizer import ShotErrors, estimate_shot_errors, fit_offset
from urd.core import raw as rawio
from urd.core.dataset import Dataset, Scene
from urd.core.errors import CalibrationError, CaptureInterrupted, UrdError
from urd.core.progress import Progress


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
    """Fit the mounting offset to a captured sweep and store it in the dataset, with the
    identity of the stage the sweep was captured with."""
    from acquire.rig import stage_identity

    angles, values = sweep_intensities(sweep)
    fit = fit_offset(np.asarray(angles), np.asarray(values), target_angle_deg)
    stage = sweep.load(verify=False)["capture"].get("stage")
    record = fit.record() if stage is None else {**fit.record(), "stage": stage_identity(stage)}
    return ds.save_calibration(record, target_angle_deg, sweep)


def calibration_stage(ds: Dataset) -> dict | None:
    """The identity (`acquire.rig.stage_identity`) of the stage the dataset's mounting offset
    was calibrated on: as recorded in ``calibration.json``, else (calibrations written before
    it was recorded) from the sweep's manifest; None when not known."""
    from acquire.rig import stage_identity

    calibration = ds.calibration()
    if calibration is None:
        return None
    stage = calibration.stage
    if stage is None and calibration.sweep is not None and Scene(calibration.sweep).exists():
        recorded = Scene(calibration.sweep).load(verify=False)["capture"].get("stage")
        stage = None if recorded is None else stage_identity(recorded)
    return stage


def offset_for_stage(ds: Dataset, stage_info: dict) -> tuple[float, str]:
    """The mounting offset (deg) a new capture with the stage ``stage_info`` (`acquire.rig.
    open_rig`'s ``info["stage"]``) commands, and a line saying which calibration that is.

    0 without a calibration. CalibrationError when the dataset's calibration belongs to
    another stage (its offset would put every shot at the wrong angle).
    """
    from acquire.rig import describe_stage, stage_identity

    calibration = ds.calibration()
    if calibration is None:
        return 0.0, "mounting offset: not calibrated (urd calibrate offset); stage zero taken as polarizer angle 0 deg"
    owner, this = calibration_stage(ds), stage_identity(stage_info)
    if owner is not None and owner != this:
        raise CalibrationError(
            f"{ds.calibration_path.resolve()}: the mounting offset {calibration.offset_deg:.3f} deg was calibrated on "
            f"{describe_stage(owner)}, not on this stage ({describe_stage(this)}); calibrate this stage "
            f"with 'urd calibrate offset {ds.root.resolve()} --stage {stage_info.get('port') or 'PORT'}"
            f"{' --camera virtual' if this['kind'] == 'ELL14 simulator' else ''}', or capture into another dataset")
    whose = describe_stage(owner) if owner is not None else "a stage it does not record"
    return calibration.offset_deg, (f"mounting offset: {calibration.offset_deg:.3f} ± {calibration.uncertainty_deg:.3f} deg "
                                    f"from {ds.calibration_path.resolve()} ({calibration.time}, on {whose})")


def sweep_and_calibrate(root: Path, stage: str, camera: str, step_deg: float, target_angle_deg: float,
                        address: str = "0", sim=None, progress: Progress | None = None) -> dict:
    """The workflow of ``urd calibrate offset``: sweep the polarizer over 180° in front of a
    polarized target, fit Malus's law, store the offset. Returns the calibration record."""
    from acquire.plan import capture_plan_record, run_capture
    from acquire.rig import open_rig

    angles = [float(a) for a in np.arange(0.0, 180.0, step_deg)]
    with open_rig(stage, camera, address, sim=sim) as rig:
        ds = Dataset.open_or_create(root)
        with ds.lock():
            sweep = ds.new_sweep(capture_plan_record(angles, 0.0, 0.5, rig.info))
            counter = iter(range(1, len(angles) + 1))
            try:
                run_capture(sweep, rig.stage, rig.camera, angles,
                            progress=lambda st: progress and st.kind == "record" and progress(next(counter), len(angles), "sweep"))
            except KeyboardInterrupt:
                raise CaptureInterrupted(f"calibration sweep interrupted; {_left(sweep)}") from None
            except (UrdError, OSError) as exc:
                raise UrdError(f"{exc}\ncalibration sweep stopped; {_left(sweep)}") from exc
            except BaseException:
                sweep.discard_if_empty()
                raise
            return calibrate_offset(ds, sweep, target_angle_deg)


def _left(sweep: Scene) -> str:
    """What a stopped sweep left: nothing, or its shots (a sweep is not resumed: the next
    'urd calibrate offset' sweeps anew and the calibration never uses an incomplete one)."""
    if sweep.discard_if_empty():
        return "no shot was taken, nothing was kept"
    return (f"its {len(sweep.shots())} shots are kept in {sweep.path.resolve()} (unused: an incomplete sweep is never "
            "fitted; delete it if you like); run 'urd calibrate offset' again for a new sweep")


def calibrate_shots(scene: Scene, apply: bool = True) -> ShotErrors:
    """Estimate a scene's per-shot angle errors; with ``apply`` store them and the calibrated
    angles in its manifest, else leave the manifest as it is."""
    with scene.lock():
        stack, _ = scene.reload().load_stack()
        base = scene.uncalibrated_angles_deg()
        result = estimate_shot_errors(stack, base)
        if apply:
            scene.set_shot_calibration(result.record(), [angle + error for angle, error in zip(base, result.errors_deg)])
    return result
