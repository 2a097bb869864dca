"""The capture plan: a plain list of small steps, and the runner that executes it.

`plan_capture` lists the steps (home; then per angle move, verify, trigger, store, record;
finish) without touching hardware, skipping shots already recorded, so a resumed capture
continues where it stopped. `run_capture` executes the steps against a stage and a camera,
writing each RAW file and the scene manifest atomically after every shot.

Angles: the plan works in polarizer angles (degrees, image-plane convention). The stage is
commanded ``polarizer angle − mounting offset`` when a calibration is known.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Callable

from acquire.camera import Camera
from acquire.ell14 import Ell14
from urd.dataset import Scene, atomic_path, file_record, new_scene_manifest, now_iso, provenance, sha256_file
from urd.errors import DatasetError, DeviceError, ManifestError


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


def _angle_error(a_deg: float, b_deg: float) -> float:
    """Smallest difference of two stage angles (deg), modulo 360."""
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def run_capture(
    scene: Scene,
    stage: Ell14,
    camera: Camera,
    angles_deg: list[float],
    offset_deg: float = 0.0,
    tolerance_deg: float = 0.5,
    move_attempts: int = 3,
    capture_info: dict | None = None,
    progress: Callable[[Step], None] | None = None,
) -> dict:
    """Capture (or resume) a scene and return its manifest.

    Args:
        scene: the scene folder (new or partly captured).
        stage, camera: the devices.
        angles_deg: polarizer angles (deg).
        offset_deg: mounting offset: polarizer angle at stage zero (deg).
        tolerance_deg: largest accepted difference of read-back and commanded stage angle.
        move_attempts: moves tried before a position outside the tolerance is an error.
        capture_info: extra capture metadata for the manifest (stage, camera, ...).
        progress: called after every step.
    """
    raw_dir = scene.path / "raw"
    raw_dir.mkdir(parents=True, exist_ok=True)
    if scene.exists():
        record = scene.load(verify=True)
        if record["capture"].get("angles_deg") != list(angles_deg):
            raise ManifestError(
                f"{scene.manifest_path}: scene was captured with angles {record['capture'].get('angles_deg')}, "
                f"not {list(angles_deg)}; use a new scene"
            )
    else:
        record = new_scene_manifest(scene.name, "capture", {
            **(capture_info or {}), "angles_deg": list(angles_deg), "offset_deg": offset_deg,
            "tolerance_deg": tolerance_deg, "started": now_iso(), "complete": False,
        })
        scene.save(record)                        # resumable from the first step on
    done = {shot["index"] for shot in record["shots"]}
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
            except OSError as exc:
                raise DatasetError(f"cannot write shot {step.index} in {raw_dir} (disk full or read-only?): {exc.strerror or exc}") from exc
        elif step.kind == "store":
            target = raw_dir / shot_name(step.index, step.angle_deg, pending.suffix)
            if target.exists():
                _set_aside(target)
            digest = sha256_file(pending)
            with atomic_path(target) as tmp:
                shutil.move(pending, tmp)
            if sha256_file(target) != digest:
                raise DeviceError(f"{target}: contents changed while storing")
            pending = target
        elif step.kind == "record":
            record["shots"].append({
                "index": step.index,
                "angle_commanded_deg": step.angle_deg,
                "angle_measured_deg": round((measured + offset_deg) % 360.0, 4),
                "angle_calibrated_deg": None,
                "stage_position_deg": round(measured, 4),
                "time": now_iso(),
                **file_record(scene.path, pending),
                "camera": meta,
            })
            record["shots"].sort(key=lambda s: s["index"])
            scene.save(record)
        elif step.kind == "finish":
            record["capture"].update(complete=True, finished=now_iso())
            record["provenance"].append(provenance("capture", {"angles_deg": list(angles_deg), "offset_deg": offset_deg,
                                                               "tolerance_deg": tolerance_deg}))
            scene.save(record)
        if progress is not None:
            progress(step)
    return record


def _set_aside(path: Path) -> None:
    """Move an unrecorded file (left by an interrupted store) aside instead of overwriting it."""
    aside = path.parent / "unrecorded"
    aside.mkdir(exist_ok=True)
    n = 0
    while (aside / f"{path.stem}.{n}{path.suffix}").exists():
        n += 1
    path.rename(aside / f"{path.stem}.{n}{path.suffix}")
