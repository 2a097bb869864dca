"""Ingest: RAW shots → dataset scenes of aligned, linear polarization stacks.

Two entry points:

* `ingest_folder` groups a folder of RAW files into new scenes (by capture time and count,
  angles in the order given) and processes each; a scene is assembled in a hidden folder and
  renamed into place only when complete, so a failed scene leaves nothing behind.
* `ingest_scene` processes a scene captured by ``urd capture`` in place.

Processing decodes every shot to linear RGB (`urd.raw.decode`), aligns shots 1.. to shot 0
with ECC (`urd.align`), and writes ``aligned/shot_NN.tiff``: 16-bit linear RGB, value/65535
being the decoded linear value. A scene whose alignment fails is flagged in its manifest and
gets no aligned stack.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
import tifffile

from urd import raw as rawio
from urd.align import Motion, align, apply_warp
from urd.dataset import (Dataset, Scene, atomic_path, file_record, new_scene_manifest, now_iso, provenance,
                         sha256_file)
from urd.errors import AlignmentError, DatasetError, RawFormatError, UrdError


@dataclasses.dataclass
class IngestOptions:
    """How shots are grouped, decoded and aligned."""

    angles_deg: tuple[float, ...] = (0.0, 45.0, 90.0)
    motion: Motion = Motion.EUCLIDEAN
    half_size: bool = False
    gap_s: float = 60.0
    redo: bool = False

    def record(self) -> dict:
        return {"angles_deg": list(self.angles_deg), "motion": self.motion.value, "half_size": self.half_size,
                "gap_s": self.gap_s}


@dataclasses.dataclass
class SceneOutcome:
    """What happened to one scene: its name when written, and an error when not (or flagged)."""

    name: str | None
    files: list[Path]
    error: str | None = None


def find_raw_files(folder: Path) -> tuple[list[Path], list[Path]]:
    """RAW files (by suffix) and other files in ``folder`` (not recursive)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such folder")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    raws = [p for p in files if p.suffix.lower() in rawio.RAW_SUFFIXES]
    return raws, [p for p in files if p not in raws]


def capture_time(path: Path) -> float:
    """Capture time (POSIX s) from the RAW metadata, else the file's modification time."""
    try:
        stamp = rawio.metadata(path)["time"]
        if stamp:
            import datetime as _dt

            return _dt.datetime.fromisoformat(stamp).timestamp()
    except RawFormatError:
        pass
    return path.stat().st_mtime


def group_shots(files: list[Path], count: int, gap_s: float) -> tuple[list[list[Path]], list[SceneOutcome]]:
    """Group files into scenes of ``count`` shots: by capture time, split at gaps > ``gap_s``.

    Returns the complete groups and, for runs whose length is not a multiple of ``count``,
    a failed outcome naming the files.
    """
    timed = sorted((capture_time(f), f.name, f) for f in files)
    runs, current, last = [], [], None
    for t, _, f in timed:
        if last is not None and t - last > gap_s:
            runs.append(current)
            current = []
        current.append(f)
        last = t
    if current:
        runs.append(current)
    groups, failures = [], []
    for run in runs:
        if len(run) % count:
            failures.append(SceneOutcome(None, run, f"wrong shot count: {len(run)} shots taken together "
                                                    f"({', '.join(p.name for p in run)}) is not a multiple of {count} angles"))
            continue
        groups += [run[i : i + count] for i in range(0, len(run), count)]
    return groups, failures


def write_aligned(path: Path, image: np.ndarray) -> None:
    """Write a linear image as 16-bit TIFF (value × 65535), atomically."""
    data = np.clip(np.rint(image * 65535.0), 0, 65535).astype(np.uint16)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, data, photometric="rgb")


def read_aligned(path: Path) -> np.ndarray:
    """Read an aligned 16-bit TIFF back to float32 linear."""
    return tifffile.imread(path).astype(np.float32) / 65535.0


def shot_angles(record: dict) -> list[float]:
    """Best known polarizer angle of each shot (deg): calibrated, else measured, else commanded."""
    out = []
    for shot in sorted(record["shots"], key=lambda s: s["index"]):
        for key in ("angle_calibrated_deg", "angle_measured_deg", "angle_commanded_deg"):
            if shot.get(key) is not None:
                out.append(float(shot[key]))
                break
    return out


def process_scene(scene: Scene, record: dict, opts: IngestOptions, progress: Callable[[str], None] | None = None) -> dict:
    """Decode and align the shots of ``scene``; write ``aligned/`` and the ``ingest`` record.

    Raises RawFormatError for an undecodable shot, AlignmentError for mixed sizes; a failed
    alignment is recorded (``ingest.ok`` false) with no aligned stack written.
    """
    paths = scene.shot_paths(record)
    aligned_dir = scene.path / "aligned"
    if aligned_dir.exists():
        if not opts.redo:
            raise DatasetError(f"{scene.path} is already ingested; pass --redo to decode and align it again")
        shutil.rmtree(aligned_dir)
    reference = rawio.decode(paths[0], opts.half_size)
    results, images = [], {0: reference}
    for i, path in enumerate(paths[1:], start=1):
        if progress:
            progress(f"{scene.name}: aligning {path.name}")
        image = rawio.decode(path, opts.half_size)
        if image.shape != reference.shape:
            raise AlignmentError(f"{path}: size {image.shape[1]}×{image.shape[0]} differs from "
                                 f"{paths[0].name} ({reference.shape[1]}×{reference.shape[0]})")
        result = align(reference, image, opts.motion)
        results.append(result)
        if result.ok:
            images[i] = apply_warp(image, result.warp)
    ok = all(r.ok for r in results)
    ingest = {"time": now_iso(), "ok": ok, "options": opts.record(), "angles_deg": shot_angles(record),
              "alignment": [{"shot": 0, "reference": True}] + [{"shot": i, **r.record()} for i, r in enumerate(results, 1)],
              "aligned": []}
    if ok:
        aligned_dir.mkdir()
        for i in range(len(paths)):
            path = aligned_dir / f"shot_{i:02d}.tiff"
            write_aligned(path, images[i])
            ingest["aligned"].append(file_record(scene.path, path))
    else:
        bad = [f"shot {i}: {r.reason}" for i, r in enumerate(results, 1) if not r.ok]
        ingest["error"] = "alignment failed, no aligned stack written (" + "; ".join(bad) + ")"
    record["ingest"] = ingest
    record["provenance"].append(provenance("ingest", opts.record()))
    scene.save(record)
    return record


def ingest_scene(scene: Scene, opts: IngestOptions, progress=None) -> SceneOutcome:
    """Process a captured scene in place."""
    record = scene.load(verify=True)
    record = process_scene(scene, record, opts, progress)
    return SceneOutcome(scene.name, scene.shot_paths(record), None if record["ingest"]["ok"] else record["ingest"]["error"])


def ingest_group(ds: Dataset, files: list[Path], opts: IngestOptions, progress=None) -> SceneOutcome:
    """Make a new scene from RAW files taken at ``opts.angles_deg``; nothing is left on failure."""
    tmp = Path(tempfile.mkdtemp(prefix=".ingest-", dir=ds.root))
    copies: dict[str, str] = {}
    try:
        scene = Scene(tmp)
        (tmp / "raw").mkdir()
        record = new_scene_manifest("pending", "ingest", {"source_files": [str(f) for f in files],
                                                          "angles_deg": list(opts.angles_deg), "complete": True})
        for i, (src, angle) in enumerate(zip(files, opts.angles_deg)):
            meta = rawio.metadata(src)
            dst = tmp / "raw" / f"shot_{i:02d}_{angle:05.1f}deg{src.suffix.lower()}"
            copies[str(dst)], copies[dst.name] = str(src), src.name
            with atomic_path(dst) as part:
                shutil.copyfile(src, part)
            if sha256_file(dst) != sha256_file(src):
                raise DatasetError(f"{src}: copy does not match the source")
            record["shots"].append({"index": i, "angle_commanded_deg": angle, "angle_measured_deg": None,
                                    "angle_calibrated_deg": None, "time": meta["time"] or now_iso(),
                                    **file_record(tmp, dst), "camera": meta})
        record = process_scene(scene, record, opts, progress)
        name = ds.next_scene_name()
        record["name"] = name
        scene.save(record)
        os.rename(tmp, ds.root / name)
        return SceneOutcome(name, files, None if record["ingest"]["ok"] else record["ingest"]["error"])
    except UrdError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        message = str(exc)
        for copy, source in sorted(copies.items(), key=lambda kv: -len(kv[0])):
            message = message.replace(copy, source)
        return SceneOutcome(None, files, message)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def ingest_folder(raw_dir: Path, dataset: Path, opts: IngestOptions, progress=None) -> tuple[list[SceneOutcome], list[Path]]:
    """Group, decode and align every scene in ``raw_dir`` into ``dataset``.

    Returns the outcome of every scene (failures included) and the ignored non-RAW files.
    """
    raws, ignored = find_raw_files(raw_dir)
    if not raws:
        raise DatasetError(f"{raw_dir}: no RAW files (looked for {', '.join(rawio.RAW_SUFFIXES)})")
    ds = Dataset.open_or_create(dataset)
    groups, outcomes = group_shots(raws, len(opts.angles_deg), opts.gap_s)
    for files in groups:
        outcomes.append(ingest_group(ds, files, opts, progress))
        if progress:
            progress(f"scene done: {outcomes[-1].name or 'failed'}")
    return outcomes, ignored


def ingest_mosaic(ds: Dataset, path: Path, layout) -> SceneOutcome:
    """Make a new scene from one division-of-focal-plane frame (8/16-bit PNG or TIFF).

    The frame is split into its 0/45/90/135 channels (`urd.mosaic`), which are simultaneous
    and need no alignment; mono sensors give grey RGB. Values are scaled by the file's bit
    depth (1.0 = its maximum code).
    """
    import cv2

    from urd.mosaic import split_mosaic

    tmp = Path(tempfile.mkdtemp(prefix=".ingest-", dir=ds.root))
    try:
        data = tifffile.imread(path) if path.suffix.lower() in (".tif", ".tiff") else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if data is None or data.ndim != 2 or data.dtype not in (np.uint8, np.uint16):
            raise RawFormatError(f"{path}: expected a single-channel 8- or 16-bit mosaic image")
        stack, angles = split_mosaic(data, layout)
        stack = stack / float(np.iinfo(data.dtype).max)
        if stack.shape[-1] == 1:
            stack = np.repeat(stack, 3, axis=-1)
        (tmp / "raw").mkdir()
        (tmp / "aligned").mkdir()
        dst = tmp / "raw" / path.name
        with atomic_path(dst) as part:
            shutil.copyfile(path, part)
        record = new_scene_manifest("pending", "ingest", {"source_files": [str(path)], "angles_deg": angles,
                                                          "mosaic": layout.value, "complete": True})
        raw_rec = file_record(tmp, dst)
        aligned = []
        for i, angle in enumerate(angles):
            record["shots"].append({"index": i, "angle_commanded_deg": angle, "angle_measured_deg": None,
                                    "angle_calibrated_deg": None, "time": now_iso(), **raw_rec})
            out = tmp / "aligned" / f"shot_{i:02d}.tiff"
            write_aligned(out, stack[i])
            aligned.append(file_record(tmp, out))
        record["ingest"] = {"time": now_iso(), "ok": True, "options": {"mosaic": layout.value}, "angles_deg": angles,
                            "alignment": "none: the channels of a division-of-focal-plane sensor are simultaneous",
                            "aligned": aligned}
        record["provenance"].append(provenance("ingest", {"mosaic": layout.value}))
        name = ds.next_scene_name()
        record["name"] = name
        Scene(tmp).save(record)
        os.rename(tmp, ds.root / name)
        return SceneOutcome(name, [path])
    except (UrdError, ValueError) as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        return SceneOutcome(None, [path], str(exc))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def load_stack(scene: Scene) -> tuple[np.ndarray, list[float]]:
    """The aligned stack (N, H, W, 3) float32 linear and its polarizer angles (deg)."""
    record = scene.load(verify=False)
    ingest = record.get("ingest")
    if not ingest:
        raise DatasetError(f"{scene.name} is not ingested yet; run: urd ingest {scene.path}")
    if not ingest["ok"]:
        raise AlignmentError(f"{scene.name}: {ingest['error']}")
    first = read_aligned(scene.path / ingest["aligned"][0]["file"])
    images = np.empty((len(ingest["aligned"]),) + first.shape, np.float32)   # filled in place: no 2x peak
    images[0] = first
    del first
    for i, f in enumerate(ingest["aligned"][1:], start=1):
        images[i] = read_aligned(scene.path / f["file"])
    return images, shot_angles(record)
