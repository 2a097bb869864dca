"""What every ``urd`` command shares: the one error voice (`fail`, `bad`, `usage`), option checks
and parsers (`within`, `given`, `parse_angles`, ...), `run_guarded` with its progress line, and the
lines printed after a separation (`report_truth`, `show_previews`).

Errors print one line, "Error: ...": bad arguments name the option ("Invalid value for '--method':
...") and exit with status 2, failures exit with status 1 (130 after Ctrl-C, 143 after SIGTERM).
"""

from __future__ import annotations

import contextlib
import enum
import json
import math
import re
import sys
from pathlib import Path
from typing import Optional

import typer

from urd.core.dataset import DATASET_MANIFEST, default_root, enclosing_dataset
from urd.core.errors import CaptureInterrupted, UrdError
from urd.core.processes import Terminated
from urd.core.progress import TerminalProgress


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


def fail(message: str, code: int = 1) -> None:
    """Print an error line in the voice of usage errors ("Error: ...") and exit with ``code``;
    the line starts a line of its own (`TerminalProgress.end_open_lines`)."""
    TerminalProgress.end_open_lines(sys.stderr)
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
        if isinstance(value, float) and not math.isfinite(value):
            raise typer.BadParameter(f"expected a finite number, got {value}")
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


def check_rig(ctx: typer.Context, stage: str, camera: str, stage_options: tuple[str, ...],
              camera_options: tuple[str, ...]) -> None:
    """Check the rig a command is given before any port is opened: a ``stage`` port that names no
    serial device is a failure (exit 1, `acquire.rig.check_port`); the virtual camera without
    the simulated stage, and simulation options that would go unused, are usage errors (exit 2).
    ``stage_options`` (parameter names) set the simulated stage and need --stage sim,
    ``camera_options`` set the virtual camera and need --camera virtual; only options given
    (`given`) count."""
    from acquire.rig import SIM, check_port

    if stage != SIM:
        run_guarded(check_port, stage)
        if camera == "virtual":
            raise usage(f"--camera virtual needs --stage sim: the virtual camera reads the true polarizer angle from the "
                        f"simulated stage, and {stage} is a real port")
    problems = []
    for names, unused_here, needs, why in (
            (stage_options, stage != SIM, "--stage sim", f"the simulated stage, and {stage} is a real port"),
            (camera_options, camera != "virtual", "--camera virtual", f"the virtual camera, not the {camera} camera")):
        unused = [f"--{name.replace('_', '-')}" for name in names if unused_here and given(ctx, name)]
        if unused:
            one = len(unused) == 1
            problems.append(f"{', '.join(unused)} {'needs' if one else 'need'} {needs}: {'it sets' if one else 'they set'} {why}")
    if problems:
        raise usage("; ".join(problems))


def refuse_weights_folder(path: Optional[Path], option: str, by_name: bool = True) -> None:
    """A usage error naming ``option`` when the weights file ``path`` is a folder (a run folder
    points at its best.pt) or not a file (nor, ``by_name``, the name of shipped weights)."""
    if path is not None and path.is_dir():
        raise bad(option, f"{path} is a folder, expected a weights file"
                  + (" (a run folder: pass its best.pt)" if (path / "best.pt").is_file() else ""))
    if path is None or path.exists():
        return
    if not by_name:
        raise bad(option, f"{path}: no such file")
    from separate.infer import WEIGHTS_DIR, shipped_weights                # torch: a name or a missing file only

    if not (path.name == str(path) and (WEIGHTS_DIR / f"{path}.pt").is_file()):
        raise bad(option, f"{path}: no such file (shipped weights, by name: {', '.join(shipped_weights())})")


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
    inside = enclosing_dataset(Path(".")) if dataset is None and not root.exists() else None
    if inside is not None:
        fail(f"no dataset named, and this folder lies inside the dataset {inside} (in {Path('.').resolve().relative_to(inside)}): "
             f"run the command from {inside}, or name that dataset in it")
    if not root.exists():
        fail(f"no dataset: {root.resolve()} does not exist. Make one with 'urd capture --stage PORT' or "
             "'urd ingest RAW_FOLDER' (both create ./dataset by default), or name an existing dataset folder")
    return root


def warn(message: str) -> None:
    typer.secho(f"warning: {message}", fg=typer.colors.YELLOW, err=True)


def note_new_dataset(root: Path) -> None:
    """Warn when ``root`` is an existing folder that holds other files (hidden ones aside) but no
    dataset, and lies in none: the dataset a command is about to make goes in beside them."""
    root = Path(root)
    with contextlib.suppress(OSError):
        if root.is_dir() and not (root / DATASET_MANIFEST).exists() and enclosing_dataset(root) is None \
                and any(not path.name.startswith(".") for path in root.iterdir()):
            warn(f"{root.resolve()} holds other files but no urd dataset: the dataset is made there, beside them "
                 "(its manifest and scene folders; nothing of yours is changed); name a new or empty folder to keep "
                 "it apart")


def run_guarded(func, *args, **kwargs):
    """Call ``func`` with a progress line on stderr, turning urd's errors into a one-line
    message and exit status 1 (130 for Ctrl-C)."""
    bar = kwargs.get("progress")
    try:
        return func(*args, **kwargs)
    except CaptureInterrupted as exc:
        fail(str(exc), 143 if exc.terminated else 130)
    except (UrdError, ValueError, OSError) as exc:
        fail(str(exc))
    except MemoryError:
        fail("out of memory: the work stopped (completed files are kept); try smaller images, or a machine with more memory")
    except KeyboardInterrupt as exc:
        stopped = "stopped by SIGTERM" if isinstance(exc, Terminated) else "interrupted"
        kept = "; ".join(getattr(exc, "__notes__", [])) or ("completed files are kept and earlier ones unchanged; what the "
                                                            "stop left unfinished is removed by the next command that writes "
                                                            "there")
        fail(f"{stopped}; {kept}", 143 if isinstance(exc, Terminated) else 130)
    finally:
        end_line(bar)


def end_line(bar) -> None:
    """End a progress line before other output."""
    if isinstance(bar, TerminalProgress):
        bar.close()


#: The largest |angle| (deg) a command-line option takes: one turn either way, as --target-angle,
#: --sim-offset and --offset.
CLI_ANGLE_DEG = 360.0


def parse_angles(text: str, min_distinct: int = 3, option: str = "--angles") -> list[float]:
    """'0,45,90' → [0.0, 45.0, 90.0] (degrees): finite, no direction twice (mod 180), at least
    ``min_distinct`` of them, spread so that they determine S0, S1, S2 (`separate.optics.check_angles`,
    the check separation applies)."""
    try:
        angles = [float(a) for a in text.split(",")]          # an empty item ("0,,45") is no angle
    except ValueError:
        raise bad(option, f"expected comma-separated degrees like 0,45,90, got {text!r}") from None
    if not all(math.isfinite(a) for a in angles):
        raise bad(option, f"expected finite angles in degrees, got {text!r}")
    if any(abs(a) > CLI_ANGLE_DEG for a in angles):
        raise bad(option, f"expected angles within ±{CLI_ANGLE_DEG:g} deg, got {text!r}")
    directions = [round(a % 180.0, 6) for a in angles]
    if len(set(directions)) != len(directions):
        raise bad(option, f"expected each polarizer direction once (angles are the same mod 180 deg), got {text!r}")
    if len(angles) < min_distinct:
        raise bad(option, f"expected at least {min_distinct} distinct polarizer angles (mod 180), got {text!r}")
    from separate.optics import check_angles

    try:
        check_angles([math.radians(a) for a in angles])
    except ValueError as exc:
        radians = all(abs(a) <= math.pi + 0.01 for a in angles)
        hint = (f"; these look like radians: in degrees they are {','.join(f'{round(math.degrees(a), 1):g}' for a in angles)}"
                if radians else "")
        raise bad(option, f"{exc}{hint}") from None
    return angles


def parse_params(items: list[str], option: str = "--param") -> dict:
    """['smoothness=0.5', 'theta_deg=35'] → {'smoothness': 0.5, 'theta_deg': 35} (JSON values, else text)."""
    params = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise bad(option, f"expected NAME=VALUE, got {item!r}")
        if name in params:
            raise bad(option, f"{name} is given twice ({name}={json.dumps(params[name])} and {item}); give it once")
        try:
            params[name] = json.loads(value)
        except json.JSONDecodeError:
            params[name] = value
        if isinstance(params[name], float) and not math.isfinite(params[name]):
            raise bad(option, f"expected a finite number for {name}, got {value}")
    return params


def parse_size(text: str, option: str = "--size", min_side: int = 32) -> tuple[int, int]:
    """'1536x1024' → (1536, 1024): the virtual camera's sensor, each side even (its Bayer
    mosaic), ``min_side`` to 20000 px."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise bad(option, f"expected WIDTHxHEIGHT like 1536x1024, got {text!r}") from None
    if not (min_side <= w <= 20000 and min_side <= h <= 20000) or w % 2 or h % 2:
        raise bad(option, f"expected each side an even number of px between {min_side} and 20000, got {text!r}")
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
    if not (math.isfinite(value) and abs(value) <= CLI_ANGLE_DEG):
        raise bad(option, f"expected 'auto', 'global' or an angle within ±{CLI_ANGLE_DEG:g} deg, got {text!r}")
    return value % 180.0


def resolve_scene(scene: str, dataset: Optional[Path]):
    """A scene given by folder path, or by name in ``dataset`` (default: ``default_root()``)."""
    from urd.core.dataset import Dataset, Scene

    path = Path(scene)
    if (path / "scene.json").is_file():
        refuse_scene_link(path, "SCENE")
        return Scene(path)
    if (path / "dataset.json").is_file():
        raise bad("SCENE", f"{scene} is a dataset; give one of its scenes ({', '.join(Dataset.open(path).scene_names()) or 'none yet'}) "
                           f"with --dataset {scene}, or separate them all with --all --dataset {scene}")
    ds = Dataset.open(existing_dataset(dataset))
    if scene not in ds.scene_names():
        raise bad("SCENE", f"no scene {scene!r} in {ds.root.resolve()} (scenes: {', '.join(ds.scene_names()) or 'none'}); "
                           "give a scene's name, or its folder")
    return ds.scene(scene)


def refuse_scene_link(path: Path, option: str) -> None:
    """A usage error naming ``option`` when the scene folder ``path`` is a symbolic link: urd works
    on a scene inside its dataset, whose manifest knows it, and follows no link into one."""
    if path.is_symlink():
        raise bad(option, f"{path} is a symbolic link to the scene {path.resolve()}; give that folder itself")


def report_truth(figures: Optional[dict]) -> None:
    """Print PSNR against ground truth (virtual-camera scenes only)."""
    if figures:
        typer.echo(f"vs ground truth: T {figures['T']['psnr_db']:.2f} dB (no separation {figures['T_no_separation']['psnr_db']:.2f} dB), "
                   f"R {figures['R']['psnr_db']:.2f} dB; SSIM T {figures['T']['ssim']:.3f}")


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
                   f"clipped.png: {100 * share:.3g}% of the pixels are clipped in some shot (white): R and T there are guesses")
