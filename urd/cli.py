"""The ``urd`` command line: a thin layer over acquire/, calib/, separate/ and urd.dataset.

Angles are degrees here and in manifests. Errors print one line and exit with status 1;
bad arguments exit with status 2.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from urd.dataset import default_root
from urd.errors import UrdError

DATASET_HELP = "Dataset folder (default: the current folder if it holds dataset.json, else ./dataset)."

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


def parse_params(items: list[str]) -> dict:
    """['smoothness=0.5', 'theta_deg=35'] → {'smoothness': 0.5, 'theta_deg': 35} (JSON values, else text)."""
    params = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise typer.BadParameter(f"expected NAME=VALUE, got {item!r}")
        try:
            params[name] = json.loads(value)
        except json.JSONDecodeError:
            params[name] = value
    return params


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
                raise UrdError(f"{exc}\ncapture of {scene.name} stopped; completed shots are kept. "
                               f"Resume with: urd capture {dataset} --scene {scene.name} ...") from exc
        if isinstance(rig.camera, VirtualCamera) and not (scene.path / "truth").exists():
            rig.camera.write_truth(scene.path / "truth")
    return scene


@app.command()
def capture(
    dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP + " Created when new.", show_default=False),
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
    result = run_guarded(do_capture, dataset or default_root(), stage, camera, angle_list, scene, tolerance, address, sim)
    typer.echo(f"scene complete: {result.path}")


def do_ingest(source: Path, dataset: Optional[Path], opts, mosaic=None) -> list:
    """Ingest a RAW folder (or polarization mosaics) into ``dataset``, or a captured scene /
    dataset in place."""
    from urd.dataset import Dataset, Scene
    from urd.ingest import SceneOutcome, ingest_folder, ingest_mosaic, ingest_scene

    def one_scene(scene: Scene) -> SceneOutcome:
        try:
            return ingest_scene(scene, opts, progress)
        except UrdError as exc:
            return SceneOutcome(scene.name, [], str(exc))

    outcomes, ignored = [], []
    with typer.progressbar(length=1, label="ingest", file=sys.stderr, show_pos=False) as bar:
        def progress(message: str) -> None:
            bar.label = message[:60]
            bar.render_progress()

        if mosaic is not None:
            ds = Dataset.open_or_create(dataset or default_root())
            files = [source] if source.is_file() else sorted(p for p in source.iterdir() if p.suffix.lower() in (".png", ".tif", ".tiff"))
            outcomes = [ingest_mosaic(ds, f, mosaic) for f in files]
        elif (source / "scene.json").is_file():
            outcomes = [one_scene(Scene(source))]
        elif (source / "dataset.json").is_file():
            ds = Dataset.open(source)
            scenes = [ds.scene(n) for n in ds.scene_names()]
            outcomes = [one_scene(s) for s in scenes if opts.redo or "ingest" not in s.load(verify=False)]
        else:
            outcomes, ignored = ingest_folder(source, dataset or default_root(), opts, progress)
        bar.update(1)
    for path in ignored:
        typer.echo(f"ignored (not a RAW file name): {path}", err=True)
    return outcomes


@app.command()
def ingest(
    source: Path = typer.Argument(..., help="A folder of RAW shots, a captured scene folder, or a dataset folder."),
    dataset: Optional[Path] = typer.Argument(None, help="Dataset to add scenes to when SOURCE is a RAW folder or mosaics (default: the current folder if it holds dataset.json, else ./dataset).", show_default=False),
    angles: str = typer.Option("0,45,90", help="Polarizer angles of consecutive shots (deg), for RAW folders without a capture manifest."),
    motion: str = typer.Option("euclidean", help="Alignment model: translation, euclidean or homography."),
    half_size: bool = typer.Option(False, help="Decode at half resolution (one pixel per 2x2 CFA tile; ~4x faster)."),
    gap: float = typer.Option(60.0, help="Seconds between shots that start a new scene when grouping by capture time."),
    redo: bool = typer.Option(False, help="Decode and align again scenes that are already ingested (replaces aligned/)."),
    mosaic: Optional[str] = typer.Option(None, help="SOURCE holds polarization-camera frames (PNG/TIFF) with this layout: imx250mzr, imx250myr or wen2019; one scene per frame."),
) -> None:
    """Decode RAW shots to linear images, group them into scenes and align each scene (ECC)."""
    from urd.align import Motion
    from urd.ingest import IngestOptions
    from urd.mosaic import MosaicLayout

    try:
        opts = IngestOptions(tuple(parse_angles(angles)), Motion(motion), half_size, gap, redo)
        layout = MosaicLayout(mosaic) if mosaic else None
    except ValueError as exc:
        raise typer.BadParameter(str(exc))
    outcomes = run_guarded(do_ingest, source, dataset, opts, layout)
    failed = 0
    for outcome in outcomes:
        if outcome.error:
            failed += 1
            where = outcome.name or ", ".join(p.name for p in outcome.files)
            typer.secho(f"FAILED {where}: {outcome.error}", fg=typer.colors.RED, err=True)
        else:
            typer.echo(f"ingested {outcome.name} (from {len(outcome.files)} files)")
    if not outcomes:
        typer.echo("nothing to ingest")
    if failed:
        fail(f"{failed} of {len(outcomes)} scenes failed or were flagged")


calibrate_app = typer.Typer(help="Measure the polarizer: mounting offset from a sweep, per-shot angle errors of a scene.",
                            no_args_is_help=True)
app.add_typer(calibrate_app, name="calibrate")


def resolve_scene(scene: str, dataset: Optional[Path]):
    """A scene given by folder path, or by name in ``dataset`` (default: ``default_root()``)."""
    from urd.dataset import Dataset, Scene

    path = Path(scene)
    if (path / "scene.json").is_file():
        return Scene(path)
    return Dataset.open(dataset or default_root()).scene(scene)


@calibrate_app.command("offset")
def calibrate_offset_cmd(
    dataset: Optional[Path] = typer.Argument(None, help="Dataset whose polarizer to calibrate (calibration.json is written there); " + DATASET_HELP, show_default=False),
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

    root = dataset or default_root()

    def work():
        ds = Dataset.open_or_create(root)
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

    record = run_guarded(work)
    typer.echo(f"mounting offset {record['offset_deg']:.3f} ± {record['uncertainty_deg']:.3f} deg "
               f"(modulation {record['modulation']:.2f}); written to {root / 'calibration.json'}")


@calibrate_app.command("shots")
def calibrate_shots_cmd(
    scene: str = typer.Argument(..., help="Scene name (scene_12) or folder; must be ingested."),
    dataset: Optional[Path] = typer.Option(None, help=DATASET_HELP, show_default=False),
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
def separate(
    scene: Optional[str] = typer.Argument(None, help="Scene name (scene_12) in --dataset, or a scene folder. Omit with --images."),
    dataset: Optional[Path] = typer.Option(None, help=DATASET_HELP, show_default=False),
    method: str = typer.Option("network", help="network (the paper's, shipped weights); baselines: schechner, kong, farid (polarization), li-brown, arvanitopoulos, ceilnet (single image: they see S0 only); none (T = S0)."),
    images: Optional[list[Path]] = typer.Option(None, "--images", help="Separate image files instead of a scene (repeat: 3 or 4 files, linear TIFF or sRGB PNG/JPEG)."),
    angles: str = typer.Option("0,45,90", help="Polarizer angles of --images (deg)."),
    out: Path = typer.Option(Path("separated"), help="Output folder for --images."),
    weights: Optional[Path] = typer.Option(None, help="Weights file of the network or ceilnet (default: the shipped ones)."),
    tile: int = typer.Option(768, help="Network tile size (px); memory grows with it, not with the image."),
    precision: str = typer.Option("auto", help="Network arithmetic: auto (bf16 where the CPU or GPU runs it natively, else fp32), fp32 or bf16."),
    colour_match: bool = typer.Option(False, help="Match each colour channel's histogram of T to the darkest observation's (paper §3.4)."),
    param: Optional[list[str]] = typer.Option(None, "--param", help="A baseline's parameter as NAME=VALUE (repeat), e.g. --method kong --param smoothness=0.5; names and paper defaults in each baseline's docstring (separate/baselines/)."),
    force: bool = typer.Option(False, help="Replace existing results of this method."),
) -> None:
    """Separate a scene into reflection R and transmission T (linear 16-bit TIFF + sRGB previews)."""
    from separate.methods import METHODS, get_method
    from urd.separation import read_image, separate_scene, write_results

    if method not in METHODS:
        raise typer.BadParameter(f"unknown method {method!r}; expected one of {sorted(METHODS)}")
    networks = ("network", "ceilnet")
    options = {"weights": weights, "tile": tile, "precision": precision, "colour_match": colour_match} if method in networks else {}
    if param and method in networks + ("none",):
        raise typer.BadParameter(f"--param is for the baselines; {method} takes its own options")
    options.update(parse_params(param or []))

    def work():
        with typer.progressbar(length=100, label=f"separate ({method})", file=sys.stderr) as bar:
            if method in networks:
                options["progress"] = lambda done, total: bar.update(round(100 * done / total) - bar.pos)
            run, info = get_method(method, **options)
            if images:
                loaded = [read_image(p) for p in images]
                if len({im.shape for im in loaded}) > 1:
                    raise ValueError(f"expected images of one size, got {[im.shape[:2] for im in loaded]}")
                stack = np.stack(loaded)
                r_hat, t_hat = run(stack, parse_angles(angles))
                paths = write_results(out, r_hat, t_hat, overwrite=force)
                return {"files": [{"file": str(p)} for p in paths], "truth_metrics": None}
            if scene is None:
                raise ValueError("expected a scene name or --images")
            return separate_scene(resolve_scene(scene, dataset), method, run, info, force)

    entry = run_guarded(work)
    for f in entry["files"]:
        typer.echo(f"wrote {f['file']}")
    report_truth(entry.get("truth_metrics"))


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
) -> None:
    """Train the separation network (or the CEILNet baseline: configs/ceilnet.toml) on synthesized data (config file, checkpoints, resume; torchrun for DDP)."""
    from separate.train import TrainConfig, train as train_run

    cfg = run_guarded(TrainConfig.from_toml, config)

    def show(record: dict) -> None:
        if "psnr_t" in record:
            typer.echo(f"step {record['step']}: loss {record['loss']:.5f}, val PSNR T {record['psnr_t']:.2f} dB, R {record['psnr_r']:.2f} dB")

    record = run_guarded(train_run, cfg, run_dir, init, show)
    typer.echo(f"stopped at step {record.get('step')}; checkpoints in {run_dir}")


@app.command()
def bench(
    count: int = typer.Option(64, help="Benchmark patches (seeded, from bsds500/test or bundled photos)."),
    size: int = typer.Option(256, help="Patch size (px)."),
    methods: str = typer.Option("none,network", help="Comma-separated methods, plus 'direct' for the direct variant (shipped urd-direct.pt or --direct-weights), and LABEL=PATH for the network with other weights."),
    direct_weights: Optional[Path] = typer.Option(None, help="Weights of the direct variant."),
) -> None:
    """Run the fixed synthetic benchmark and print RMSE / PSNR / SSIM of R and T per method
    (with network and direct: their paired T PSNR difference and its 95% bootstrap interval)."""
    from separate.bench import format_paired, format_table, run_benchmark

    rows = run_guarded(run_benchmark, [m for m in methods.split(",") if m], count, size, direct_weights)
    typer.echo(format_table(rows))
    if {"network", "direct"} <= {r["method"] for r in rows}:
        typer.echo(format_paired(rows, "network", "direct"))


@app.command()
def report(dataset: Optional[Path] = typer.Argument(None, help=DATASET_HELP, show_default=False)) -> None:
    """Summarize a dataset: scenes, angles, ingest and calibration status, results."""
    from urd.dataset import Dataset

    def work():
        ds = Dataset.open(dataset or default_root())
        cal = ds.read_calibration()
        lines = [f"dataset {ds.root}: {len(ds.scene_names())} scenes; polarizer offset "
                 + (f"{cal['offset_deg']:.3f} ± {cal['uncertainty_deg']:.3f} deg" if cal else "not calibrated")]
        for name in ds.scene_names():
            rec = ds.scene(name).load(verify=False)
            ingest = rec.get("ingest")
            state = "not ingested" if not ingest else ("aligned" if ingest["ok"] else "ALIGNMENT FAILED")
            angles = ",".join(f"{s['angle_commanded_deg']:g}" for s in rec["shots"])
            calib = "angles calibrated" if rec.get("calibration", {}).get("applied") else "nominal angles"
            results = ", ".join(rec.get("results", {})) or "no results"
            lines.append(f"  {name}: {len(rec['shots'])} shots at {angles} deg, {state}, {calib}, {results}")
        return "\n".join(lines)

    typer.echo(run_guarded(work))


@app.command()
def demo(
    folder: Path = typer.Argument(Path("urd-demo"), help="Dataset folder for the demo (created, or extended with a new scene)."),
    size: str = typer.Option("1536x1024", help="Virtual sensor size WIDTHxHEIGHT."),
    seed: int = typer.Option(0, help="Random seed of the simulated rig."),
) -> None:
    """Run the whole pipeline on the simulated rig with bundled images (no hardware, no download)."""
    from acquire.rig import SimSettings
    from separate.methods import get_method
    from urd.align import Motion
    from urd.ingest import IngestOptions, ingest_scene
    from urd.separation import separate_scene

    width, height = parse_size(size)
    sim = SimSettings(offset_deg=0.0, jitter_deg=0.3, width=width, height=height, seed=seed)

    def work():
        scene = do_capture(folder, "sim", "virtual", [0.0, 45.0, 90.0], None, 0.5, "0", sim)
        typer.echo(f"1/3 captured {scene.path} (3 DNG shots from the simulated ELL14 and virtual camera)")
        outcome = ingest_scene(scene, IngestOptions(motion=Motion.EUCLIDEAN))
        if outcome.error:
            raise UrdError(outcome.error)
        typer.echo(f"2/3 ingested: decoded to linear RGB and aligned (ECC) in {scene.path / 'aligned'}")
        run, info = get_method("network", precision="auto")
        entry = separate_scene(scene, "network", run, info)
        typer.echo(f"3/3 separated: {scene.path / 'results' / 'network'}")
        return entry

    entry = run_guarded(work)
    report_truth(entry["truth_metrics"])


def main() -> None:
    app(prog_name="urd")


if __name__ == "__main__":
    sys.exit(main())
