"""Calibration from images, and its records in a dataset.

The mounting offset comes from a sweep: a scene under ``calibration/sweep_NN`` (`Dataset.new_sweep`
creates it; the workflow that captures and fits it is `urd.calibration`) whose shots see a
polarized target; `sweep_intensities` reads what the fit needs from it, and the fit is stored in
``calibration.json`` (`Dataset.save_calibration`, with the history of earlier fits). Per-shot
angle errors of an ingested scene go into its manifest (`calibrate_shots`,
`Scene.set_shot_calibration`). This package knows no device: a capture reads the stored offset
itself (`acquire.rig.offset_for_stage`).
"""

from __future__ import annotations

import math

from calib.polarizer import ShotErrors, estimate_shot_errors
from urd.core import raw as rawio
from urd.core.dataset import Scene
from urd.core.errors import CalibrationError


def sweep_intensities(scene: Scene) -> tuple[list[float], list[float]]:
    """Stage angles (deg) and mean central-crop intensities of a sweep scene's shots.
    CalibrationError when a shot records no stage angle (the scene is no sweep urd captured)."""
    shots = scene.shots()
    unknown = next((shot for shot in shots if shot.stage_position_deg is None), None)
    if unknown is not None:
        raise CalibrationError(f"{scene.manifest_path}: shot {unknown.index} records no stage angle "
                               "(stage_position_deg), which every shot of a calibration sweep has")
    angles, values = [], []
    for shot, path in zip(shots, scene.raw_paths()):
        image = rawio.decode(path, half_size=True)
        h, w = image.shape[:2]
        values.append(float(image[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4].mean()))
        angles.append(float(shot.stage_position_deg))
    return angles, values


#: Camera motion between the shots (px of shift, deg of turn) above which the shots were not taken
#: from a tripod: per-shot angle errors need shots registered to a few hundredths of a pixel.
TRIPOD_SHIFT_PX, TRIPOD_TURN_DEG = 0.5, 0.05


def shot_motion(scene: Scene) -> tuple[float, float]:
    """The largest shift (px) and turn (deg) of a shot against the reference that the scene's
    ingest recorded (0, 0 for a mosaic frame, registered as taken)."""
    alignment = scene.load(verify=False)["ingest"].get("alignment")
    warps = [entry["warp"] for entry in alignment if entry.get("warp")] if isinstance(alignment, list) else []
    shift = max((math.hypot(w[0][2], w[1][2]) for w in warps), default=0.0)
    return shift, max((abs(turn) for turn in scene.frame_turns_deg()), default=0.0)


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
