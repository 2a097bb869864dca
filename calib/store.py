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

import numpy as np

from calib.polarizer import ShotErrors, estimate_shot_errors
from urd.core import raw as rawio
from urd.core.dataset import Scene
from urd.core.errors import CalibrationError
from urd.core.images import stored_tiff_layout


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
    """The largest shift (px, of the frame's centre: a warp turns about pixel (0, 0)) and turn (deg)
    of a shot against the reference that the scene's ingest recorded (0, 0 for a mosaic frame,
    registered as taken)."""
    ingest = scene.load(verify=False)["ingest"]
    alignment = ingest.get("alignment")
    warps = [np.asarray(entry["warp"], np.float64)[:2] for entry in alignment if entry.get("warp")] \
        if isinstance(alignment, list) else []
    if not warps:
        return 0.0, 0.0
    height, width = stored_tiff_layout(scene.path / ingest["aligned"][0]["file"])[0][:2]
    centre = np.array([width / 2.0, height / 2.0, 1.0])
    shift = max(float(np.hypot(*(w @ centre - centre[:2]))) for w in warps)
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
