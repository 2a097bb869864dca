"""``urd calibrate offset`` (the mounting offset from a sweep) and ``urd calibrate shots`` (each shot's
angle error from a scene's images): the ``calibrate`` group."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from urd.cli.capture import SIM_SIZE_HELP
from urd.cli.common import (DATASET_HELP, HELP_OPTIONS, WorkflowOrder, check_address, check_rig, choice, parse_size, resolve_scene,
                            note_new_dataset, run_guarded, warn, within)
from urd.core.dataset import default_root
from urd.core.manifest import renew_command
from urd.core.progress import TerminalProgress


calibrate_app = typer.Typer(cls=WorkflowOrder, help="Measure the polarizer: mounting offset from a sweep, per-shot angle errors of a scene."
                                 "\n\n\b\nExample:\n  urd calibrate offset --stage /dev/ttyUSB0\n  urd calibrate shots scene_01",
                            no_args_is_help=True, rich_markup_mode=None, context_settings=HELP_OPTIONS)


@calibrate_app.command("offset")
def calibrate_offset_cmd(
    ctx: typer.Context,
    dataset: Optional[Path] = typer.Argument(None, help="Dataset whose polarizer to calibrate, where calibration.json is written (default: the current folder if it holds dataset.json, else ./dataset).", show_default=False),
    stage: str = typer.Option(..., help="Serial port of the ELL14 stage, or 'sim'."),
    camera: str = typer.Option("gphoto2", help="Camera driver: gphoto2 or virtual (needs --stage sim)."),
    step: float = typer.Option(10.0, callback=within(1.0, 45.0), help="Sweep step (deg), 1 to 45: one shot every STEP deg over 180 deg."),
    target_angle: float = typer.Option(0.0, callback=within(-360.0, 360.0), help="Polarization angle of the target's light (deg, image plane, CCW from x)."),
    check_direction: Optional[float] = typer.Option(None, callback=within(-360.0, 360.0), help="Check the stage's sense of rotation with a second sweep: after the first, turn the target's axis to this angle (deg, counter-clockwise as the camera sees it; 45 deg from --target-angle is best) and press Enter."),
    address: str = typer.Option("0", help="ELL14 device address 0-F.", callback=check_address),
    sim_offset: float = typer.Option(0.0, callback=within(-360.0, 360.0), help="[sim] true mounting offset of the simulated polarizer (deg)."),
    sim_size: str = typer.Option("256x192", help=SIM_SIZE_HELP),
    seed: int = typer.Option(0, callback=within(0), help="[sim/virtual] random seed."),
    sim_reversed: bool = typer.Option(False, "--sim-reversed", help="[sim] the simulated mount turned round: the stage turns the polarizer clockwise as the camera sees it."),
) -> None:
    """Sweep the polarizer in front of a polarized target and fit Malus's law for the mounting offset.

    \b
    Writes, in DATASET:
      calibration.json         the fitted offset, with the history of earlier fits
      calibration/sweep_NN/    the sweep: raw/shot_NN_ANGLEdeg.dng and scene.json
    Later captures with this stage use the offset. urd takes a positive stage move to turn the
    polarizer counter-clockwise as the camera sees it; --check-direction checks that with a
    second sweep (a mount turned round is refused, saying so).
    [sim] options need --stage sim, [virtual] options --camera virtual.

    \b
    Example:
      urd calibrate offset --stage /dev/ttyUSB0 --target-angle 90
      urd calibrate offset --stage sim --camera virtual --sim-offset 3
      urd calibrate offset --stage /dev/ttyUSB0 --target-angle 0 --check-direction 45
    """
    from acquire.camera import CameraKind
    from acquire.rig import SimSettings
    from urd.calibration import sweep_and_calibrate

    choice(CameraKind, camera, "--camera")
    width, height = parse_size(sim_size, "--sim-size")
    check_rig(ctx, stage, camera, ("sim_offset", "seed", "sim_reversed"), ("sim_size",))
    root = dataset or default_root()
    note_new_dataset(root)
    sim = SimSettings(offset_deg=sim_offset, width=width, height=height, shake_px=0, shake_deg=0, seed=seed,
                      target_angle_deg=target_angle, reversed=sim_reversed)

    def turn_target(angle: float) -> None:
        if stage != "sim":
            typer.prompt(f"turn the target's axis to {angle:g} deg (counter-clockwise as the camera sees it), then press "
                         "Enter", default="", show_default=False, err=True)

    bar = TerminalProgress()
    record = run_guarded(sweep_and_calibrate, root, stage, camera, step, target_angle, address, sim, progress=bar,
                         check_target_deg=check_direction, turn_target=lambda angle: (bar.close(), turn_target(angle)))
    typer.echo(f"mounting offset {record.offset_deg:.3f} ± {record.uncertainty_deg:.3f} deg "
               f"(modulation {record.modulation:.2f}); written to {(Path(root) / 'calibration.json').resolve()}")
    if record.direction is not None:
        typer.echo(f"sense of rotation: counter-clockwise, as urd takes it (the offsets at target angles {target_angle:g} "
                   f"and {check_direction:g} deg agree within {abs(record.direction['difference_deg']):.2f} deg)")
    else:
        typer.echo(f"sense of rotation not checked: add --check-direction {(target_angle + 45) % 180:g} (a second sweep with the "
                   "target turned by 45 deg counter-clockwise as the camera sees it)")


@calibrate_app.command("shots")
def calibrate_shots_cmd(
    scene: str = typer.Argument(..., help="Scene name (scene_12) or folder; must be ingested."),
    dataset: Optional[Path] = typer.Option(None, help=DATASET_HELP, show_default=False),
    apply: bool = typer.Option(True, help="Store the calibrated angles in the manifest (used by separation); --no-apply only prints them and leaves the manifest as it is."),
) -> None:
    """Estimate each shot's polarizer angle error from the images (needs 4+ angles; 5+ for all errors).

    \b
    Example:
      urd calibrate shots scene_01
      urd calibrate shots dataset/scene_01 --no-apply
    """
    from calib.store import TRIPOD_SHIFT_PX, TRIPOD_TURN_DEG, calibrate_shots, shot_motion

    target = run_guarded(resolve_scene, scene, dataset)
    stale_before = run_guarded(lambda: target.status().stale)
    result = run_guarded(calibrate_shots, target, apply)
    for i, (e, u) in enumerate(zip(result.errors_deg, result.uncertainty_deg)):
        typer.echo(f"shot {i}: {e:+.3f} ± {u:.3f} deg")
    if result.unobservable is not None:
        warn("with 4 angles one combination of the errors cannot be seen in the images "
             f"(direction {[round(v, 2) for v in result.unobservable]}); the smallest consistent "
             "correction is reported. Capture 5 or more angles to determine every error.")
    typer.echo("calibrated angles stored in the manifest" if apply else "manifest unchanged (--no-apply)")
    shift, turn = run_guarded(shot_motion, target)
    if shift > TRIPOD_SHIFT_PX or turn > TRIPOD_TURN_DEG:
        warn(f"the shots moved between frames (up to {shift:.1f} px and {turn:.2f} deg): per-shot angle errors need shots "
             "registered to a few hundredths of a pixel, which hand-held shots are not; calibrate from a tripod "
             "(--no-apply only reports the estimate)")
    for method in run_guarded(lambda: target.reload().status().stale):
        if method not in stale_before:
            warn(f"results of {method} are now stale (separated at other angles than the calibrated ones); renew them "
                 f"with: {renew_command(target.path, method)}")
