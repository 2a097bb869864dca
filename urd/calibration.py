"""The calibration sweep, the workflow of ``urd calibrate offset``: it runs a capture (`acquire`)
and fits it (`calib`), so it lives above both, and neither of them imports the other.

The sweep is a scene under ``calibration/sweep_NN`` whose shots see a polarized target through
the polarizer at stage angles over 180°; the Malus-law fit of its intensities
(`calib.polarizer.fit_offset`) gives the mounting offset, stored in ``calibration.json`` with
the identity of the stage it was measured on (`acquire.rig.stage_identity`); later captures with
that stage command ``polarizer angle − offset`` (`acquire.rig.offset_for_stage`). A second sweep
with the target turned checks the stage's sense of rotation (`calib.polarizer.check_direction`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from acquire.plan import capture_plan_record, run_capture
from acquire.rig import open_rig, stage_identity
from acquire.virtual_camera import PolarizedTarget
from calib.polarizer import OffsetFit, check_direction, check_target_turn, fit_offset
from calib.store import sweep_intensities
from urd.core.dataset import Dataset, Scene
from urd.core.errors import UrdError
from urd.core.processes import capture_stopped
from urd.core.progress import Progress


def fit_sweep(sweep: Scene, target_angle_deg: float) -> OffsetFit:
    """The Malus-law fit of a captured sweep (`calib.polarizer.fit_offset`)."""
    angles, values = sweep_intensities(sweep)
    return fit_offset(np.asarray(angles), np.asarray(values), target_angle_deg)


def calibrate_offset(ds: Dataset, sweep: Scene, target_angle_deg: float, direction: dict | None = None,
                     fit: OffsetFit | None = None) -> dict:
    """Fit the mounting offset to a captured sweep (unless its ``fit`` is given) and store it in
    the dataset, with the identity of the stage the sweep was captured with (and ``direction``,
    the record of a checked sense of rotation, where there is one)."""
    fit = fit or fit_sweep(sweep, target_angle_deg)
    stage = sweep.load(verify=False)["capture"].get("stage")
    record = fit.record() if stage is None else {**fit.record(), "stage": stage_identity(stage)}
    if direction is not None:
        record["direction"] = direction
    return ds.save_calibration(record, target_angle_deg, sweep)


def sweep_and_calibrate(root: Path, stage: str, camera: str, step_deg: float, target_angle_deg: float,
                        address: str = "0", sim=None, progress: Progress | None = None,
                        check_target_deg: float | None = None, turn_target: Callable[[float], None] | None = None) -> dict:
    """The workflow of ``urd calibrate offset``: sweep the polarizer over 180° in front of a
    polarized target, fit Malus's law, store the offset. Returns the calibration record.

    With ``check_target_deg`` a second sweep follows once ``turn_target(check_target_deg)`` has
    returned (the user turned the target there; on the simulated rig the virtual target turns),
    and the two fits must say that the stage turns the polarizer counter-clockwise
    (`calib.polarizer.check_direction`); CalibrationError otherwise, and calibration.json is not
    written (the two sweeps stay in ``calibration/``, to look at)."""
    angles = [float(a) for a in np.arange(0.0, 180.0, step_deg)]
    if check_target_deg is not None:
        check_target_turn(target_angle_deg, check_target_deg)     # before any sweep
    with open_rig(stage, camera, address, sim=sim) as rig, Dataset.made_for(root) as ds:
        with ds.lock():
            try:
                ds.calibration()                    # a damaged record stops it before the sweep, not after
            except UrdError as exc:
                raise UrdError(f"{exc}; the sweep was not started: repair the file, or move it away to measure anew") from exc
            first = _sweep(ds, rig, angles, progress, "sweep")
            if check_target_deg is None:
                return calibrate_offset(ds, first, target_angle_deg)
            if turn_target is not None:
                turn_target(check_target_deg)
            if isinstance(getattr(rig.camera, "scene", None), PolarizedTarget):      # the virtual target turns
                rig.camera.scene.angle = float(np.radians(check_target_deg))
            second = _sweep(ds, rig, angles, progress, "second sweep",
                            f"the direction check's second sweep (the first, {first.path.name}, is complete but unused: "
                            "calibration.json is written after both)")
            fit, check = fit_sweep(first, target_angle_deg), fit_sweep(second, check_target_deg)
            difference = check_direction(fit, target_angle_deg, check, check_target_deg)
            return calibrate_offset(ds, first, target_angle_deg, {
                "target_angle_deg": float(check_target_deg), "offset_deg": round(check.offset_deg, 5),
                "difference_deg": round(difference, 5), "sweep": second.path.relative_to(ds.root).as_posix()}, fit)


def _sweep(ds: Dataset, rig, angles: list[float], progress: Progress | None, label: str,
           what: str = "calibration sweep") -> Scene:
    """One sweep of the polarizer at ``angles`` (deg) into a new ``calibration/sweep_NN``; stopped,
    the message names it as ``what``."""
    sweep = ds.new_sweep(capture_plan_record(angles, 0.0, 0.5, rig.info))
    counter = iter(range(1, len(angles) + 1))
    try:
        run_capture(sweep, rig.stage, rig.camera, angles,
                    progress=lambda st: progress and st.kind == "record" and progress(next(counter), len(angles), label))
    except KeyboardInterrupt as exc:
        raise capture_stopped(exc, what, _left(sweep)) from None
    except (UrdError, OSError) as exc:
        raise UrdError(f"{exc}\n{what} stopped; {_left(sweep)}") from exc
    except BaseException:
        sweep.discard_if_empty()
        raise
    return sweep


def _left(sweep: Scene) -> str:
    """What a stopped sweep left: nothing, or its shots (a sweep is not resumed: the next
    'urd calibrate offset' sweeps anew and the calibration never uses an incomplete one)."""
    if sweep.discard_if_empty():
        return "no shot was taken, nothing was kept"
    return (f"its {len(sweep.shots())} shots are kept in {sweep.path.resolve()} (unused: an incomplete sweep is never "
            "fitted; delete it if you like); run 'urd calibrate offset' again for a new sweep")
