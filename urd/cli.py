"""The ``urd`` command line: a thin layer. Each command parses its options, calls one workflow
function (acquire.plan, urd.ingest, urd.calibration, calib.store, urd.separation, urd.report, urd.demo,
separate.train, separate.bench) and prints.

Angles are degrees here and in manifests. Errors print one line in one voice, "Error: ...":
bad arguments name the option ("Invalid value for '--method': ...") and exit with status 2,
failures exit with status 1 (130 after Ctrl-C). Output paths are printed absolute.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Optional

import typer

from urd import __version__
from urd.core.dataset import default_root
from urd.core.errors import CaptureInterrupted, DatasetError, UrdError
from urd.core.processes import Terminated, terminate_on_sigterm
from urd.core.progress import TerminalProgress, plural

DATASET_HELP = "Dataset folder (default: the current folder if it holds dataset.json, else ./dataset)."
HELP_OPTIONS = {"help_option_names": ["-h", "--help"]}

class WorkflowOrder(typer.core.TyperGroup):
    """Lists the commands in the order of the work: capture, calibrate, ingest, separate, look."""

    ORDER = ("capture", "calibrate", "ingest", "separate", "report", "verify", "demo", "train", "bench", "sim-stage")

    def list_commands(self, ctx) -> list[str]:
        order = {name: k for k, name in enumerate(self.ORDER)}
        return sorted(super().list_commands(ctx), key=lambda name: order.get(name, len(order)))

    def format_commands(self, ctx, formatter) -> None:
        """Each command with its whole first sentence (wrapped, never cut with "...")."""
        commands = [(name, self.get_command(ctx, name)) for name in self.list_commands(ctx)]
        rows = [(name, command.get_short_help_str(limit=1000)) for name, command in commands
                if command is not None and not command.hidden]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


app = typer.Typer(
    cls=WorkflowOrder,
    help="urd: photograph scenes through glass with a rotating polarizer and separate reflection from transmission.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings=HELP_OPTIONS,
)


def show_version(value: bool) -> None:
    if value:
        typer.echo(f"urd {__version__}")
        raise typer.Exit()


@app.callback()
def main_options(
    version: bool = typer.Option(False, "--version", callback=show_version, is_eager=True, help="Print urd's version and exit."),
) -> None:
    """urd: photograph scenes through glass with a rotating polarizer and separate reflection from transmission."""


def fail(message: str, code: int = 1) -> None:
    """Print an error line in the voice of usage errors ("Error: ...") and exit with ``code``."""
    typer.secho(f"Error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


def bad(option: str, message: str) -> typer.BadParameter:
    """A usage error (exit 2) naming ``option``: "Invalid value for '--option': message"."""
    return typer.BadParameter(message, param_hint=f"'{option}'")


class OptionClash(typer.BadParameter):
    """A usage error (exit 2) about options that do not go together; its message names them."""

    def format_message(self) -> str:
        return self.message


def usage(message: str) -> OptionClash:
    """An `OptionClash` saying ``message``."""
    return OptionClash(message)


def within(low: float | None = None, high: float | None = None):
    """An option callback: the value, or a usage error naming the option when it is below ``low`` or above ``high``."""
    def check(value):
        if value is not None and ((low is not None and value < low) or (high is not None and value > high)):
            expected = (f"between {low:g} and {high:g}" if low is not None and high is not None
                        else f"at least {low:g}" if low is not None else f"at most {high:g}")
            raise typer.BadParameter(f"expected {expected}, got {value:g}")
        return value
    return check


def given(ctx: typer.Context, name: str) -> bool:
    """True when the option ``name`` was given (on the command line or by the environment), not
    left at its default."""
    return ctx.get_parameter_source(name).name != "DEFAULT"


def check_address(value: str) -> str:
    """An ELL14 address: one hex digit 0-F (upper case)."""
    if not re.fullmatch(r"[0-9A-Fa-f]", value):
        raise typer.BadParameter(f"expected one hex digit 0-F, got {value!r}")
    return value.upper()


def choice(kind: type[enum.Enum], value: str, option: str) -> enum.Enum:
    """The member of ``kind`` whose value is ``value``; a bad parameter listing the choices otherwise."""
    try:
        return kind(value)
    except ValueError:
        names = [member.value for member in kind]
        raise typer.BadParameter(f"expected one of {', '.join(names)}, got {value!r}", param_hint=f"'{option}'") from None


def existing_dataset(dataset: Optional[Path]) -> Path:
    """The dataset a command reads: ``dataset``, else `urd.core.dataset.default_root`; an error saying
    how to make one when its folder does not exist."""
    root = dataset or default_root()
    if not root.exists():
        fail(f"no dataset: {root.resolve()} does not exist. Make one with 'urd capture --stage PORT' or "
             "'urd ingest RAW_FOLDER' (both create ./dataset by default), or name an existing dataset folder")
    return root


def warn(message: str) -> None:
    typer.secho(f"warning: {message}", fg=typer.colors.YELLOW, err=True)


def run_guarded(func, *args, **kwargs):
    """Call ``func`` with a progress line on stderr, turning urd's errors into a one-line
    message and exit status 1 (130 for Ctrl-C)."""
    bar = kwargs.get("progress")
    try:
        return func(*args, **kwargs)
    except CaptureInterrupted as exc:
        end_line(bar)
        fail(str(exc), 130)
    except (UrdError, ValueError, OSError) as exc:
        end_line(bar)
        fail(str(exc))
    except KeyboardInterrupt as exc:
        end_line(bar)
        stopped = "stopped by SIGTERM" if isinstance(exc, Terminated) else "interrupted"
        kept = "; ".join(getattr(exc, "__notes__", [])) or "completed files are kept, unfinished outputs were discarded"
        fail(f"{stopped}; {kept}", 143 if isinstance(exc, Terminated) else 130)
    finally:
        end_line(bar)


def end_line(bar) -> None:
    """End a progress line before other output."""
    if isinstance(bar, TerminalProgress):
        bar.close()


def parse_angles(text: str, min_distinct: int = 3, option: str = "--angles") -> list[float]:
    """'0,45,90' → [0.0, 45.0, 90.0] (degrees): finite, no direction twice (mod 180), at least
    ``min_distinct`` of them."""
    try:
        angles = [float(a) for a in text.split(",") if a.strip()]
    except ValueError:
        raise bad(option, f"expected comma-separated degrees like 0,45,90, got {text!r}") from None
    if not all(math.isfinite(a) for a in angles):
        raise bad(option, f"expected finite angles in degrees, got {text!r}")
    directions = [round(a % 180.0, 6) for a in angles]
    if len(set(directions)) != len(directions):
        raise bad(option, f"expected each polarizer direction once (angles are the same mod 180 deg), got {text!r}")
    if len(angles) < min_distinct:
        raise bad(option, f"expected at least {min_distinct} distinct polarizer angles (mod 180), got {text!r}")
    return angles


def parse_params(items: list[str], option: str = "--param") -> dict:
    """['smoothness=0.5', 'theta_deg=35'] → {'smoothness': 0.5, 'theta_deg': 35} (JSON values, else text)."""
    params = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise bad(option, f"expected NAME=VALUE, got {item!r}")
        try:
            params[name] = json.loads(value)
        except json.JSONDecodeError:
            params[name] = value
    return params


def parse_size(text: str, option: str = "--size") -> tuple[int, int]:
    """'1536x1024' → (1536, 1024), each side 16 to 20000 px."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise bad(option, f"expected WIDTHxHEIGHT like 1536x1024, got {text!r}") from None
    if not (16 <= w <= 20000 and 16 <= h <= 20000):
        raise bad(option, f"expected each side between 16 and 20000 px, got {text!r}")
    return w, h


def parse_seeds(text: str, option: str = "--seeds") -> list[int]:
    """'0,1' → [0, 1]: at least two different non-negative integers."""
    try:
        seeds = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise bad(option, f"expected comma-separated integers like 0,1, got {text!r}") from None
    if len(set(seeds)) < 2 or min(seeds) < 0:
        raise bad(option, f"expected at least two different non-negative seeds, got {text!r}")
    return seeds


def parse_reference(text: str, option: str = "--reference") -> str | float:
    """'auto', 'global' or degrees."""
    if text in ("auto", "global"):
        return text
    try:
        value = float(text)
    except ValueError:
        raise bad(option, f"expected 'auto', 'global' or an angle in degrees, got {text!r}") from None
    if not math.isfinite(value):
        raise bad(option, f"expected a finite angle, got {text!r}")
    return value % 180.0


def sim_settings(offset: float, jitter: float, faults: str, size: str, shake: float, reflection, transmission, seed: int):
    """Simulation knobs from the [sim]/[virtual] options."""
    from acquire.rig import SimSettings
    from acquire.sim_ell14 import parse_faults

    width, height = parse_size(size, "--sim-size")
    try:
        fault_map = parse_faults(faults)
    except ValueError as exc:
        raise bad("--sim-faults", str(exc)) from None
    return SimSettings(offset, jitter, fault_map, width, height, shake, 0.5, reflection, transmission, seed)


@app.command()
def capture(
    ctx: typer.Context,
    dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP + " Created when new.", show_default=False),
    stage: str = typer.Option(..., help="Serial port of the ELL14 stage (e.g. /dev/ttyUSB0), or 'sim' for the simulated stage."),
    camera: str = typer.Option("gphoto2", help="Camera driver: 'gphoto2' (real camera over USB) or 'virtual' (needs --stage sim)."),
    angles: str = typer.Option("0,45,90", help="Polarizer angles in degrees, comma-separated (at least 3 distinct)."),
    scene: Optional[str] = typer.Option(None, help="Scene name; an existing incomplete scene is resumed. Default: resume the newest incomplete scene, else the next free scene_NN."),
    new_scene: bool = typer.Option(False, "--new-scene", help="Start a new scene even if an incomplete one exists."),
    tolerance: float = typer.Option(0.5, callback=within(0.0), help="Largest accepted difference of read-back and commanded angle (deg)."),
    address: str = typer.Option("0", help="ELL14 device address 0-F.", callback=check_address),
    sim_offset: float = typer.Option(0.0, help="[sim] polarizer mounting offset (deg)."),
    sim_jitter: float = typer.Option(0.0, callback=within(0.0), help="[sim] per-move angle error the encoder does not see, std (deg)."),
    sim_faults: str = typer.Option("", help="[sim] fault probabilities per command, e.g. drop=0.05,garble=0.05,mech_timeout=0.02,miss=0.02,vanish=0.01."),
    sim_size: str = typer.Option("1536x1024", help="[virtual] sensor size WIDTHxHEIGHT."),
    sim_shake: float = typer.Option(4.0, callback=within(0.0), help="[virtual] camera shake between shots, max translation (px)."),
    reflection: Optional[Path] = typer.Option(None, help="[virtual] image file reflected in the glass (default: bundled photo)."),
    transmission: Optional[Path] = typer.Option(None, help="[virtual] image file seen through the glass (default: bundled photo)."),
    seed: int = typer.Option(0, help="[sim/virtual] random seed."),
) -> None:
    """Capture one scene: home the polarizer stage, then move, verify, trigger and download at each angle.

    An interrupted capture is resumed by the next 'urd capture' (or with --scene NAME).

    \b
    Example:
      urd capture --stage sim --camera virtual
      urd capture dataset --stage /dev/ttyUSB0 --angles 0,45,90,135
    """
    from acquire.camera import CameraKind
    from acquire.plan import capture_scene

    choice(CameraKind, camera, "--camera")
    angle_list = parse_angles(angles) if given(ctx, "angles") else None
    sim = sim_settings(sim_offset, sim_jitter, sim_faults, sim_size, sim_shake, reflection, transmission, seed)
    bar = TerminalProgress()
    result = run_guarded(capture_scene, dataset or default_root(), stage, camera, angle_list, scene, new_scene,
                         tolerance if given(ctx, "tolerance") else None, address, sim,
                         announce=lambda line: (bar.break_line(), typer.echo(line)), progress=bar)
    typer.echo(f"scene complete: {result.path.resolve()}")


@app.command("sim-stage")
def sim_stage(
    address: str = typer.Option("0", help="Device address 0-F.", callback=check_address),
    offset: float = typer.Option(0.0, help="Polarizer mounting offset the encoder does not see (deg)."),
    jitter: float = typer.Option(0.0, callback=within(0.0), help="Per-move angle error the encoder does not see, std (deg)."),
    faults: str = typer.Option("", help="Fault probabilities per command, e.g. drop=0.05,garble=0.05,mech_timeout=0.02,miss=0.02,vanish=0.01."),
    seed: int = typer.Option(0, help="Random seed of jitter and faults."),
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


@app.command()
def ingest(
    ctx: typer.Context,
    source: Path = typer.Argument(..., help="A folder of RAW shots, a captured scene folder, a dataset folder, or (with --mosaic) polarization-camera frames."),
    dataset: Optional[Path] = typer.Argument(None, help="Dataset to add scenes to when SOURCE is a RAW folder or mosaics (default: the current folder if it holds dataset.json, else ./dataset).", show_default=False),
    angles: str = typer.Option("0,45,90", help="Polarizer angles of consecutive shots (deg), for RAW folders without a capture manifest."),
    motion: str = typer.Option("euclidean", help="Alignment model: translation, euclidean or homography."),
    half_size: bool = typer.Option(False, help="Decode at half resolution (one pixel per 2x2 CFA tile; ~4x faster)."),
    gap: float = typer.Option(60.0, callback=within(0.0), help="Seconds between shots that start a new scene when grouping by capture time."),
    redo: bool = typer.Option(False, help="Decode and align again scenes that are already ingested (the old aligned stack is replaced only on success)."),
    mosaic: Optional[str] = typer.Option(None, help="SOURCE holds polarization-camera frames (PNG/TIFF) with this layout: imx250mzr, imx250myr or wen2019; one scene per frame."),
    demosaic: str = typer.Option("newton", help="Demosaicing of --mosaic frames: none (sites as they are, unregistered), bilinear, newton (registers the four polarizer sites)."),
    transfer: str = typer.Option("linear", help="8-bit frames: linear (sensor codes, polarization cameras) or srgb (photos from ordinary cameras). 16-bit frames are always linear."),
    jobs: int = typer.Option(1, callback=within(1), help="Worker processes for the scenes of a dataset (SOURCE a dataset folder): each decodes and aligns one scene at a time."),
) -> None:
    """Decode RAW shots to linear images, group them into scenes and align each scene (ECC).

    Already-ingested files (same SHA-256) are skipped; incomplete captures are reported.

    \b
    Example:
      urd ingest raw/
      urd ingest raw/ dataset --angles 0,45,90,135
      urd ingest dataset --jobs 2
    """
    from urd.core.align import Motion
    from urd.core.images import Transfer
    from urd.ingest import IngestOptions, ingest as ingest_workflow

    opts = IngestOptions(tuple(parse_angles(angles)), choice(Motion, motion, "--motion"), half_size, gap, redo)
    layout = method = None
    if mosaic:
        from urd.core.mosaic import Demosaic, MosaicLayout

        layout, method = choice(MosaicLayout, mosaic, "--mosaic"), choice(Demosaic, demosaic, "--demosaic")
    transfer_rule = choice(Transfer, transfer, "--transfer")
    if not source.exists():
        raise bad("SOURCE", f"{source}: no such folder or file")
    if source.is_file() and not mosaic:
        raise bad("SOURCE", f"{source} is a file; ingest takes a folder (of RAW shots, a captured scene, or a "
                                 "dataset): put the shots in a folder and pass that")
    recorded = (source / "scene.json").is_file() or (source / "dataset.json").is_file()
    if recorded and given(ctx, "angles"):
        raise usage("a scene's angles are in its manifest; --angles is for a folder of RAW files. To "
                                 "record other angles, move the scene folder away and ingest its raw/ files again")
    if jobs > 1 and (not recorded or mosaic):
        raise usage("--jobs is for a dataset or scene folder; a RAW folder or mosaic frames are ingested "
                                 "by one process (ingest them, then the dataset with --jobs)")
    unused = [f"--{name}" for name in ("demosaic", "transfer") if given(ctx, name)]
    if unused and not mosaic:
        raise usage(f"{', '.join(unused)}: for --mosaic frames")
    report = run_guarded(ingest_workflow, source, dataset or default_root(), opts, layout, method, transfer_rule,
                         progress=TerminalProgress(), jobs=jobs)
    for path in report.ignored:
        typer.echo(f"ignored (not a RAW file name): {path.resolve()}", err=True)
    for note in report.notes:
        warn(note)
    for outcome in report.outcomes:
        where = outcome.name or ", ".join(p.name for p in outcome.files)
        if outcome.state == "failed":
            typer.secho(f"FAILED {where}: {outcome.error}", fg=typer.colors.RED, err=True)
        elif outcome.state == "ingested":
            names = ", ".join(p.name for p in outcome.files)
            origin = f"from {len(outcome.files)} files" if len(outcome.files) > 3 else f"from {names}"
            typer.echo(f"ingested {outcome.name} ({origin})")
        else:
            typer.echo(f"{outcome.state} {where}: {outcome.error}")
    if not report.outcomes:
        typer.echo("nothing to ingest")
    if report.failed:
        failed = len(report.failed)
        fail(f"{failed} of {plural(len(report.outcomes), 'scene')} {'failed or was' if failed == 1 else 'failed or were'} flagged")


calibrate_app = typer.Typer(cls=WorkflowOrder, help="Measure the polarizer: mounting offset from a sweep, per-shot angle errors of a scene."
                                 "\n\n\b\nExample:\n  urd calibrate offset --stage /dev/ttyUSB0\n  urd calibrate shots scene_01",
                            no_args_is_help=True, rich_markup_mode=None, context_settings=HELP_OPTIONS)
app.add_typer(calibrate_app, name="calibrate")


def resolve_scene(scene: str, dataset: Optional[Path]):
    """A scene given by folder path, or by name in ``dataset`` (default: ``default_root()``)."""
    from urd.core.dataset import Dataset, Scene

    path = Path(scene)
    if (path / "scene.json").is_file():
        return Scene(path)
    ds = Dataset.open(existing_dataset(dataset))
    if scene not in ds.scene_names():
        raise bad("SCENE", f"no scene {scene!r} in {ds.root.resolve()} (scenes: {', '.join(ds.scene_names()) or 'none'}); "
                           "give a scene's name, or its folder")
    return ds.scene(scene)


@calibrate_app.command("offset")
def calibrate_offset_cmd(
    dataset: Optional[Path] = typer.Argument(None, help="Dataset whose polarizer to calibrate, where calibration.json is written (default: the current folder if it holds dataset.json, else ./dataset).", show_default=False),
    stage: str = typer.Option(..., help="Serial port of the ELL14 stage, or 'sim'."),
    camera: str = typer.Option("gphoto2", help="Camera driver: gphoto2 or virtual."),
    step: float = typer.Option(10.0, callback=within(1.0, 45.0), help="Sweep step (deg) over 180 deg."),
    target_angle: float = typer.Option(0.0, help="Polarization angle of the target's light (deg, image plane, CCW from x)."),
    address: str = typer.Option("0", help="ELL14 device address 0-F.", callback=check_address),
    sim_offset: float = typer.Option(0.0, help="[sim] true mounting offset of the simulated polarizer (deg)."),
    seed: int = typer.Option(0, help="[sim/virtual] random seed."),
) -> None:
    """Sweep the polarizer in front of a polarized target and fit Malus's law for the mounting offset.

    \b
    Example:
      urd calibrate offset --stage /dev/ttyUSB0 --target-angle 90
      urd calibrate offset --stage sim --camera virtual --sim-offset 3
    """
    from acquire.camera import CameraKind
    from acquire.rig import SimSettings
    from urd.calibration import sweep_and_calibrate

    choice(CameraKind, camera, "--camera")
    root = dataset or default_root()
    sim = SimSettings(offset_deg=sim_offset, width=256, height=192, shake_px=0, shake_deg=0, seed=seed,
                      target_angle_deg=target_angle)
    record = run_guarded(sweep_and_calibrate, root, stage, camera, step, target_angle, address, sim, progress=TerminalProgress())
    typer.echo(f"mounting offset {record.offset_deg:.3f} ± {record.uncertainty_deg:.3f} deg "
               f"(modulation {record.modulation:.2f}); written to {(Path(root) / 'calibration.json').resolve()}")


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
    from calib.store import calibrate_shots

    result = run_guarded(lambda: calibrate_shots(resolve_scene(scene, dataset), apply))
    for i, (e, u) in enumerate(zip(result.errors_deg, result.uncertainty_deg)):
        typer.echo(f"shot {i}: {e:+.3f} ± {u:.3f} deg")
    if result.unobservable is not None:
        warn("with 4 angles one combination of the errors cannot be seen in the images "
             f"(direction {[round(v, 2) for v in result.unobservable]}); the smallest consistent "
             "correction is reported. Capture 5 or more angles to determine every error.")
    typer.echo("calibrated angles stored in the manifest" if apply else "manifest unchanged (--no-apply)")


@app.command()
def separate(
    ctx: typer.Context,
    scene: Optional[str] = typer.Argument(None, help="Scene name (scene_12) in --dataset, or a scene folder. Omit with --images."),
    dataset: Optional[Path] = typer.Option(None, help=DATASET_HELP, show_default=False),
    method: str = typer.Option("network", help="network (the paper's, shipped weights); baselines: schechner, kong, farid (polarization), li-brown, arvanitopoulos, ceilnet (single image: they see S0 only); none (T = S0)."),
    images: Optional[list[Path]] = typer.Option(None, "--images", help="Separate image files instead of a scene (repeat: one file per angle, 3 or more)."),
    angles: str = typer.Option("0,45,90", help="Polarizer angles of --images (deg)."),
    transfer: str = typer.Option("linear", help="8-bit --images: linear (sensor codes) or srgb (ordinary photos). 16-bit files are always linear."),
    out: Path = typer.Option(Path("separated"), help="Output folder for --images."),
    reference: str = typer.Option("auto", help="Reference angle (deg): the glass's s-direction, where the reflection is brightest; 'auto' estimates it per pixel from the shots (a smooth field, for wide views and curved panes), 'global' one angle for the whole view."),
    weights: Optional[Path] = typer.Option(None, help="Weights file of the network or ceilnet, or a shipped one by name: urd-anchored (the default: the network anchored to the Fresnel inversion by a learned gate), urd-canonical (the same network without the gate), urd-canonical-transposed (the paper's decoder), urd-direct, ceilnet."),
    tile: Optional[int] = typer.Option(None, help="Network tile size (px, at least 320: twice the 160 px overlap; default 2048 for the network, 1024 for ceilnet: separate.infer.default_tile); memory grows with it, not with the image.", show_default=False),
    precision: str = typer.Option("auto", help="Network arithmetic: auto (bf16 where the CPU or GPU runs it natively, else fp32), fp32 or bf16."),
    device: str = typer.Option("auto", help="Where the network runs: auto (a CUDA GPU where torch sees one, else the CPU), cpu or cuda."),
    colour_match: bool = typer.Option(False, help="Match each colour channel's histogram of T to the darkest observation's (paper §3.4)."),
    return_copies: Optional[bool] = typer.Option(None, "--return-copies/--keep-copies", help="Network: move light that R shows as a local copy of T (the scene's own polarization: sky, no glass) back into T (separate/copies.py). Default: --return-copies.", show_default=False),
    incidence: Optional[float] = typer.Option(None, "--incidence", help="Network: the angle of incidence on the glass (deg, between the camera's axis and the pane's normal) where you know it; the network's Fresnel gate uses it instead of the estimate from the shots. Schechner takes it as --param theta_deg=DEG.", show_default=False),
    param: Optional[list[str]] = typer.Option(None, "--param", help="A baseline's parameter as NAME=VALUE (repeat), e.g. --method kong --param smoothness=0.5; names and paper defaults in each baseline's docstring (separate/baselines/)."),
    force: bool = typer.Option(False, help="Replace existing results of this method (only once the new ones are complete)."),
    maps: bool = typer.Option(False, "--maps", help="Also write the polarization maps: S0, S1, S2, DoLP, AoLP, phi_perp, theta as float32 TIFF with units (results/METHOD/maps/); on a scene that has results of the method, adds the maps to them without separating again."),
    all_scenes: bool = typer.Option(False, "--all", help="Every ingested scene of the dataset without results of this method (with --force: every ingested scene)."),
    jobs: int = typer.Option(1, callback=within(1), help="With --all: worker processes, each on cores/jobs threads."),
) -> None:
    """Separate a scene into reflection R and transmission T (linear 16-bit TIFF, sRGB previews,
    a reflection-presence map and the reference angle used), or every scene with --all.

    \b
    Example:
      urd separate scene_01
      urd separate scene_01 --method kong --param smoothness=0.5
      urd separate --all --jobs 2 --dataset dataset
      urd separate scene_01 --maps --reference global
      urd separate --images a.tif --images b.tif --images c.tif --angles 0,45,90 --transfer srgb
    """
    from separate.infer import OVERLAP, check_tiling
    from separate.methods import METHODS, get_method
    from separate.precision import describe, resolve, resolve_device
    from urd.core.images import Transfer
    from urd.core.raw import RAW_SUFFIXES
    from urd.separation import add_maps, check_out_folder, describe_incidence, sees_polarization_of, separate_images, separate_scene

    if method not in METHODS:
        raise bad("--method", f"expected one of {', '.join(sorted(METHODS))}, got {method!r}")
    raws = [Path(name).name for name in [*(images or []), *([scene] if scene else [])]
            if Path(name).suffix.lower() in RAW_SUFFIXES]
    if raws:
        raise usage(f"{', '.join(raws)}: RAW files; separate takes an ingested scene, or with --images "
                                 "decoded images (TIFF, PNG, JPEG). Ingest RAW shots with 'urd ingest FOLDER', "
                                 "then run 'urd separate SCENE'")
    if all_scenes and (scene is not None or images):
        raise usage("expected --all alone, without a scene name or --images")
    if jobs > 1 and not all_scenes:
        raise usage("--jobs is for --all (one scene runs in one process)")
    if images is None and scene is None and not all_scenes:
        raise usage("expected a scene name, --all or --images")
    if images and scene is not None:
        raise usage(f"expected a scene name or --images, not both (got {scene!r} and --images)")
    networks = ("network", "ceilnet")
    unused = [f"--{name.replace('_', '-')}" for name in ("weights", "tile", "precision", "device", "colour_match")
              if given(ctx, name)]
    if unused and method not in networks:
        raise usage(f"{', '.join(unused)}: for the networks (network, ceilnet), not {method}")
    unused = [f"--{name}" for name in ("angles", "out", "transfer") if given(ctx, name)]
    if unused and not images:
        raise usage(f"{', '.join(unused)}: for --images; a scene's angles come from its manifest and its "
                                 "results go into the scene's results/METHOD/")
    try:
        network_device = resolve_device(device) if method in networks else None
    except ValueError as exc:
        raise bad("--device", str(exc)) from None
    try:
        chosen = resolve(precision, network_device or "cpu")
    except ValueError as exc:
        raise bad("--precision", str(exc)) from None
    try:
        if tile is not None and method in networks:
            check_tiling(tile, OVERLAP)
    except ValueError as exc:
        raise bad("--tile", str(exc)) from None
    transfer_rule = choice(Transfer, transfer, "--transfer")
    if return_copies is not None and method != "network":
        raise usage(f"--return-copies/--keep-copies is for the network, not {method}")
    return_copies = return_copies is not False
    if incidence is not None and method != "network":
        raise usage(f"--incidence is for the network, not {method}" + (
            " (use --param theta_deg=DEG)" if method == "schechner" else ""))
    if incidence is not None and not 0 < incidence < 90:
        raise bad("--incidence", f"expected between 0 and 90 deg, got {incidence:g}")
    if param and method in networks + ("none",):
        raise usage(f"--param is for the baselines; {method} takes its own options")
    params = parse_params(param or [])
    forced = parse_reference(reference)
    angle_list = parse_angles(angles) if images else None
    if images:
        try:
            check_out_folder(out, method)
        except DatasetError as exc:
            raise bad("--out", str(exc)) from None
    if images and len(images) != len(angle_list):
        raise usage(f"expected one --images file per angle of --angles {angles}, got {len(images)} files")
    if all_scenes:
        separate_dataset(dataset, method, weights, tile, chosen, colour_match, return_copies, incidence, params, force,
                         forced, maps, jobs, network_device)
        return
    target = None if images else run_guarded(resolve_scene, scene, dataset)
    if target is not None and maps and not force and method in target.methods():
        result = run_guarded(add_maps, target, method, forced)
        typer.echo(f"added the polarization maps to {target.name}'s {method} results (a Stokes fit; not separated again)")
        for path in result.files:
            typer.echo(f"wrote {Path(path).resolve()}")
        return
    if target is not None and not force:
        run_guarded(target.check_no_results, method)
    bar = TerminalProgress()

    def show(done: int, total: int) -> None:
        bar(done, total, f"separate ({method})")

    if method in networks:
        options = {"weights": weights, "tile": tile, "precision": chosen.value, "device": network_device.type,
                   "colour_match": colour_match, "progress": show,
                   **({"return_copies": return_copies, "incidence_deg": incidence} if method == "network" else {})}
        typer.echo(f"precision: {describe(chosen, network_device)}" + (f" on {network_device.type}" if network_device.type != "cpu" else ""), err=True)
    else:
        options = {**params, "progress": show} if method in PROGRESS_BASELINES else params
    run, info = run_guarded(get_method, method, **options)
    # separate.methods records a baseline's keywords as its parameters: the callback is not one
    if images:
        result = run_guarded(separate_images, images, angle_list, out, run, transfer_rule, force, forced, maps,
                             sees_polarization_of(info))
    else:
        result = run_guarded(separate_scene, target, method, run, info, force, forced, maps)
    bar.close()
    for line in result.warnings:
        warn(line)
    kinds = {"auto": "estimated; per pixel, a field around it: reference_deg.tiff", "global": "estimated"}
    kind = kinds[forced] if isinstance(forced, str) else "given"
    if sees_polarization_of(info):
        typer.echo(f"reference angle {result.reference_deg:.1f} deg ({kind})")
    if "incidence" in info:
        typer.echo(describe_incidence(info["incidence"]))
    for path in result.files:
        typer.echo(f"wrote {Path(path).resolve()}")
    report_truth(result.truth_metrics)
    show_previews(result.files)


def separate_dataset(dataset: Optional[Path], method: str, weights: Optional[Path], tile: Optional[int], chosen,
                     colour_match: bool, return_copies: bool, incidence: Optional[float], params: dict, force: bool,
                     reference, maps: bool, jobs: int, network_device=None) -> None:
    """``urd separate --all``: every scene that needs it (`urd.batch.separate_all`), one line per
    scene; exit 1 when any failed. ``network_device``: the networks' torch device."""
    from urd.batch import separate_all

    root = existing_dataset(dataset)
    options = ({"weights": weights, "tile": tile, "precision": chosen.value, "device": network_device.type,
                "colour_match": colour_match, **({"return_copies": return_copies, "incidence_deg": incidence} if method == "network" else {})}
               if method in ("network", "ceilnet") else params)
    outcomes = run_guarded(separate_all, root, method, options, force, reference, maps, jobs, progress=TerminalProgress())
    for outcome in outcomes:
        typer.echo(f"{outcome.scene}: {outcome.state}{': ' + outcome.detail if outcome.detail else ''}")
    failed = sum(o.state == "failed" for o in outcomes)
    done = sum(o.state == "separated" for o in outcomes)
    mapped = sum(o.state == "maps added" for o in outcomes)
    typer.echo(f"{plural(done, 'scene')} separated with {method}, " + (f"maps added to {mapped}, " if mapped else "") +
               f"{failed} failed" + (
        f"; results in each scene's results/{method}/ (look at them: urd report {root} --html report)" if done else ""))
    if failed:
        raise typer.Exit(1)


#: Baselines that report progress (their ``separate`` takes a ``progress`` callback).
PROGRESS_BASELINES = ("kong", "arvanitopoulos", "li-brown")


def report_truth(figures: Optional[dict]) -> None:
    """Print PSNR against ground truth (virtual-camera scenes only)."""
    if figures:
        typer.echo(f"vs ground truth: T {figures['T']['psnr_db']:.2f} dB (no separation {figures['T_no_separation']['psnr_db']:.2f} dB), "
                   f"R {figures['R']['psnr_db']:.2f} dB; SSIM T {figures['T']['ssim']:.3f}")


@app.command()
def train(
    config: Path = typer.Argument(..., help="TOML config (see configs/cpu.toml and configs/paper.toml)."),
    run_dir: Path = typer.Argument(..., help="Run folder: checkpoints, log.jsonl; an existing run resumes."),
    init: Optional[Path] = typer.Option(None, help="Start from these weights (e.g. the shipped ones) instead of scratch."),
    seed: Optional[int] = typer.Option(None, callback=within(0), help="Override the config's seed (weight initialisation and training data), e.g. for a multi-seed ablation."),
) -> None:
    """Train the separation network (or the CEILNet baseline: configs/ceilnet.toml) on synthesized data (config file, checkpoints, resume; torchrun for DDP).

    \b
    Example:
      urd train configs/cpu.toml runs/cpu
      urd train configs/paper.toml runs/paper --init separate/weights/urd-canonical.pt
    """
    from separate.precision import describe, resolve
    from separate.train import TrainConfig, train as train_run

    cfg = run_guarded(TrainConfig.from_toml, config)
    if seed is not None:
        cfg = dataclasses.replace(cfg, seed=seed)
    typer.echo(f"precision: {describe(resolve(cfg.precision))}", err=True)
    bar = TerminalProgress()

    def show(record: dict) -> None:
        bar(record["step"], cfg.steps, "train")
        if "psnr_t" in record:
            loss = f"loss {record['loss']:.5f}" if "loss" in record else "the --init weights"
            bar.break_line()
            typer.echo(f"step {record['step']}: {loss}, val PSNR T {record['psnr_t']:.2f} dB, R {record['psnr_r']:.2f} dB "
                       f"({record['wall_s'] / 60:.1f} min of training)")

    last = Path(run_dir) / "last.pt"
    if last.is_file() and os.environ.get("RANK", "0") == "0":
        from separate.train import load_checkpoint

        state = run_guarded(load_checkpoint, last)
        typer.echo(f"resuming {run_dir} from step {state['step']} of {cfg.steps} ({last}; "
                   f"{state.get('wall_s', 0.0) / 60:.1f} min trained so far)")
    record = run_guarded(train_run, cfg, run_dir, init, progress=show)
    bar.close()
    if os.environ.get("RANK", "0") == "0":                   # under torchrun, rank 0 reports
        typer.echo(f"stopped at step {record.get('step')}; checkpoints in {Path(run_dir).resolve()}")


@app.command()
def bench(
    ctx: typer.Context,
    quick: bool = typer.Option(False, "--quick", help="The paper's evaluation, reduced (< 10 min on 2 cores): tables, CSV and plots in docs/bench/quick, checked against docs/bench/expected-quick.json."),
    full: bool = typer.Option(False, "--full", help="The paper's full evaluation (20-50 min on 2 cores): cross-validation, robustness, speed into docs/bench/full."),
    large: bool = typer.Option(False, "--24mp", help="With --full: also time the network and Schechner on a 24 MP scene."),
    images: Optional[Path] = typer.Option(None, help="With --quick/--full: also cross-validate on the photos of this folder (JPEG, PNG, 8/16-bit TIFF)."),
    out: Optional[Path] = typer.Option(None, help="With --quick/--full/--ablation: output folder (default docs/bench)."),
    count: int = typer.Option(64, callback=within(1), help="Benchmark patches (seeded, from bsds500/test or bundled photos)."),
    size: int = typer.Option(256, callback=within(32), help="Patch size (px)."),
    methods: str = typer.Option("none,network", help="Comma-separated methods, plus 'direct' for the direct variant (shipped urd-direct.pt or --direct-weights), and LABEL=PATH for the network with other weights."),
    direct_weights: Optional[Path] = typer.Option(None, help="Weights of the direct variant."),
    ablation: bool = typer.Option(False, "--ablation", help="The paper's pipeline ablation (DR, DR+NRD, DR+NRD+LCG) with several seeds: trains the runs missing from --runs (configs/ablation-*.toml, about 1 h of CPU each), scores them on --count patches, writes OUT/ablation (default docs/bench/ablation)."),
    seeds: str = typer.Option("0,1", help="With --ablation: comma-separated training seeds (at least two)."),
    jobs: int = typer.Option(2, callback=within(1), help="With --ablation: training runs side by side (one thread each)."),
    runs: Optional[Path] = typer.Option(None, help="With --ablation: folder of the training runs (unfinished ones resume; default runs/ablation, or runs/ablation-STEPS with --steps)."),
    steps: Optional[int] = typer.Option(None, callback=within(1), help="With --ablation: training steps of every run (default: the configs' 4000; e.g. 16000 on a GPU); its runs in runs/ablation-STEPS and its report in OUT/ablation-STEPS."),
    semireal: bool = typer.Option(False, "--semireal", help="The semi-real set: held-out real captures without glass (../shared/data/polarization) as the transmitted layer behind a rendered pane reflecting a bsds500/test photo, exact ground truth; 3, 4 and 6 shots, mono, and the no-glass R share; every method of --methods (default none, Schechner, Kong, Farid, network; LABEL=PATH adds the network with other weights); tables in OUT/semireal (default docs/bench/semireal). About 20 min on 2 cores."),
    weights: Optional[Path] = typer.Option(None, help="With --semireal: the network's weights (default: shipped)."),
    virtual: bool = typer.Option(False, "--virtual", help="The virtual-camera set: flat panes rendered by urd's virtual camera at angles of incidence 20-75 deg and a wide view (phi_perp turning 50 deg), the network against Schechner, Kong, Farid and no separation (4 photo pairs of 768x512; --methods to choose); tables in OUT/virtual (default docs/bench/virtual)."),
) -> None:
    """Benchmark the methods on synthetic data with ground truth: by default one table of RMSE /
    PSNR / SSIM of R and T per method (with network and direct: their paired T PSNR difference);
    with --quick or --full the paper's tables, robustness study and speed figures; with
    --ablation the multi-seed pipeline ablation.

    \b
    Example:
      urd bench --methods none,schechner,network --count 16
      urd bench --quick
      urd bench --virtual
    """
    if large and not full:
        raise usage("--24mp goes with --full")
    if semireal:
        if virtual or quick or full or ablation or given(ctx, "count") or given(ctx, "size"):
            raise usage("--semireal goes alone (with --methods, --weights and --out): it has its own scenes")
        bench_semireal(methods if given(ctx, "methods") else None, weights, out)
        return
    if weights is not None:
        raise usage("--weights goes with --semireal")
    if virtual:
        if quick or full or ablation or given(ctx, "count") or given(ctx, "size"):
            raise usage("--virtual goes alone (with --methods and --out): it has its own scenes")
        bench_virtual(methods if given(ctx, "methods") else None, out)
        return
    if not ablation and (seeds != "0,1" or jobs != 2 or runs is not None or steps is not None):
        raise usage("--seeds, --jobs, --runs and --steps go with --ablation")
    if ablation:
        from separate.ablation import run_ablation
        from separate.bench_run import DEFAULT_OUT

        seed_list = parse_seeds(seeds)
        folder = (out or DEFAULT_OUT) / ("ablation" + (f"-{steps}" if steps else ""))
        bar = TerminalProgress()
        runs = runs or Path("runs/ablation" + (f"-{steps}" if steps else ""))
        result = run_guarded(run_ablation, folder, runs, seed_list, jobs, count, size,
                             progress=lambda done, total: bar(done, total, "ablation training runs"),
                             command=" ".join(["urd"] + sys.argv[1:]), steps=steps)
        bar.close()
        typer.echo(Path(result["files"][0]).read_text())
        typer.echo(f"table, CSV, plot and weights in {folder.resolve()}")
        if not (quick or full):
            return
    if quick or full:
        from separate.bench_run import DEFAULT_OUT, run_evaluation

        result = run_guarded(run_evaluation, out or DEFAULT_OUT, quick, images, progress=TerminalProgress(),
                             large=large, command=" ".join(["urd"] + sys.argv[1:]))
        typer.echo(f"tables, CSV and plots in {Path(result['folder']).resolve()}")
        return
    from separate.bench import format_paired, format_table, run_benchmark

    rows = run_guarded(run_benchmark, [m for m in methods.split(",") if m], count, size, direct_weights)
    typer.echo(format_table(rows))
    if {"network", "direct"} <= {r["method"] for r in rows}:
        typer.echo(format_paired(rows, "network", "direct"))


def bench_semireal(methods: Optional[str], weights: Optional[Path], out: Optional[Path]) -> None:
    """``urd bench --semireal``: print the tables and write them, with the per-scene figures, into OUT/semireal."""
    import json

    from separate.bench_run import DEFAULT_OUT
    from separate.semireal import DEFAULT_METHODS, run_semireal
    from urd.core.files import write_bytes_atomic

    chosen = tuple(methods.split(",")) if methods else DEFAULT_METHODS
    bar = TerminalProgress()
    tables, records = run_guarded(run_semireal, chosen, weights, progress=bar)
    bar.close()
    folder = (out or DEFAULT_OUT) / "semireal"
    folder.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(folder / "tables.md", tables.encode(), overwrite=True)
    write_bytes_atomic(folder / "scenes.json", json.dumps(records, indent=1).encode(), overwrite=True)
    typer.echo(tables)
    typer.echo(f"wrote {(folder / 'tables.md').resolve()} and scenes.json")


def bench_virtual(methods: Optional[str], out: Optional[Path]) -> None:
    """``urd bench --virtual``: print the tables and write them into OUT/virtual/tables.md."""
    from separate.bench_run import DEFAULT_OUT
    from urd.core.files import write_bytes_atomic
    from urd.virtual_bench import DEFAULT_METHODS, run_virtual_bench

    chosen = tuple(methods.split(",")) if methods else DEFAULT_METHODS
    bar = TerminalProgress()
    tables = run_guarded(run_virtual_bench, chosen, progress=bar)
    bar.close()
    folder = (out or DEFAULT_OUT) / "virtual"
    folder.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(folder / "tables.md", tables.encode(), overwrite=True)
    typer.echo(tables)
    typer.echo(f"wrote {(folder / 'tables.md').resolve()}")


@app.command()
def report(
    dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP, show_default=False),
    html: Optional[Path] = typer.Option(None, "--html", help="Also write a self-contained HTML report into this folder (opens from disk: shots, S0/DoLP/AoLP, results side by side with a comparison slider)."),
    force: bool = typer.Option(False, help="Replace an existing HTML report folder."),
) -> None:
    """Summarize a dataset: scenes (incomplete, broken, ingested), angles, calibration, results.

    \b
    Example:
      urd report
      urd report dataset --html report/
    """
    from urd.report import report_html, report_text

    from urd.report_html import is_report_folder

    root = existing_dataset(dataset)
    if html is not None and (html.exists() or html.is_symlink()):
        if html.is_symlink() or not is_report_folder(html):
            fail(f"{html}: exists and is not an urd HTML report; choose another folder for the report")
        if not force:
            fail(f"{html}: report folder already exists; pass --force to replace it, or another folder")
    typer.echo(run_guarded(report_text, root))
    if html is not None:
        index = run_guarded(report_html, root, html, force, progress=TerminalProgress())
        typer.echo(f"wrote {Path(index).resolve()}")


@app.command()
def verify(dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP + " Or one scene's folder.", show_default=False)) -> None:
    """Check every file a dataset's manifests list against its size and SHA-256; exit 1 on any problem.

    \b
    Example:
      urd verify
      urd verify dataset
      urd verify dataset/scene_01
    """
    from urd.report import verify as verify_dataset

    problems = run_guarded(verify_dataset, existing_dataset(dataset))
    bad = 0
    for name, issues in problems.items():
        for issue in issues:
            typer.secho(f"{name}: {issue}", fg=typer.colors.RED, err=True)
        bad += bool(issues)
        if not issues:
            typer.echo(f"{name}: ok")
    scenes = len(problems) - ("calibration" in problems)
    what = plural(scenes, "scene") + (" and the calibration" if "calibration" in problems else "")
    if bad:
        fail(f"{bad} of {what} {'has' if bad == 1 else 'have'} problems")
    typer.echo(f"{'all ' if scenes > 1 else ''}{what} intact")


@app.command()
def demo(
    folder: Path = typer.Argument(Path("urd-demo"), help="Dataset folder for the demo, created; when it exists, a fresh FOLDER-2, FOLDER-3 … (said on the first line)."),
    size: str = typer.Option("1536x1024", help="Virtual sensor size WIDTHxHEIGHT."),
    seed: int = typer.Option(0, help="Random seed of the simulated rig."),
    precision: str = typer.Option("auto", help="Network arithmetic: auto, fp32 or bf16."),
) -> None:
    """Run the whole pipeline on the simulated rig with bundled images (no hardware, no download).

    \b
    Example:
      urd demo
      urd demo urd-demo --size 768x512 --seed 1
    """
    from separate.precision import resolve
    from urd.demo import run_demo

    width, height = parse_size(size)
    try:
        resolve(precision)
    except ValueError as exc:
        raise bad("--precision", str(exc)) from None
    result = run_guarded(run_demo, folder, width, height, seed, precision, typer.echo, progress=TerminalProgress())
    report_truth(result.truth_metrics)
    show_previews(result.files)


def show_previews(files: list) -> None:
    """Point to the files to open first: the sRGB previews, and what clipped.png means."""
    previews = [Path(p) for p in files if Path(p).name.endswith("_preview.png")]
    if previews:
        typer.echo("open the previews: " + "  ".join(str(p.resolve()) for p in sorted(previews, reverse=True)))
    clipped = next((Path(p) for p in files if Path(p).name == "clipped.png"), None)
    if clipped is not None:
        import cv2

        mask = cv2.imread(str(clipped), cv2.IMREAD_GRAYSCALE)
        share = 0.0 if mask is None else float((mask > 0).mean())
        typer.echo("clipped.png: no pixel is clipped in any shot (the mask is all black)" if share == 0 else
                   f"clipped.png: {100 * share:.2f}% of the pixels are clipped in some shot (white): R and T there are guesses")


def main() -> None:
    terminate_on_sigterm()                  # SIGTERM stops worker pools and says what was kept, as Ctrl-C does
    app(prog_name="urd")


if __name__ == "__main__":
    sys.exit(main())
