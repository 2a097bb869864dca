"""``urd capture`` (one scene on the rig, real or simulated) and ``urd sim-stage`` (a simulated ELL14
on a pseudo-terminal)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from urd.cli.common import (DATASET_HELP, bad, check_address, check_rig, choice, given, note_new_dataset, parse_angles, parse_size,
                            run_guarded, usage, within)
from urd.core.dataset import SCENE_NAME, default_root
from urd.core.progress import TerminalProgress


#: Options of ``urd capture`` that set the simulated stage (they need --stage sim) and the virtual
#: camera (they need --camera virtual); parameter names.
SIM_STAGE_OPTIONS = ("sim_offset", "sim_jitter", "sim_faults", "seed", "sim_reversed")
VIRTUAL_CAMERA_OPTIONS = ("sim_size", "sim_shake", "sim_turn", "reflection", "transmission")
#: The virtual camera's largest turn between shots (deg) when it shakes and --sim-turn is not given.
DEFAULT_TURN_DEG = 0.5

SIM_SIZE_HELP = "[virtual] sensor size WIDTHxHEIGHT (px), each side an even number from 32 to 20000."


def check_tolerance(value: float) -> float:
    """An option callback: the read-back tolerance (deg), within `acquire.plan`'s
    MIN_TOLERANCE_DEG..MAX_TOLERANCE_DEG (0.01 to 10)."""
    from acquire.plan import MAX_TOLERANCE_DEG, MIN_TOLERANCE_DEG

    return within(high=MAX_TOLERANCE_DEG)(within(MIN_TOLERANCE_DEG)(value))     # each bound's own message


def sim_settings(offset: float, jitter: float, faults: str, size: str, shake: float, reflection, transmission, seed: int,
                 reversed_mount: bool = False, turn: float | None = None):
    """Simulation knobs from the [sim]/[virtual] options."""
    from acquire.rig import SimSettings
    from acquire.sim_ell14 import parse_faults

    width, height = parse_size(size, "--sim-size")
    try:
        fault_map = parse_faults(faults)
    except ValueError as exc:
        raise bad("--sim-faults", str(exc)) from None
    turn = (DEFAULT_TURN_DEG if shake > 0 else 0.0) if turn is None else turn
    return SimSettings(offset, jitter, fault_map, width, height, shake, turn, reflection, transmission, seed, reversed=reversed_mount)


def capture(
    ctx: typer.Context,
    dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP + " Created when new.", show_default=False),
    stage: str = typer.Option(..., help="Serial port of the ELL14 stage (e.g. /dev/ttyUSB0), or 'sim' for the simulated stage."),
    camera: str = typer.Option("gphoto2", help="Camera driver: 'gphoto2' (real camera over USB) or 'virtual' (needs --stage sim)."),
    angles: str = typer.Option("0,45,90", help="Polarizer angles in degrees, comma-separated: at least 3 directions (mod 180) spread over the half turn, like 0,45,90."),
    scene: Optional[str] = typer.Option(None, help="Scene name scene_NN, like scene_01: an existing incomplete scene is resumed, a new name is created. Default: resume the newest incomplete scene (or write the ground truth a stopped capture did not finish), else the next free scene_NN."),
    new_scene: bool = typer.Option(False, "--new-scene", help="Start the next free scene_NN even if an incomplete one exists (not with --scene)."),
    tolerance: float = typer.Option(0.5, callback=check_tolerance, help="Largest accepted difference of read-back and commanded angle (deg), 0.01 to 10: at least the ELL14's encoder step of 0.0025, at most 10 so that a missed move is caught."),
    address: str = typer.Option("0", help="ELL14 device address 0-F.", callback=check_address),
    sim_offset: float = typer.Option(0.0, callback=within(-360.0, 360.0), help="[sim] polarizer mounting offset (deg)."),
    sim_jitter: float = typer.Option(0.0, callback=within(0.0), help="[sim] per-move angle error the encoder does not see, std (deg)."),
    sim_faults: str = typer.Option("", help="[sim] fault probabilities per command, e.g. drop=0.05,garble=0.05,mech_timeout=0.02,miss=0.02,vanish=0.01."),
    sim_reversed: bool = typer.Option(False, "--sim-reversed", help="[sim] the mount turned round: the stage turns the polarizer clockwise as the camera sees it (urd calibrate offset --check-direction finds it out)."),
    sim_size: str = typer.Option("1536x1024", help=SIM_SIZE_HELP),
    sim_shake: float = typer.Option(4.0, callback=within(0.0), help="[virtual] camera shake between shots: max translation (px), with a turn of up to --sim-turn; 0 is a tripod (neither)."),
    sim_turn: Optional[float] = typer.Option(None, callback=within(0.0, 5.0), help="[virtual] largest turn of the camera between shots (deg, 0 to 5; the polarizer turns with it); default 0.5 with --sim-shake above 0, else 0.", show_default=False),
    reflection: Optional[Path] = typer.Option(None, help="[virtual] image file reflected in the glass (default: bundled photo)."),
    transmission: Optional[Path] = typer.Option(None, help="[virtual] image file seen through the glass (default: bundled photo)."),
    seed: int = typer.Option(0, callback=within(0), help="[sim/virtual] random seed."),
) -> None:
    """Capture one scene: home the polarizer stage, then move, verify, trigger and download at each angle.

    An interrupted capture is resumed by the next 'urd capture' (or with --scene NAME).

    \b
    Writes, in DATASET/scene_NN/:
      raw/shot_NN_ANGLEdeg.dng   each shot's RAW file, e.g. shot_01_045.0deg.dng
                                 (the camera's own RAW suffix with gphoto2)
      scene.json                 the manifest: plan, devices, angles, SHA-256 of each file
      truth/                     simulated captures (--camera virtual): the true layers
    [sim] options need --stage sim, [virtual] options --camera virtual.

    \b
    Example:
      urd capture --stage sim --camera virtual
      urd capture dataset --stage /dev/ttyUSB0 --angles 0,45,90,135
    """
    from acquire.camera import CameraKind
    from acquire.plan import capture_scene

    choice(CameraKind, camera, "--camera")
    if scene is not None and not SCENE_NAME.match(scene):
        raise bad("--scene", f"expected a scene name like scene_01, got {scene!r}")
    if scene is not None and new_scene:
        raise usage(f"--scene {scene} and --new-scene do not go together: --scene names the scene to capture (resumed "
                    "when incomplete, created when new), --new-scene starts the next free scene_NN; give one of them")
    for option, path in (("--reflection", reflection), ("--transmission", transmission)):
        if path is not None and not path.is_file():
            raise bad(option, f"{path}: no such image file")
    angle_list = parse_angles(angles) if given(ctx, "angles") else None
    sim = sim_settings(sim_offset, sim_jitter, sim_faults, sim_size, sim_shake, reflection, transmission, seed, sim_reversed,
                       sim_turn)
    check_rig(ctx, stage, camera, SIM_STAGE_OPTIONS, VIRTUAL_CAMERA_OPTIONS)
    root = dataset or default_root()
    note_new_dataset(root)
    bar = TerminalProgress()
    result = run_guarded(capture_scene, root, stage, camera, angle_list, scene, new_scene,
                         tolerance if given(ctx, "tolerance") else None, address, sim,
                         announce=lambda line: (bar.break_line(), typer.echo(line)), progress=bar)
    typer.echo(f"scene complete: {result.path.resolve()}")


def sim_stage(
    address: str = typer.Option("0", help="Device address 0-F.", callback=check_address),
    offset: float = typer.Option(0.0, callback=within(-360.0, 360.0), help="Polarizer mounting offset the encoder does not see (deg)."),
    jitter: float = typer.Option(0.0, callback=within(0.0), help="Per-move angle error the encoder does not see, std (deg)."),
    faults: str = typer.Option("", help="Fault probabilities per command, e.g. drop=0.05,garble=0.05,mech_timeout=0.02,miss=0.02,vanish=0.01."),
    seed: int = typer.Option(0, callback=within(0), help="Random seed of jitter and faults."),
) -> None:
    """Serve a simulated ELL14 rotation mount on a pseudo-terminal until Ctrl-C (to test any Elliptec client).

    \b
    Example:
      urd sim-stage --offset 2 --faults drop=0.05
    """
    from acquire.sim_ell14 import SimulatedEll14, parse_faults, serve

    try:
        fault_map = parse_faults(faults)
    except ValueError as exc:
        raise bad("--faults", str(exc)) from None
    with SimulatedEll14(address, sim_offset_deg=offset, sim_jitter_deg=jitter, sim_faults=fault_map, seed=seed) as sim:
        run_guarded(serve, sim, typer.echo)
