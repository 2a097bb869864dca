"""Ingest: RAW shots → dataset scenes of aligned, linear polarization stacks.

`ingest` is the workflow of ``urd ingest``; it takes

* a folder of RAW files: grouped into new scenes (by capture time and count, angles in the
  order given); files already in the dataset (same SHA-256) are reported and skipped, so
  ingesting a folder twice, or a scene's own ``raw/``, makes no duplicate; a file that cannot
  be decoded is reported by name;
* a captured scene, or a whole dataset: every complete scene not yet ingested, in place;
  incomplete captures are reported with the command that resumes them;
* polarization-camera frames (``mosaic``): one scene per frame.

Processing decodes every shot to linear RGB (`urd.core.raw.decode`), aligns shots 1.. to shot 0 with
ECC (`urd.core.align`), and writes ``aligned/shot_NN.tiff``: 16-bit linear RGB, value/65535 being the
decoded linear value. Outputs are staged and swapped in only on success (`Scene.set_ingest`).
New scenes are assembled in a hidden folder and moved into place only when complete. A scene
whose alignment fails is flagged in its manifest and gets no aligned stack. Ingesting a scene
again (``redo``) supersedes what was computed from its earlier alignment: its results are
marked stale and its per-shot angle calibration is removed (kept in the provenance).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import re
import shlex
import shutil
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Iterable

import numpy as np
import tifffile

from acquire.plan import resume_command
from urd.core import raw as rawio
from urd.core.align import Alignment, Motion, align, apply_warp, prepare_target
from urd.core.dataset import Dataset, Scene
from urd.core.swap import STAGING_PREFIX
from urd.core.errors import AlignmentError, DatasetError, RawFormatError, UrdError
from urd.core.files import atomic_path, sha256_file
from urd.core.processes import kept_note, process_pool
from urd.core.manifest import printable, renew_command
from urd.core.images import IMAGE_SUFFIXES, Transfer, codes_to_linear, linear_to_u16, read_raw_codes
from urd.core.mosaic import MosaicLayout
from urd.core.progress import Progress


@dataclasses.dataclass
class IngestOptions:
    """How shots are grouped, decoded and aligned."""

    angles_deg: tuple[float, ...] = (0.0, 45.0, 90.0)
    motion: Motion = Motion.EUCLIDEAN
    half_size: bool = False
    gap_s: float = 60.0
    redo: bool = False

    def record(self) -> dict:
        """What a scene's ingest record keeps: how it was decoded and aligned (the angles are its
        shots', the grouping of a RAW folder its capture record's)."""
        return {"motion": self.motion.value, "half_size": self.half_size}


@dataclasses.dataclass
class SceneOutcome:
    """What happened to one scene or file group: ``state`` is ingested, failed (``error``
    says why), skipped (already ingested: ``error`` says where) or incomplete; ``notes`` are
    warnings for the user (shots taken at different exposures)."""

    name: str | None
    files: list[Path]
    error: str | None = None
    state: str = "ingested"
    notes: list[str] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class IngestReport:
    """Outcomes of one ``urd ingest`` run, the files it ignored (not RAW by name) and notes for
    the user (how shots were grouped where that is a guess)."""

    outcomes: list[SceneOutcome]
    ignored: list[Path]
    notes: list[str] = dataclasses.field(default_factory=list)

    @property
    def failed(self) -> list[SceneOutcome]:
        return [o for o in self.outcomes if o.state == "failed"]


def find_raw_files(folder: Path) -> tuple[list[Path], list[Path]]:
    """RAW files (by suffix) and other files in ``folder`` (not recursive)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such folder")
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    raws = [p for p in files if p.suffix.lower() in rawio.RAW_SUFFIXES]
    return raws, [p for p in files if p not in raws]


#: urd's own shot file names (`acquire.plan.shot_name`): shot_NN_ANGLEdeg.SUFFIX.
SHOT_NAME = re.compile(r"shot_(\d+)_(-?\d+(?:\.\d+)?)deg\.[^.]+\Z")


def named_angles(paths: list[Path]) -> list[float] | None:
    """The polarizer angles (deg) that urd's own shot files carry in their names, by shot number
    (shot_00 first), where every file is so named and each shot number names one angle; else None."""
    named: dict[int, float] = {}
    for path in paths:
        match = SHOT_NAME.match(path.name)
        if match is None or named.setdefault(int(match.group(1)), float(match.group(2))) != float(match.group(2)):
            return None
    return [named[k] for k in sorted(named)] if named and sorted(named) == list(range(len(named))) else None


def read_shots(paths: list[Path], progress: Progress | None = None) -> tuple[dict[Path, dict], dict[Path, str]]:
    """Each file's RAW metadata (`urd.core.raw.metadata`), read once, and for each file that
    cannot be ingested (empty, corrupt, not RAW) why."""
    metas, unreadable = {}, {}
    for done, path in enumerate(paths, 1):
        if path.stat().st_size == 0:
            unreadable[path] = "empty file"
        else:
            try:
                metas[path] = rawio.metadata(path)
            except RawFormatError as exc:
                unreadable[path] = str(exc).removeprefix(f"{path}: ")
        if progress:
            progress(done, len(paths), "read RAW files")
    return metas, unreadable


def capture_time(path: Path, meta: dict | None) -> float:
    """Capture time (POSIX s) from the RAW metadata ``meta``, else the file's modification time."""
    if meta and meta["time"]:
        return _dt.datetime.fromisoformat(meta["time"]).timestamp()
    return path.stat().st_mtime


def group_shots(files: list[Path], metas: dict[Path, dict], count: int,
                gap_s: float) -> tuple[list[list[Path]], list[SceneOutcome], list[str]]:
    """Group files into scenes of ``count`` shots: by capture time (`capture_time` of their
    ``metas``), split at gaps > ``gap_s``.

    Returns the complete groups, for runs whose length is not a multiple of ``count`` a failed
    outcome naming the files, and a note for each run split into several scenes (one capture at
    more angles than ``count`` looks the same) and for each scene whose shots share a capture time
    (cameras record whole seconds) with file numbers that wrap around (`counter_wraps`): their
    order, and so their angles, follows the file names (`name_order`), which is not the shooting
    order then.
    """
    timed = sorted((capture_time(f, metas.get(f)), name_order(f.name), f) for f in files)
    when = {f: t for t, _, f in timed}
    runs, current, last = [], [], None
    for t, _, f in timed:
        if last is not None and t - last > gap_s:
            runs.append(current)
            current = []
        current.append(f)
        last = t
    if current:
        runs.append(current)
    groups, failures, notes = [], [], []
    for run in runs:
        if len(run) % count:
            failures.append(SceneOutcome(None, run, f"wrong shot count: {len(run)} shots taken together "
                                                    f"({', '.join(p.name for p in run)}) is not a multiple of {count} angles; "
                                                    f"shots more than --gap {gap_s:g} s apart start a new scene, and "
                                                    "--angles gives the angles of one scene's shots", "failed"))
            continue
        groups += [run[i : i + count] for i in range(0, len(run), count)]
        if len(run) > count:
            notes.append(f"{len(run)} shots taken together ({run[0].name} … {run[-1].name}) became "
                         f"{len(run) // count} scenes of {count} angles; if they are one capture at {len(run)} "
                         "angles, move those scenes away and ingest the files again with --angles")
    for group in groups:
        tied = [[f.name for f in group if when[f] == t] for t in {when[f] for f in group}]
        if any(len(names) > 1 and counter_wraps(names) for names in tied):
            notes.append(f"{', '.join(p.name for p in group)}: shots with one capture time (cameras record whole "
                         "seconds) are ordered, and given their angles, by file name, and these file numbers wrap "
                         "around (a camera's counter rolling over, IMG_9999 → IMG_0001): check each shot's angle")
    return groups, failures, notes


def name_order(name: str) -> tuple:
    """Sort key of a file name with its numbers compared as numbers (frame_8 before frame_10)."""
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name))


def identical_pairs(files: list[Path], digests: dict[Path, str]) -> list[tuple[Path, Path]]:
    """(earlier, later) pairs of ``files`` with the same content (SHA-256 ``digests``), in file order."""
    return [(q, p) for k, p in enumerate(files) for q in files[:k] if digests[q] == digests[p]]


def counter_wraps(names: list[str]) -> bool:
    """Whether the file numbers ending the names (IMG_9998, IMG_9999, IMG_0001) span more than half
    their digits' range: a camera's counter that rolled over between the shots."""
    numbers = [re.search(r"(\d+)$", Path(name).stem) for name in names]
    if not all(numbers):
        return False
    values = [int(m.group(1)) for m in numbers]
    return max(values) - min(values) > 10 ** max(len(m.group(1)) for m in numbers) // 2


#: Exposure settings the shots of a scene should share (the separation assumes one exposure):
#: camera metadata key, what it is, and the text before and after its values.
EXPOSURE_SETTINGS = (("exposure_s", "exposure times", "", " s"), ("iso", "ISO speeds", "", ""), ("aperture", "apertures", "f/", ""))


def exposure_warning(cameras: list[dict | None]) -> str | None:
    """What differs between the exposure settings of a scene's shots, from their camera metadata
    (`urd.core.raw.metadata`: exposure time (s), ISO speed, aperture (f-number)), or None when
    they agree; a setting a shot does not record is compared among the others. The camera models
    it names are `printable` (a RAW file's metadata may hold terminal escapes).

    Raises AlignmentError when the shots come from different camera models.
    """
    records = [camera or {} for camera in cameras]
    models = [printable(str(r.get("model") or "?")) for r in records]
    if len(set(models) - {"?"}) > 1:
        raise AlignmentError(f"the shots come from different cameras ({', '.join(models)}): a scene is one camera's "
                             "shots of one view; put each camera's shots in a folder of their own")
    differ = []
    for key, what, prefix, unit in EXPOSURE_SETTINGS:
        values = [r.get(key) for r in records]
        if len({v for v in values if v is not None}) > 1:
            differ.append(f"{what} differ ({', '.join('?' if v is None else f'{prefix}{v:g}' for v in values)}{unit})")
    if not differ:
        return None
    return (f"the shots' {' and '.join(differ)}: auto-exposure? the separation assumes one exposure; "
            "set the camera to manual")


def _exposure_notes(scene: Scene) -> list[str]:
    """`exposure_warning` of a recorded scene's shots as a note naming the scene (none when
    they agree); AlignmentError when they come from different cameras."""
    warning = exposure_warning([shot.camera for shot in scene.shots()])
    return [] if warning is None else [f"{scene.name}: {warning}"]


def write_aligned(path: Path, image: np.ndarray) -> None:
    """Write a linear image as 16-bit TIFF (`urd.core.images.linear_to_u16`, 1.0 = 65535), atomically."""
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, linear_to_u16(image), photometric="rgb")


#: Shots decoded, aligned and written at a time by one ingest (threads: rawpy, OpenCV, NumPy and
#: file writes run outside Python's lock): on two cores each step takes about half the wall time,
#: for the memory of one more shot (each shot is written once aligned; the reference's pyramid stays).
INGEST_THREADS = 2


@dataclasses.dataclass
class PreparedIngest:
    """A scene decoded and aligned, its aligned shots written into a staging folder inside the
    scene, not yet recorded (`prepare_ingest`; `commit_ingest` records it)."""

    scene: Path
    ok: bool
    alignment: list | str
    staging: Path | None
    staged: dict[str, Path]
    error: str | None = None
    options: dict | None = None             # the options to record, where not the ingest's own (a mosaic frame's)


#: The alignment record of a polarization-camera frame's channels.
SIMULTANEOUS = "none: the channels of a division-of-focal-plane sensor are simultaneous"


def prepare_ingest(scene: Scene, opts: IngestOptions, progress: Progress | None = None) -> PreparedIngest:
    """Decode and align the shots of ``scene`` and stage ``aligned/`` in a new staging folder of
    the scene, without touching its manifest (so that several processes can prepare scenes of
    one dataset while one commits them; the dataset's recovery removes the folder should the
    process die first). A scene made from a polarization-camera frame is demosaiced again
    instead, as it was first ingested.

    Raises RawFormatError for an undecodable shot, AlignmentError for mixed sizes; a failed
    alignment is prepared as ok false, with no aligned stack.
    """
    if "mosaic" in scene.ingest_options():
        return _prepare_mosaic(scene, progress)
    paths = scene.raw_paths()
    label = f"ingest {scene.name}"
    if progress:
        progress(0, len(paths), label)
    staging = scene.new_staging()
    staged = {f"aligned/shot_{i:02d}.tiff": staging / f"shot_{i:02d}.tiff" for i in range(len(paths))}
    written = list(staged.values())
    prepared: Future = Future()                                   # (reference shape, Target) once shot 0 is decoded

    def aligned(i: int) -> Alignment:                             # decoded, aligned, written: one shot in memory
        image = rawio.decode(paths[i], opts.half_size)
        shape, target = prepared.result()
        if image.shape != shape:
            raise AlignmentError(f"{paths[i]}: size {image.shape[1]}×{image.shape[0]} differs from "
                                 f"{paths[0].name} ({shape[1]}×{shape[0]})")
        result = align(target, image, opts.motion)
        if result.ok:
            image = apply_warp(image, result.warp)               # the decoded shot goes once warped
            write_aligned(written[i], image)
        return result

    pool = ThreadPoolExecutor(INGEST_THREADS)
    try:
        decoding = pool.submit(rawio.decode, paths[0], opts.half_size)
        runs = pool.map(aligned, range(1, len(paths)))            # the first shot decoded beside the reference
        try:
            reference = decoding.result()
            prepared.set_result((reference.shape, prepare_target(reference)))    # once for every shot
        finally:
            if not prepared.done():
                prepared.set_exception(AlignmentError(f"{paths[0]}: the reference shot was not decoded"))
        write_aligned(written[0], reference)
        del reference
        results = []
        for i, result in enumerate(runs, start=1):
            if progress:
                progress(i, len(paths), label)
            results.append(result)
    except BaseException:
        pool.shutdown(cancel_futures=True)                        # the shots not begun are not decoded (Ctrl-C)
        shutil.rmtree(staging, ignore_errors=True)
        raise
    pool.shutdown()
    alignment = [{"shot": 0, "reference": True}] + [{"shot": i, **r.record()} for i, r in enumerate(results, 1)]
    if not all(r.ok for r in results):
        shutil.rmtree(staging, ignore_errors=True)
        bad = [f"shot {i}: {r.reason}" for i, r in enumerate(results, 1) if not r.ok]
        return PreparedIngest(scene.path, False, alignment, None, {},
                              "alignment failed, no aligned stack written (" + "; ".join(bad) + ")")
    if progress:
        progress(len(paths), len(paths), label)
    return PreparedIngest(scene.path, True, alignment, staging, staged)


def _prepare_mosaic(scene: Scene, progress: Progress | None = None) -> PreparedIngest:
    """`prepare_ingest` of a scene made from a polarization-camera frame: demosaic its frame
    again with the layout, demosaicing and transfer it was ingested with."""
    from urd.core.mosaic import Demosaic

    options = scene.ingest_options()
    frame = scene.raw_paths()[0]
    if progress:
        progress(0, 1, f"ingest {scene.name}")
    stack, _ = _demosaiced(frame, MosaicLayout(options["mosaic"]), Demosaic(options["demosaic"]),
                           Transfer(options["transfer"]))
    staging = scene.new_staging()
    try:
        staged = _write_stack(staging, stack)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if progress:
        progress(1, 1, f"ingest {scene.name}")
    return PreparedIngest(scene.path, True, SIMULTANEOUS, staging, staged, options=options)


def _demosaiced(path: Path, layout, demosaic, transfer: Transfer) -> tuple[np.ndarray, list[float]]:
    """A frame's linear RGB stack (mono sensors give grey RGB) and its polarizer angles (deg).

    Raises RawFormatError for a frame that is not a mosaic, or too small (or too narrow) to
    separate once demosaiced at half size (`separate.presentation.check_stack`).
    """
    from separate.presentation import check_stack
    from urd.core.mosaic import demosaic as run_demosaic

    data = read_raw_codes(path)
    if data.ndim != 2 or data.dtype not in (np.uint8, np.uint16):
        raise RawFormatError(f"{path}: expected a single-channel 8- or 16-bit mosaic image, got {data.dtype} {data.shape}")
    codes, angles = run_demosaic(data, layout, demosaic)
    stack = codes_to_linear(codes, data.dtype, transfer)
    try:
        check_stack(stack, angles)
    except ValueError as exc:
        raise RawFormatError(f"{path}: the {data.shape[1]}×{data.shape[0]} px frame gives {stack.shape[2]}×{stack.shape[1]} "
                             f"px images (one pixel per 2×2 polarizer cell), too small to separate ({exc})") from exc
    return (np.repeat(stack, 3, axis=-1) if stack.shape[-1] == 1 else stack), [float(a) for a in angles]


def _write_stack(staging: Path, shots: Iterable[np.ndarray]) -> dict[str, Path]:
    """Write shots (H×W×C linear) as aligned TIFFs into ``staging``, `INGEST_THREADS` at a
    time; final name → staged path."""
    files, writes = {}, []
    with ThreadPoolExecutor(INGEST_THREADS) as pool:
        for i, shot in enumerate(shots):
            files[f"aligned/shot_{i:02d}.tiff"] = staging / f"shot_{i:02d}.tiff"
            writes.append(pool.submit(write_aligned, files[f"aligned/shot_{i:02d}.tiff"], shot))
    for write in writes:
        write.result()                                      # a failed write raises here
    return files


def commit_ingest(scene: Scene, prepared: PreparedIngest, opts: IngestOptions) -> str | None:
    """Record a prepared ingest in the scene's manifest (`Scene.set_ingest`; the caller holds the
    dataset's lock); the staging folder is removed either way. Returns the error of an ingest
    that failed, None for one that aligned; a failed redo keeps the scene's earlier aligned shots."""
    try:
        recorded = scene.set_ingest(prepared.ok, prepared.options or opts.record(), prepared.alignment,
                                    prepared.staged, error=prepared.error)
    finally:
        if prepared.staging is not None:
            shutil.rmtree(prepared.staging, ignore_errors=True)
    if prepared.ok:
        return None
    return prepared.error if recorded else f"{prepared.error}; the earlier aligned shots and results are kept"


def process_scene(scene: Scene, opts: IngestOptions, progress: Progress | None = None) -> str | None:
    """Decode and align the shots of ``scene``, stage ``aligned/`` and record the ingest
    (`prepare_ingest`, then `commit_ingest`); the error of a failed one, else None."""
    return commit_ingest(scene, prepare_ingest(scene, opts, progress), opts)


def _not_to_ingest(scene: Scene, opts: IngestOptions) -> SceneOutcome | None:
    """Why a captured scene is not processed (broken, incomplete, its alignment failed, already
    ingested), or None."""
    status = scene.reload().status()
    if status.state == "broken":
        return SceneOutcome(scene.name, [], status.problem, "failed")
    if status.state == "incomplete":
        return SceneOutcome(scene.name, [], f"incomplete capture ({status.shots} of {status.expected} shots); "
                            f"resume it with: {resume_command(scene.path.parent, scene)}", "incomplete")
    if status.state == "alignment failed" and not opts.redo:
        error = printable(scene.load(verify=False)["ingest"].get("error", ""))
        return SceneOutcome(scene.name, [], f"its alignment failed ({error}); --redo tries again, e.g. with another "
                            "--motion", "skipped")
    if scene.is_ingested() and not opts.redo:
        aligned = {rec["file"] for rec in scene.load(verify=False)["ingest"].get("aligned", [])}
        missing = [name for name in scene.missing_files() if name in aligned]
        if missing:
            redo = " ".join(shlex.quote(word) for word in ("urd", "ingest", str(scene.path.resolve()), "--redo"))
            return SceneOutcome(scene.name, [], f"ingested, but its aligned shots are missing or changed "
                                f"({', '.join(missing)}); decode and align it again with: {redo}", "failed")
        return SceneOutcome(scene.name, [], "already ingested (--redo decodes and aligns it again)", "skipped")
    return None


def _outcome(scene: Scene, error: str | None, notes: list[str]) -> SceneOutcome:
    """The outcome of a scene whose ingest was committed (`commit_ingest`'s ``error``), with
    ``notes`` for the user, and a note of what the new alignment superseded (`Scene.set_ingest`):
    results marked stale, a per-shot angle calibration removed."""
    if error is None:
        steps = scene.reload().provenance()
        earlier = steps[-2].get("parameters", {}) if len(steps) >= 2 and steps[-2].get("step") == "supersede" else {}
        for method in earlier.get("stale_results", []):
            notes = [*notes, f"{scene.name}: results of {method} are stale (of the earlier alignment); renew them with: "
                             f"{renew_command(scene.path, method)}"]
        if "calibration" in earlier:
            notes = [*notes, f"{scene.name}: its per-shot angle calibration was of the earlier alignment and is removed "
                             f"(kept in the provenance); calibrate again with: urd calibrate shots {scene.name} "
                             f"--dataset {scene.path.parent}"]
    return SceneOutcome(scene.name, scene.raw_paths(), error, "failed" if error else "ingested", notes)


def ingest_scene(scene: Scene, opts: IngestOptions, progress: Progress | None = None) -> SceneOutcome:
    """Process a captured scene in place (not again unless ``opts.redo``)."""
    skipped = _not_to_ingest(scene, opts)
    if skipped is not None:
        return skipped
    try:
        notes = _exposure_notes(scene)
        scene.check_files([{"file": s.file, "size": s.size, "sha256": s.sha256} for s in scene.shots()])
        error = process_scene(scene, opts, progress)
    except Exception as exc:  # noqa: BLE001 - one scene's failure, whatever it is, must not stop the others
        return SceneOutcome(scene.name, [], failure_message(exc), "failed")
    return _outcome(scene, error, notes)


def failure_message(exc: Exception) -> str:
    """What a scene's failed outcome says: urd's own message, else the exception's type and text
    (an OSError of a network share, a decoder's error)."""
    return str(exc) if isinstance(exc, UrdError) else f"{type(exc).__name__}: {exc}"


def _prepare_worker(path: str, opts: IngestOptions) -> PreparedIngest:
    """Worker process: check and prepare one scene (`prepare_ingest`)."""
    scene = Scene(Path(path))
    scene.check_files([{"file": s.file, "size": s.size, "sha256": s.sha256} for s in scene.shots()])
    return prepare_ingest(scene, opts)


def ingest_scenes(scenes: list[Scene], opts: IngestOptions, jobs: int, progress: Progress | None = None) -> list[SceneOutcome]:
    """Ingest captured scenes of one dataset in place with ``jobs`` worker processes: workers
    decode and align (`prepare_ingest`), this process (holding the dataset's lock) records each
    scene as it is done, so a kill leaves every recorded scene intact; a failing scene is reported
    and the others go on. Progress counts scenes."""
    import concurrent.futures

    outcomes, todo, notes = [], [], {}
    for scene in scenes:
        skipped = _not_to_ingest(scene, opts)
        if skipped is not None:
            outcomes.append(skipped)
            continue
        try:
            notes[scene.name] = _exposure_notes(scene)
        except UrdError as exc:
            outcomes.append(SceneOutcome(scene.name, [], str(exc), "failed"))
            continue
        todo.append(scene)
    label = f"ingest ({jobs} jobs)"
    if progress:
        progress(0, len(todo), label)
    try:
        with process_pool(jobs) as pool:                          # workers die with this process; an interrupt kills them
            futures = {pool.submit(_prepare_worker, str(scene.path), opts): scene for scene in todo}
            for done, future in enumerate(concurrent.futures.as_completed(futures), 1):
                scene = futures[future]
                try:
                    error = commit_ingest(scene, future.result(), opts)
                    outcomes.append(_outcome(scene, error, notes[scene.name]))
                except Exception as exc:  # noqa: BLE001 - one scene's failure, whatever it is, must not stop the others
                    outcomes.append(SceneOutcome(scene.name, [], failure_message(exc), "failed"))
                if progress:
                    progress(done, len(todo), label)
    except KeyboardInterrupt as exc:
        _note_kept(exc, outcomes, {scene.name for scene in todo}, opts)
        raise
    order = {scene.name: k for k, scene in enumerate(scenes)}
    return sorted(outcomes, key=lambda o: order.get(o.name, len(order)))


def _note_kept(exc: KeyboardInterrupt, outcomes: list[SceneOutcome], names: set[str], opts: IngestOptions) -> None:
    """Note on an interrupt what the scenes ``names`` ingested before it kept, with what each
    superseded (`_outcome`'s notes: stale results, a removed shot calibration)."""
    kept = [o for o in outcomes if o.name in names and o.state == "ingested"]
    exc.add_note(kept_note([o.name for o in kept], "ingested", opts.redo))
    for note in (note for o in kept for note in o.notes):
        exc.add_note(note)


def ingest_group(ds: Dataset, files: list[Path], metas: list[dict], digests: list[str], opts: IngestOptions,
                 progress: Progress | None = None) -> SceneOutcome:
    """Make a new scene from RAW files taken at ``opts.angles_deg`` (``metas``: their
    `urd.core.raw.metadata`, ``digests`` their SHA-256 as read before); nothing is left on failure."""
    try:
        warning = exposure_warning(metas)
        with ds.staged_scene("ingest", {"source_files": [str(f) for f in files], "angles_deg": list(opts.angles_deg),
                                        "gap_s": opts.gap_s, "complete": True}) as staged:
            (staged.path / "raw").mkdir()
            for i, (src, angle, meta, digest) in enumerate(zip(files, opts.angles_deg, metas, digests)):
                dst = staged.path / "raw" / f"shot_{i:02d}_{angle:05.1f}deg{src.suffix.lower()}"
                with atomic_path(dst) as part:
                    shutil.copyfile(src, part)
                if sha256_file(dst) != digest:
                    raise DatasetError(f"{src}: copy does not match the source (did it change while being ingested?)")
                staged.add_shot(i, dst, angle, time=meta["time"], camera=meta)
            named = progress and (lambda done, total, _: progress(done, total, f"ingest {files[0].name}"))
            error = process_scene(staged, opts, named)  # the staged scene has no name yet: its first file's
            scene = ds.adopt_scene(staged.path)
    except Exception as exc:  # noqa: BLE001 - one group's failure, whatever it is, must not stop the others
        message = re.sub(rf"\S*{re.escape(STAGING_PREFIX)}[^/\s]*/raw/", "", failure_message(exc))    # the staged copies' folder
        if isinstance(exc, AlignmentError) and "differs from" in message:
            message += ("; shots of another camera or setting fell into this scene: put them in another folder, or "
                        "split the scenes with a smaller --gap")
        for i, src in enumerate(files):
            message = message.replace(f"shot_{i:02d}_{opts.angles_deg[i]:05.1f}deg{src.suffix.lower()}", src.name)
        return SceneOutcome(None, files, message, "failed")
    notes = [] if warning is None else [f"{scene.name}: {warning}"]
    return SceneOutcome(scene.name, files, error, "failed" if error else "ingested", notes)


def ingest_folder(raw_dir: Path, ds: Dataset, opts: IngestOptions, progress: Progress | None = None) -> IngestReport:
    """Group, decode and align every new scene in ``raw_dir`` into ``ds``.

    Files whose content the dataset already holds are skipped (one outcome per scene they
    are in); unreadable files are named, with the group they belong to.
    """
    raws, ignored = find_raw_files(raw_dir)
    if not raws:
        frames = [p for p in ignored if p.suffix.lower() in IMAGE_SUFFIXES]
        hint = (f"; it holds {len(frames)} PNG/TIFF/JPEG images: polarization-camera frames are ingested with "
                f"--mosaic {'|'.join(m.value for m in MosaicLayout)} (the sensor's layout), and one image per "
                "polarizer angle is separated with 'urd separate --images A --images B --images C --angles ...'") if frames else ""
        raise DatasetError(f"{raw_dir}: no RAW files (looked for {', '.join(rawio.RAW_SUFFIXES)}){hint}")
    known = ds.shot_index()
    digests = {}
    for done, path in enumerate(raws, 1):
        digests[path] = sha256_file(path)
        if progress:
            progress(done, len(raws), "hash RAW files")
    outcomes, fresh, already = [], [], {}
    for path in raws:
        scene = known.get(digests[path])
        if scene is None:
            fresh.append(path)
        else:
            already.setdefault(scene, []).append(path)
    for scene, paths in already.items():
        try:
            recorded = ds.scene(scene).stage_angles_deg()
        except (UrdError, OSError):                     # a broken scene says so where it is listed
            recorded = list(opts.angles_deg)
        other = "" if [float(a) for a in opts.angles_deg] == [float(a) for a in recorded] else (
            f" at {','.join(f'{a:g}' for a in recorded)} deg (not {','.join(f'{a:g}' for a in opts.angles_deg)}: a "
            f"scene keeps the angles it was ingested with; to record others, move {ds.root / scene} away and ingest "
            "again with --angles)")
        outcomes.append(SceneOutcome(scene, paths, f"already ingested as {scene}{other}", "skipped"))
    if not fresh:
        return IngestReport(outcomes, ignored)
    metas, unreadable = read_shots(fresh, progress)
    groups, failures, notes = group_shots(fresh, metas, len(opts.angles_deg), opts.gap_s)
    for failure in failures:
        bad = [p for p in failure.files if p in unreadable]
        twins = identical_pairs(failure.files, digests)
        if bad:
            failure.error = "; ".join(f"{p.name} is unreadable ({unreadable[p]})" for p in bad)
        elif twins:
            failure.error += "; " + "; ".join(f"{q.name} and {p.name} are the same file (identical content)" for q, p in twins)
    outcomes += failures
    for files in groups:
        bad = [p for p in files if p in unreadable]
        twins = identical_pairs(files, digests)
        if bad:
            outcomes.append(SceneOutcome(None, files, "; ".join(f"{p.name} is unreadable ({unreadable[p]})" for p in bad),
                                         "failed"))
        elif twins:
            first, twin = twins[0]
            outcomes.append(SceneOutcome(None, files, f"{first.name} and {twin.name} are the same file (identical "
                                                      "content): a scene needs one shot per polarizer angle", "failed"))
        else:
            outcomes.append(ingest_group(ds, files, [metas[p] for p in files], [digests[p] for p in files], opts, progress))
    return IngestReport(outcomes, ignored, notes)


def ingest_mosaic(ds: Dataset, path: Path, layout, demosaic, transfer: Transfer = Transfer.LINEAR) -> SceneOutcome:
    """Make a new scene from one division-of-focal-plane frame (8/16-bit PNG or TIFF).

    The frame is demosaiced into its 0/45/90/135 channels (`urd.core.mosaic.demosaic`, the four
    sites registered to common points), which are simultaneous and need no alignment; mono
    sensors give grey RGB. 8-bit codes follow ``transfer`` (`urd.core.images`).
    """
    digest = sha256_file(path)
    owner = ds.shot_index().get(digest)
    if owner is not None:
        return SceneOutcome(owner, [path], f"already ingested as {owner}", "skipped")
    try:
        stack, angles = _demosaiced(path, layout, demosaic, transfer)
        options = {"mosaic": layout.value, "demosaic": str(getattr(demosaic, "value", demosaic)), "transfer": Transfer(transfer).value}
        with ds.staged_scene("ingest", {"source_files": [str(path)], "angles_deg": angles,
                                        "complete": True, **options}) as staged:
            (staged.path / "raw").mkdir()
            dst = staged.path / "raw" / path.name
            with atomic_path(dst) as part:
                shutil.copyfile(path, part)
            for i, angle in enumerate(angles):
                staged.add_shot(i, dst, angle)
            with staged.staging() as staging:
                staged.set_ingest(True, options, SIMULTANEOUS, _write_stack(staging, stack))
            scene = ds.adopt_scene(staged.path)
        return SceneOutcome(scene.name, [path])
    except (UrdError, ValueError) as exc:
        return SceneOutcome(None, [path], str(exc), "failed")


#: Image files whose compression is lossy, by suffix: the kind named in the warning.
LOSSY_KINDS = {".jpg": "JPEG", ".jpeg": "JPEG"}


def lossy_notes(frames: list[Path]) -> list[str]:
    """A warning per lossy kind of file (JPEG) among mosaic ``frames``: lossy compression mixes
    neighbouring pixels, which sit behind different polarizers."""
    kinds: dict[str, list[Path]] = {}
    for frame in frames:
        if frame.suffix.lower() in LOSSY_KINDS:
            kinds.setdefault(LOSSY_KINDS[frame.suffix.lower()], []).append(frame)
    notes = []
    for kind, paths in kinds.items():
        which = paths[0].name if len(paths) == 1 else f"{len(paths)} frames ({paths[0].name} … {paths[-1].name})"
        notes.append(f"{which}: {kind} compression is lossy and mixes neighbouring pixels, which sit behind different "
                     "polarizers, so the polarization is biased; save the camera's frames as PNG or TIFF")
    return notes


def ingest(source: Path, root: Path, opts: IngestOptions, mosaic=None, demosaic="newton",
           transfer: Transfer = Transfer.LINEAR, progress: Progress | None = None, jobs: int = 1) -> IngestReport:
    """The workflow of ``urd ingest``: a RAW folder (or mosaic frames) into the dataset at
    ``root``, or a captured scene / a whole dataset in place (see the module docstring); a
    dataset's scenes with ``jobs`` worker processes when ``jobs`` > 1 (`ingest_scenes`)."""
    if jobs < 1:
        raise ValueError(f"expected at least 1 job, got {jobs}")
    source = Path(source)
    if not source.exists():
        raise DatasetError(f"{source}: no such folder or file")
    if (source / "scene.json").is_file():
        root, scenes = source.parent, [source.name]
    elif (source / "dataset.json").is_file():
        root, scenes = source, None
    else:
        scenes = []
    if jobs > 1 and (scenes == [] or mosaic is not None):
        raise ValueError(f"expected a dataset or scene folder with --jobs {jobs}, got {source}: a RAW folder or "
                         "mosaic frames are ingested by one process (ingest them, then a dataset with --jobs)")
    with Dataset.made_for(root) if scenes == [] else contextlib.nullcontext(Dataset.open(root)) as ds:
        return _ingest_into(ds, source, scenes, opts, mosaic, demosaic, transfer, progress, jobs)


def _ingest_into(ds: Dataset, source: Path, scenes: list[str] | None, opts: IngestOptions, mosaic, demosaic,
                 transfer: Transfer, progress: Progress | None, jobs: int) -> IngestReport:
    """`ingest` once the dataset is open."""
    with ds.lock():
        ds.remove_stale()
        if mosaic is not None:
            files = [source] if source.is_file() else sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not files:
                raise DatasetError(f"{source}: no image files to ingest (expected {', '.join(sorted(IMAGE_SUFFIXES))})")
            outcomes = []
            for i, f in enumerate(files):
                if progress:
                    progress(i, len(files), "ingest mosaics")
                outcomes.append(ingest_mosaic(ds, f, mosaic, demosaic, transfer))
            if progress:
                progress(len(files), len(files), "ingest mosaics")
            ingested = [f for f, outcome in zip(files, outcomes) if outcome.state == "ingested"]
            return IngestReport(outcomes, [], lossy_notes(ingested))
        if scenes == []:
            return ingest_folder(source, ds, opts, progress)
        targets = [ds.root / name for name in (scenes or ds.scene_names())]
        if jobs > 1:
            return IngestReport(ingest_scenes([Scene(path) for path in targets], opts, jobs, progress), [])

        outcomes = []
        try:
            for path in targets:
                outcomes.append(ingest_scene(Scene(path), opts, progress))
        except KeyboardInterrupt as exc:
            _note_kept(exc, outcomes, {path.name for path in targets}, opts)
            raise
        return IngestReport(outcomes, [])
