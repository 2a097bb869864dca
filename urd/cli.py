"""The ``urd`` command line: a thin layer over acquire/, calib/, separate/ and urd.dataset.

Angles are degrees here and in manifests. Errors print one line and exit with status 1;
a command that is not built yet says so and exits with status 2.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from urd.errors import UrdError

app = typer.Typer(
    help="urd: photograph scenes through glass with a rotating polarizer and separate reflection from transmission.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def fail(message: str, code: int = 1) -> None:
    """Print an error line and exit with ``code``."""
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)


def not_built(command: str) -> None:
    """Say that a command is not built yet and exit with status 2."""
    typer.secho(f"urd {command}: not built yet in urd {__import__('urd').__version__}", err=True)
    raise typer.Exit(2)


def parse_angles(text: str, min_distinct: int = 3) -> list[float]:
    """'0,45,90' → [0.0, 45.0, 90.0] (degrees); at least ``min_distinct`` distinct directions."""
    try:
        angles = [float(a) for a in text.split(",") if a.strip()]
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated degrees like 0,45,90, got {text!r}")
    if len({round(a % 180.0, 6) for a in angles}) < min_distinct:
        raise typer.BadParameter(f"expected at least {min_distinct} distinct polarizer angles (mod 180), got {text!r}")
    return angles


def run_guarded(func, *args, **kwargs):
    """Call ``func``, turning urd's errors into a one-line message and exit status 1."""
    try:
        return func(*args, **kwargs)
    except (UrdError, ValueError, OSError) as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        fail("interrupted; completed files are kept and a re-run resumes", 130)


def parse_faults(text: str) -> dict[str, float]:
    """'drop=0.1,garble=0.05' → {'drop': 0.1, 'garble': 0.05}."""
    faults = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        kind, _, prob = item.partition("=")
        try:
            faults[kind] = float(prob)
        except ValueError:
            raise typer.BadParameter(f"expected KIND=PROBABILITY items like drop=0.1, got {item!r}")
    return faults


def parse_size(text: str) -> tuple[int, int]:
    """'1536x1024' → (1536, 1024)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected WIDTHxHEIGHT like 1536x1024, got {text!r}")
    return w, h


def do_capture(dataset: Path, stage: str, camera: str, angles: list[float], scene_name: str | None,
               tolerance: float, address: str, sim) -> "Scene":
    """Capture (or resume) one scene; shared by ``urd capture`` and ``urd demo``."""
    from acquire.plan import plan_capture, run_capture
    from acquire.rig import open_rig
    from acquire.virtual_camera import VirtualCamera
    from urd.dataset import Dataset, Scene

    ds = Dataset.open_or_create(dataset)
    calibration = ds.read_calibration() or {}
    offset = float(calibration.get("offset_deg", 0.0))
    scene = ds.scene(scene_name) if scene_name and (ds.root / scene_name / "scene.json").exists() else ds.new_scene(scene_name)
    with open_rig(stage, camera, address, sim) as rig:
        done = {s["index"] for s in scene.load()["shots"]} if scene.exists() else set()
        steps = plan_capture(angles, done)
        typer.echo(f"capturing {scene.path} at {angles} deg ({len(angles) - len(done)} shots to take)")
        with typer.progressbar(length=len(steps), label="capture", file=sys.stderr) as bar:
            try:
                run_capture(scene, rig.stage, rig.camera, angles, offset, tolerance,
                            capture_info=rig.info, progress=lambda step: bar.update(1))
            except (UrdError, OSError) as exc:
                raise type(exc)(f"{exc}\ncapture of {scene.name} stopped; completed shots are kept. "
                                f"Resume with: urd capture {dataset} --scene {scene.name} ...") from exc
        if isinstance(rig.camera, VirtualCamera) and not (scene.path / "truth").exists():
            rig.camera.write_truth(scene.path / "truth")
    return scene


@app.command()
def capture(
    dataset: Path = typer.Argument(..., help="Dataset folder; created when new."),
    stage: str = typer.Option(..., help="Serial port of the ELL14 stage (e.g. /dev/ttyUSB0), or 'sim' for the simulated stage."),
    camera: str = typer.Option("gphoto2", help="Camera driver: 'gphoto2' (real camera over USB) or 'virtual' (needs --stage sim)."),
    angles: str = typer.Option("0,45,90", help="Polarizer angles in degrees, comma-separated (at least 3 distinct)."),
    scene: Optional[str] = typer.Option(None, help="Scene name; an existing incomplete scene is resumed. Default: next free scene_NN."),
    tolerance: float = typer.Option(0.5, help="Largest accepted difference of read-back and commanded angle (deg)."),
    address: str = typer.Option("0", help="ELL14 device address 0-F."),
    sim_offset: float = typer.Option(0.0, help="[sim] polarizer mounting offset (deg)."),
    sim_jitter: float = typer.Option(0.0, help="[sim] per-move angle error the encoder does not see, std (deg)."),
    sim_faults: str = typer.Option("", help="[sim] fault probabilities per command, e.g. drop=0.05,garble=0.05,mech_timeout=0.02,miss=0.02,vanish=0.01."),
    sim_size: str = typer.Option("1536x1024", help="[virtual] sensor size WIDTHxHEIGHT."),
    sim_shake: float = typer.Option(4.0, help="[virtual] camera shake between shots, max translation (px)."),
    reflection: Optional[Path] = typer.Option(None, help="[virtual] image file reflected in the glass (default: bundled photo)."),
    transmission: Optional[Path] = typer.Option(None, help="[virtual] image file seen through the glass (default: bundled photo)."),
    seed: int = typer.Option(0, help="[sim/virtual] random seed."),
) -> None:
    """Capture one scene: home the polarizer stage, then move, verify, trigger and download at each angle."""
    from acquire.rig import SimSettings

    angle_list = parse_angles(angles)
    width, height = parse_size(sim_size)
    sim = SimSettings(sim_offset, sim_jitter, parse_faults(sim_faults), width, height, sim_shake, 0.5,
                      reflection, transmission, seed)
    result = run_guarded(do_capture, dataset, stage, camera, angle_list, scene, tolerance, address, sim)
    typer.echo(f"scene complete: {result.path}")


def do_ingest(source: Path, dataset: Optional[Path], opts) -> list:
    """Ingest a RAW folder into ``dataset``, or a captured scene / dataset in place."""
    from urd.dataset import Dataset, Scene
    from urd.ingest import ingest_folder, ingest_scene

    outcomes, ignored = [], []
    with typer.progressbar(length=1, label="ingest", file=sys.stderr, show_pos=False) as bar:
        def progress(message: str) -> None:
            bar.label = message[:60]
            bar.render_progress()

        if (source / "scene.json").is_file():
            outcomes = [ingest_scene(Scene(source), opts, progress)]
        elif (source / "dataset.json").is_file():
            ds = Dataset.open(source)
            todo = [ds.scene(n) for n in ds.scene_names() if opts.redo or "ingest" not in ds.scene(n).load(verify=False)]
            outcomes = [ingest_scene(scene, opts, progress) for scene in todo]
        else:
            outcomes, ignored = ingest_folder(source, dataset or Path("dataset"), opts, progress)
        bar.update(1)
    for path in ignored:
        typer.echo(f"ignored (not a RAW file name): {path}", err=True)
    return outcomes


@app.command()
def ingest(
    source: Path = typer.Argument(..., help="A folder of RAW shots, a captured scene folder, or a dataset folder."),
    dataset: Optional[Path] = typer.Argument(None, help="Dataset to add scenes to when SOURCE is a RAW folder (default: ./dataset)."),
    angles: str = typer.Option("0,45,90", help="Polarizer angles of consecutive shots (deg), for RAW folders without a capture manifest."),
    motion: str = typer.Option("euclidean", help="Alignment model: translation, euclidean or homography."),
    half_size: bool = typer.Option(False, help="Decode at half resolution (one pixel per 2x2 CFA tile; ~4x faster)."),
    gap: float = typer.Option(60.0, help="Seconds between shots that start a new scene when grouping by capture time."),
    redo: bool = typer.Option(False, help="Decode and align again scenes that are already ingested (replaces aligned/)."),
) -> None:
    """Decode RAW shots to linear images, group them into scenes and align each scene (ECC)."""
    from urd.align import Motion
    from urd.ingest import IngestOptions

    try:
        opts = IngestOptions(tuple(parse_angles(angles)), Motion(motion), half_size, gap, redo)
    except ValueError as exc:
        raise typer.BadParameter(str(exc))
    outcomes = run_guarded(do_ingest, source, dataset, opts)
    failed = 0
    for outcome in outcomes:
        if outcome.error:
            failed += 1
            where = outcome.name or ", ".join(p.name for p in outcome.files)
            typer.secho(f"FAILED {where}: {outcome.error}", fg=typer.colors.RED, err=True)
        else:
            typer.echo(f"ingested {outcome.name} ({len(outcome.files)} shots)")
    if not outcomes:
        typer.echo("nothing to ingest")
    if failed:
        fail(f"{failed} of {len(outcomes)} scenes failed or were flagged")


calibrate_app = typer.Typer(help="Measure the polarizer: mounting offset from a sweep, per-shot angle errors of a scene.",
                            no_args_is_help=True)
app.add_typer(calibrate_app, name="calibrate")


def resolve_scene(scene: str, dataset: Path):
    """A scene given by name in ``dataset`` or by folder path."""
    from urd.dataset import Dataset, Scene

    path = Path(scene)
    if (path / "scene.json").is_file():
        return Scene(path)
    return Dataset.open(dataset).scene(scene)


@calibrate_app.command("offset")
def calibrate_offset_cmd(
    dataset: Path = typer.Argument(..., help="Dataset whose polarizer to calibrate (calibration.json is written there)."),
    stage: str = typer.Option(..., help="Serial port of the ELL14 stage, or 'sim'."),
    camera: str = typer.Option("gphoto2", help="Camera driver: gphoto2 or virtual."),
    step: float = typer.Option(10.0, help="Sweep step (deg) over 180 deg."),
    target_angle: float = typer.Option(0.0, help="Polarization angle of the target's light (deg, image plane, CCW from x)."),
    sim_offset: float = typer.Option(0.0, help="[sim] true mounting offset of the simulated polarizer (deg)."),
    seed: int = typer.Option(0, help="[sim/virtual] random seed."),
) -> None:
    """Sweep the polarizer in front of a polarized target and fit Malus's law for the mounting offset."""
    from acquire.plan import run_capture
    from acquire.rig import SimSettings, open_rig
    from calib.store import calibrate_offset
    from urd.dataset import Dataset, Scene

    def work():
        ds = Dataset.open_or_create(dataset)
        sweeps = ds.root / "calibration"
        sweeps.mkdir(exist_ok=True)
        n = 1
        while (sweeps / f"sweep_{n:02d}").exists():
            n += 1
        (sweeps / f"sweep_{n:02d}").mkdir()
        sweep = Scene(sweeps / f"sweep_{n:02d}")
        angles = [float(a) for a in np.arange(0.0, 180.0, step)]
        sim = SimSettings(offset_deg=sim_offset, width=256, height=192, shake_px=0, shake_deg=0, seed=seed,
                          target_angle_deg=target_angle)
        with open_rig(stage, camera, sim=sim) as rig:
            with typer.progressbar(length=len(angles), label="sweep", file=sys.stderr) as bar:
                run_capture(sweep, rig.stage, rig.camera, angles, 0.0, capture_info=rig.info,
                            progress=lambda st: bar.update(1) if st.kind == "record" else None)
        return calibrate_offset(ds, sweep, target_angle)

    import numpy as np

    record = run_guarded(work)
    typer.echo(f"mounting offset {record['offset_deg']:.3f} ± {record['uncertainty_deg']:.3f} deg "
               f"(modulation {record['modulation']:.2f}); written to {dataset / 'calibration.json'}")


@calibrate_app.command("shots")
def calibrate_shots_cmd(
    scene: str = typer.Argument(..., help="Scene name (scene_12) or folder; must be ingested."),
    dataset: Path = typer.Option(Path("."), help="Dataset folder holding the scene."),
    apply: bool = typer.Option(True, help="Store the calibrated angles in the manifest (used by separation)."),
) -> None:
    """Estimate each shot's polarizer angle error from the images (needs 4+ angles; 5+ for all errors)."""
    from calib.store import calibrate_shots

    result = run_guarded(lambda: calibrate_shots(resolve_scene(scene, dataset), apply))
    for i, (e, u) in enumerate(zip(result.errors_deg, result.uncertainty_deg)):
        typer.echo(f"shot {i}: {e:+.3f} ± {u:.3f} deg")
    if result.unobservable is not None:
        typer.secho("warning: with 4 angles one combination of the errors cannot be seen in the images "
                    f"(direction {[round(v, 2) for v in result.unobservable]}); the smallest consistent "
                    "correction is reported. Capture 5 or more angles to determine every error.", err=True)
    typer.echo("calibrated angles stored in the manifest" if apply else "manifest unchanged (--no-apply)")


@app.command()
def separate(scene: str = typer.Argument(..., help="Scene name (scene_12) or folder.")) -> None:
    """Separate a scene into reflection R̂ and transmission T̂ (network or a classical method)."""
    not_built("separate")


@app.command()
def train() -> None:
    """Train the separation network on synthesized data (config file, checkpoints, resume)."""
    not_built("train")


@app.command()
def bench() -> None:
    """Run the fixed synthetic benchmark and print RMSE / PSNR / SSIM per method."""
    not_built("bench")


@app.command()
def report() -> None:
    """Summarize a dataset: scenes, angles, alignment and calibration status, results."""
    not_built("report")


@app.command()
def demo() -> None:
    """Run the whole pipeline on the simulated rig with bundled images (no hardware, no download)."""
    not_built("demo")


def main() -> None:
    app(prog_name="urd")


if __name__ == "__main__":
    sys.exit(main())
