"""The capture plan: a plain list of small steps, and the runner that executes it.

`plan_capture` lists the steps (home; then per angle move, verify, trigger, store, record;
finish) without touching hardware, skipping shots already recorded, so a resumed capture
continues where it stopped. `run_capture` executes the steps against a stage and a camera,
writing each RAW file and the scene manifest atomically after every shot. `capture_scene` is
the workflow behind ``urd capture``: it opens the rig, picks or resumes the scene, runs the
plan under the dataset's lock, and leaves no empty scene behind.

Angles: the plan works in polarizer angles (degrees, image-plane convention). The stage is
commanded ``polarizer angle − mounting offset`` when a calibration is known.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shlex
import shutil
from pathlib import Path
from typing import Callable, Iterator

from acquire.camera import Camera
from acquire.ell14 import Ell14
from urd.core.dataset import SCENE_NAME, Dataset, Scene
from urd.core.errors import DatasetError, DeviceError, ManifestError, RawFormatError, UrdError
from urd.core.files import atomic_path, disk_full, sha256_file, write_error
from urd.core.manifest import printable
from urd.core.processes import capture_stopped
from urd.core.progress import Progress


@dataclasses.dataclass(frozen=True)
class Step:
    """One step of a capture: ``kind`` in home, move, verify, trigger, store, record, finish."""

    kind: str
    index: int | None = None
    angle_deg: float | None = None


def plan_capture(angles_deg: list[float], done: set[int] = frozenset()) -> list[Step]:
    """The steps that capture the shots at ``angles_deg`` not yet in ``done``."""
    steps = [Step("home")]
    for index, angle in enumerate(angles_deg):
        if index not in done:
            steps += [Step(kind, index, angle) for kind in ("move", "verify", "trigger", "store", "record")]
    return steps + [Step("finish")]


def shot_name(index: int, angle_deg: float, suffix: str) -> str:
    """File name of a shot, e.g. shot_01_045.0deg.dng."""
    return f"shot_{index:02d}_{angle_deg:05.1f}deg{suffix}"


#: Range of the read-back tolerance (deg): at least 0.01 (above the ELL14's encoder step of
#: 0.0025 deg), at most 10 (a larger one would pass a missed move and mislabel the shot).
MIN_TOLERANCE_DEG, MAX_TOLERANCE_DEG = 0.01, 10.0


def _angle_error(a_deg: float, b_deg: float) -> float:
    """Smallest difference of two stage angles (deg), modulo 360."""
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def capture_plan_record(angles_deg: list[float], offset_deg: float = 0.0, tolerance_deg: float = 0.5,
                        info: dict | None = None) -> dict:
    """The capture record of a new scene: the plan's angles, mounting offset and read-back
    tolerance (deg), the devices (``info``), not yet complete."""
    return {**(info or {}), "angles_deg": [float(a) for a in angles_deg], "offset_deg": float(offset_deg),
            "tolerance_deg": float(tolerance_deg), "complete": False}


def new_capture_scene(ds: Dataset, angles_deg: list[float], offset_deg: float = 0.0, tolerance_deg: float = 0.5,
                      info: dict | None = None, name: str | None = None) -> Scene:
    """A new scene whose manifest records the capture plan (resumable from its first step)."""
    return ds.new_scene("capture", capture_plan_record(angles_deg, offset_deg, tolerance_deg, info), name)


def run_capture(
    scene: Scene,
    stage: Ell14,
    camera: Camera,
    angles_deg: list[float],
    move_attempts: int = 3,
    progress: Callable[[Step], None] | None = None,
) -> Scene:
    """Capture the shots of ``scene`` (made by `new_capture_scene`) not yet recorded.

    Args:
        scene: the scene (new or partly captured); its manifest holds the plan's angles,
            mounting offset (polarizer angle at stage zero) and read-back tolerance (deg).
        stage, camera: the devices.
        angles_deg: polarizer angles (deg); must be the scene's planned angles.
        move_attempts: moves tried before a position outside the tolerance is an error.
        progress: called after every step.
    """
    planned = scene.capture_angles_deg()
    if planned != [float(a) for a in angles_deg]:
        raise ManifestError(f"{scene.manifest_path}: scene was captured with angles {planned}, "
                            f"not {list(angles_deg)}; use a new scene")
    offset_deg, tolerance_deg = scene.capture_settings()
    scene.remove_stale()                                  # refuses a scene holding a link before anything is made in it
    raw_dir = scene.path / "raw"
    raw_dir.mkdir(exist_ok=True)
    done = {shot.index for shot in scene.shots()}
    measured = pending = meta = None
    for step in plan_capture(angles_deg, done):
        if step.kind == "home":
            stage.info()
            stage.home()
        elif step.kind == "move":
            command = (step.angle_deg - offset_deg) % 360.0
            for _ in range(move_attempts):
                measured = stage.move_to(command)
                if _angle_error(measured, command) <= tolerance_deg:
                    break
        elif step.kind == "verify":
            command = (step.angle_deg - offset_deg) % 360.0
            if _angle_error(measured, command) > tolerance_deg:
                raise DeviceError(
                    f"stage reads {measured:.3f} deg after {move_attempts} moves to {command:.3f} deg "
                    f"(tolerance {tolerance_deg} deg); shot {step.index} not taken"
                )
        elif step.kind == "trigger":
            try:
                pending, meta = camera.capture(raw_dir, step.index)
            except RawFormatError as exc:
                raise DeviceError(f"shot {step.index} at {step.angle_deg:g} deg: {exc}") from exc
            except OSError as exc:
                if disk_full(exc, raw_dir):
                    raise write_error(raw_dir / shot_name(step.index, step.angle_deg, ""), exc, full=True) from exc
                raise DatasetError(f"cannot write shot {step.index} in {raw_dir} (disk full or read-only?): {exc.strerror or exc}") from exc
        elif step.kind == "store":
            target = raw_dir / shot_name(step.index, step.angle_deg, pending.suffix)
            if target.exists():
                _set_aside(target)
            digest = sha256_file(pending)
            with atomic_path(target) as tmp:
                shutil.move(pending, tmp)
                tmp.chmod(0o644)                       # like every other output (the camera's file may be private)
            if sha256_file(target) != digest:
                raise DeviceError(f"{target}: contents changed while storing")
            pending = target
        elif step.kind == "record":
            scene.add_shot(step.index, pending, step.angle_deg, angle_measured_deg=round((measured + offset_deg) % 360.0, 4),
                           stage_position_deg=round(measured, 4), camera=meta)
        elif step.kind == "finish":
            finish_capture(scene)
        if progress is not None:
            progress(step)
    return scene


DEFAULT_ANGLES_DEG = (0.0, 45.0, 90.0)


def resume_command(root: Path, scene: Scene) -> str:
    """The command line that resumes ``scene`` with the plan and devices its manifest records:
    its stage port and address, camera, angles and tolerance, and for the simulated stage and
    virtual camera their settings (those that differ from `acquire.rig.SimSettings`' defaults)."""
    from acquire.rig import SimSettings

    capture = scene.load(verify=False)["capture"]
    stage, camera = capture.get("stage", {}), capture.get("camera", {})
    angles = ",".join(f"{a:g}" for a in capture["angles_deg"])
    words = ["urd", "capture", str(Path(root).resolve()), "--stage", stage.get("port", "PORT"),
             "--camera", camera.get("kind", "gphoto2"), "--angles", angles, "--scene", scene.name]
    if stage.get("address", "0") != "0":
        words += ["--address", stage["address"]]
    if capture.get("tolerance_deg", 0.5) != 0.5:
        words += ["--tolerance", f"{capture['tolerance_deg']:g}"]
    default = SimSettings()
    simulated = stage.get("simulated")
    options = {}
    if simulated is not None:
        faults = ",".join(f"{kind}={prob:g}" for kind, prob in simulated["faults"].items())
        options.update({"--sim-offset": (simulated["offset_deg"], default.offset_deg),
                        "--sim-jitter": (simulated["jitter_deg"], default.jitter_deg),
                        "--sim-faults": (faults, ""), "--seed": (simulated.get("seed", default.seed), default.seed)})
    if camera.get("kind") == "virtual":
        options.update({"--sim-size": (f"{camera['width']}x{camera['height']}", f"{default.width}x{default.height}"),
                        "--sim-shake": (camera["shake_px"], default.shake_px), "--seed": (camera["seed"], default.seed),
                        "--sim-turn": (camera.get("shake_deg", 0.0), default.shake_deg if camera["shake_px"] > 0 else 0.0),
                        "--reflection": (camera.get("reflection"), None), "--transmission": (camera.get("transmission"), None)})
    for option, (value, usual) in options.items():
        if value != usual:
            words += [option, f"{value:g}" if isinstance(value, float) else str(value)]
    if simulated is not None and simulated.get("reversed"):
        words.append("--sim-reversed")
    return " ".join(shlex.quote(word) for word in words)


def recorded_mismatches(scene: Scene, info: dict) -> list[str]:
    """How the devices in ``info`` (`acquire.rig.open_rig`'s) differ from those ``scene`` was
    captured with: the camera's description field by field (fields the scene does not record
    are not compared) and the stage's identity (`acquire.rig.stage_identity`), `printable`."""
    from acquire.rig import describe_stage, stage_identity

    capture = scene.load(verify=False)["capture"]
    problems = []
    recorded = capture.get("camera", {})
    for key, value in recorded.items():
        if info["camera"].get(key) != value:
            problems.append(printable(f"camera {key} {value} (this one: {info['camera'].get(key)})"))
    if "stage" in capture:
        was, now = stage_identity(capture["stage"]), stage_identity(info["stage"])
        if was != now:
            problems.append(printable(f"stage {describe_stage(was)} (this one: {describe_stage(now)})"))
    return problems


def check_resumable(scene: Scene, info: dict, angles_deg: list[float] | None, tolerance_deg: float | None,
                    resume: str) -> None:
    """ManifestError unless ``scene`` can go on with these devices, angles and tolerance
    (None: the scene's own); the message ends with the command ``resume`` that can."""
    planned = scene.capture_angles_deg()
    problems = recorded_mismatches(scene, info)
    if angles_deg is not None and planned != [float(a) for a in angles_deg]:
        problems.append(f"angles {planned} deg (asked for: {[float(a) for a in angles_deg]})")
    recorded_tolerance = scene.capture_settings()[1]
    if tolerance_deg is not None and float(tolerance_deg) != recorded_tolerance:
        problems.append(f"tolerance {recorded_tolerance:g} deg (asked for: {tolerance_deg:g})")
    if problems:
        raise ManifestError(f"{scene.name} was captured with " + "; ".join(problems) + ". Its shots must all come "
                            f"from one plan and one rig: resume it with: {resume}\nor start another scene with --new-scene")


def finish_capture(scene: Scene) -> None:
    """Mark ``scene`` complete with the plan it recorded (every planned shot is taken)."""
    offset_deg, tolerance_deg = scene.capture_settings()
    scene.mark_complete({"angles_deg": scene.capture_angles_deg(), "offset_deg": offset_deg, "tolerance_deg": tolerance_deg})


def _stopped(scene: Scene, root: Path) -> str:
    """What a stopped capture left, for its message: nothing, a complete scene (every shot was
    taken: marked complete here if it was not yet), or completed shots and the resume command."""
    if scene.discard_if_empty():
        return "no shot was taken, no scene was kept"
    if len(scene.shots()) == len(scene.capture_angles_deg()):
        if not scene.is_complete():
            finish_capture(scene)
        return f"every shot was taken: {scene.path.resolve()} is complete"
    return f"completed shots are kept. Resume with: {resume_command(root, scene)}"


def capture_scene(root: Path, stage: str, camera: str, angles_deg: list[float] | None = None,
                  scene_name: str | None = None, new: bool = False, tolerance_deg: float | None = None,
                  address: str = "0", sim=None, announce: Callable[[str], None] = print,
                  progress: Progress | None = None) -> Scene:
    """Capture one scene into the dataset at ``root`` (created when new): the workflow of
    ``urd capture``.

    Without ``scene_name`` the newest incomplete scene is resumed (unless ``new``), or the newest
    whose ground truth a stopped capture set aside (`_lost_truth`), else a new scene is made;
    with it, that scene is resumed or created. A resumed scene keeps its own
    plan (angles, offset, tolerance; ``angles_deg`` and ``tolerance_deg`` None take them, other
    values must match) and must be captured with the camera and stage it recorded. A new scene
    takes ``angles_deg`` (default `DEFAULT_ANGLES_DEG`), ``tolerance_deg`` (default 0.5) and the
    dataset's mounting offset calibration of this stage (`acquire.rig.offset_for_stage`).
    ``scene_name`` with ``new``, and a tolerance outside `MIN_TOLERANCE_DEG`..`MAX_TOLERANCE_DEG`,
    are a ValueError. The rig is opened before the dataset or any scene is made, and a scene
    that got no shot is removed, so a failing start leaves nothing. Errors and Ctrl-C are re-raised with the
    command that resumes the capture; once every shot is taken the scene is complete instead.
    """
    from acquire.rig import offset_for_stage, open_rig

    if scene_name is not None and not SCENE_NAME.match(scene_name):
        raise DatasetError(f"expected a scene name like scene_01, got {scene_name!r}")
    if scene_name is not None and new:
        raise ValueError(f"expected a scene name or a new scene, not both (scene {scene_name!r} and new)")
    if tolerance_deg is not None and not MIN_TOLERANCE_DEG <= tolerance_deg <= MAX_TOLERANCE_DEG:
        raise ValueError(f"expected a tolerance between {MIN_TOLERANCE_DEG:g} and {MAX_TOLERANCE_DEG:g} deg, got {tolerance_deg:g}")
    with open_rig(stage, camera, address, sim) as rig:
        with Dataset.made_for(root) as ds, ds.lock():    # one that fails before its first shot leaves no dataset
            ds.remove_stale()
            scene = None
            if scene_name and (ds.root / scene_name).is_dir():
                scene = ds.scene(scene_name)
            elif scene_name is None and not new:
                scene = ds.latest_incomplete()
                if scene is not None:
                    announce(f"resuming the incomplete capture {scene.path.resolve()} ({len(scene.shots())} of "
                             f"{len(scene.capture_angles_deg() or [])} shots; --new-scene starts another)")
                else:
                    scene = _lost_truth(ds, rig.info)
                    if scene is not None:
                        announce(f"writing the ground truth of {scene.path.resolve()}, which its capture did not "
                                 "finish (--new-scene starts another scene)")
            if scene is None:
                offset_deg, line = offset_for_stage(ds, rig.info["stage"])
                announce(line)
                scene = new_capture_scene(ds, list(angles_deg or DEFAULT_ANGLES_DEG), offset_deg,
                                          0.5 if tolerance_deg is None else tolerance_deg, rig.info, scene_name)
            elif scene.is_complete() and not _truth_missing(scene, rig.info):
                raise DatasetError(f"{scene.name} is complete ({len(scene.shots())} shots); capture another scene: "
                                   "--new-scene, or --scene with a new name")
            else:
                check_resumable(scene, rig.info, angles_deg, tolerance_deg, resume_command(ds.root, scene))
                announce(f"mounting offset: {scene.capture_settings()[0]:.3f} deg, as {scene.name} recorded when it was started")
            planned = scene.capture_angles_deg()
            done = {shot.index for shot in scene.shots()}
            steps = len(plan_capture(planned, done))
            announce(f"capturing {scene.path.resolve()} at {planned} deg ({len(planned) - len(done)} shot{'' if len(planned) - len(done) == 1 else 's'} to take)")
            try:
                with _shown(rig.stage, progress, steps, f"capture {scene.name}", announce) as show:
                    run_capture(scene, rig.stage, rig.camera, planned, progress=show)
                if not scene.truth_dir().exists():
                    rig.camera.write_truth(scene.truth_dir())
                    for aside in scene.path.glob("truth-incomplete-*"):     # what a stopped writing of it left
                        shutil.rmtree(aside, ignore_errors=True)
            except KeyboardInterrupt as exc:
                raise capture_stopped(exc, "capture", _stopped(scene, ds.root)) from None
            except (UrdError, OSError) as exc:
                raise UrdError(f"{exc}\ncapture of {scene.name} stopped; {_stopped(scene, ds.root)}") from exc
            except Exception as exc:                       # a defect: its traceback, and the scene left tidy
                exc.add_note(f"capture of {scene.name} stopped; {_stopped(scene, ds.root)}")
                raise
    return scene


@contextlib.contextmanager
def _shown(stage, progress: Progress | None, steps: int, label: str,
           announce: Callable[[str], None]) -> Iterator[Callable[[Step], None]]:
    """A `run_capture` progress callback counting steps, with the stage's waits and retries
    shown: the bar is redrawn while a reply is awaited (its clock runs through a lost reply's
    time-out) and each retry is announced with its reason. The stage's hooks are removed after."""
    done = 0

    def show(step: Step) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, steps, label)

    def waiting() -> None:
        if progress is not None:
            progress(done, steps, label)

    stage.on_wait, stage.on_retry = waiting, lambda line: announce(f"stage: {line}")
    waiting()
    try:
        yield show
    finally:
        stage.on_wait = stage.on_retry = None


def _truth_missing(scene: Scene, rig_info: dict) -> bool:
    """Whether a virtual-camera scene lacks its ground truth (a capture stopped while writing it:
    the dataset's recovery set the torn folder aside); resuming it writes the truth again."""
    return rig_info["camera"].get("kind") == "virtual" and not scene.truth_dir().exists()


def _lost_truth(ds: Dataset, rig_info: dict) -> Scene | None:
    """The newest complete scene whose ground truth a stopped capture set aside
    (`Scene.lost_truth`), captured with the devices of ``rig_info``: resuming it writes the truth."""
    if rig_info["camera"].get("kind") != "virtual":
        return None
    for scene in reversed(ds.scenes()):
        if (scene.status().state not in ("broken", "incomplete") and scene.lost_truth()
                and not recorded_mismatches(scene, rig_info)):
            return scene
    return None


def _set_aside(path: Path) -> None:
    """Move an unrecorded file (left by an interrupted store) aside instead of overwriting it."""
    aside = path.parent / "unrecorded"
    aside.mkdir(exist_ok=True)
    n = 0
    while (aside / f"{path.stem}.{n}{path.suffix}").exists():
        n += 1
    path.rename(aside / f"{path.stem}.{n}{path.suffix}")
