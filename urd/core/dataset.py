"""The urd dataset: the one module that reads and writes manifests.

Layout::

    DATASET/
      dataset.json              dataset manifest (schema "urd.dataset")
      calibration.json          mounting offset of the polarizer with its history (schema
                                "urd.calibration"); written by `Dataset.save_calibration`
                                for `calib.store`
      calibration/sweep_NN/     the sweeps behind it: scenes like any other (owned by
                                `calib.store`, created by `Dataset.new_sweep`)
      .urd.lock                 the lock file of commands that write (`Dataset.lock`)
      scene_01/
        scene.json              scene manifest (schema "urd.scene")
        raw/                    the RAW shots as captured, e.g. shot_00_000.0deg.dng
        aligned/                16-bit linear TIFF per shot, aligned to the first shot
        truth/                  ground truth, for scenes from the virtual camera only; its
                                truth.json, written last, holds each file's size and SHA-256
        results/METHOD/         R.tiff, T.tiff (linear 16-bit), sRGB previews, extra maps

Guarantees, all kept here:

* **typed**: commands use `Dataset`, `Scene` and `Shot`; nothing else reads or writes a
  manifest key. Every field is checked on load (`urd.core.manifest`), with errors naming the
  file and the field; newer schema versions are refused.
* **atomic**: every write goes to a temporary file that is renamed into place (`urd.core.files`);
  new outputs of a re-run (``--redo``, ``--force``) are staged beside the old ones and the
  manifest is the commit point (`Scene._commit`): it names the old files, then the staged new
  ones, then the new ones under their final names, never a missing file; old files go only
  after that. A run killed in between is rolled forward when the dataset's lock is next taken
  (`Dataset.recover`).
* **confined**: file paths in a manifest are relative and stay inside their scene folder;
  nothing is written or deleted in a scene that holds a symbolic link, or whose folder is one
  (`Scene.refuse_links`, checked before every write: manifest, staging, swap, recovery), and
  the lock file is opened without following a link (`urd.core.files.pid_lock`).
* **verified**: files are checked against their size and SHA-256 before use (a cache keyed by
  size, mtime, ctime and inode avoids re-hashing unchanged files); `Scene.verify` hashes
  everything in full, ground truth included.
* **locked**: commands that write take the dataset's lock; a second one is told who holds it.
* **idempotent**: `Dataset.shot_index` maps RAW content hashes to scenes, so ingest skips
  shots it already has.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import copy
import dataclasses
import os
import re
import shutil
import tempfile
from pathlib import Path, PurePosixPath
from typing import Any, Callable, Iterator

from urd.core import __version__
from urd.core.errors import DatasetBusyError, DatasetError, ManifestError, UrdError
from urd.core.files import link_error, pid_lock, read_json, refuse_links, sha256_file, write_json_atomic
from urd.core.manifest import (
    DATASET_SCHEMA,
    DATASET_SCHEMA_ALIASES,
    SCHEMA_VERSION,
    confined_path,
    now_iso,
    provenance,
    validate_calibration,
    validate_dataset,
    validate_scene,
    validate_truth,
)

DATASET_MANIFEST = "dataset.json"
SCENE_MANIFEST = "scene.json"
CALIBRATION_FILE = "calibration.json"
LOCK_FILE = ".urd.lock"
HASH_CACHE = ".urd-hashes.json"
TRUTH_FILE = "truth.json"
STAGING_PREFIX = ".staging-"
TEMPORARY = re.compile(r"^\..+(\.tmp(\.[^.]+)?|\.\d+\.link)$")   # `urd.core.files.atomic_path` and `_place` leftovers
SCENE_NAME = re.compile(r"^scene_(\d{2,})$")
VERIFY_TRIES = 5                        # checks of a scene whose manifest a concurrent command keeps changing


# ---------------------------------------------------------------- staged swap


def _file_records(record: dict) -> list[dict]:
    """Every file record a scene manifest names (shots, aligned stack, results), the live dicts."""
    files = list(record["shots"]) + list(record.get("ingest", {}).get("aligned", []))
    return files + [rec for entry in record.get("results", {}).values() for rec in entry["files"]]


def _final_name(name: str) -> str:
    """The final name of a manifest file name: ``.staging-XXXX/aligned/shot_00.tiff`` →
    ``aligned/shot_00.tiff`` (a staged file of a committed swap); other names are final."""
    parts = PurePosixPath(name).parts
    return PurePosixPath(*parts[1:]).as_posix() if parts[0].startswith(STAGING_PREFIX) and len(parts) > 1 else name


def _path_chain(base: Path, relative: str) -> list[Path]:
    """``base/a``, ``base/a/b``, ... ``base/relative``: each path on the way to a relative name."""
    parts = PurePosixPath(relative).parts
    return [Path(base).joinpath(*parts[: i + 1]) for i in range(len(parts))]


def _place(source: Path, target: Path) -> None:
    """Give ``target`` the content of ``source`` in one step (a hard link, else a copy, renamed
    onto it); ``source`` stays."""
    link = target.with_name(f".{target.name}.{os.getpid()}.link")
    link.unlink(missing_ok=True)
    try:
        os.link(source, link)
    except OSError:
        shutil.copy2(source, link)
    try:
        os.replace(link, target)
    except BaseException:
        link.unlink(missing_ok=True)
        raise


# ---------------------------------------------------------------- ground truth


def write_truth_record(folder: Path, info: dict) -> None:
    """Write a ground-truth folder's ``truth.json``: ``info`` (gain, camera, ...) and the size
    and SHA-256 of every other file in ``folder``. Write it last: its presence marks the folder
    complete, and `Scene.verify` checks the files against it."""
    folder = Path(folder)
    files = [{"file": p.name, "size": p.stat().st_size, "sha256": sha256_file(p)}
             for p in sorted(folder.iterdir()) if p.is_file() and p.name != TRUTH_FILE and not p.name.startswith(".")]
    write_json_atomic(folder / TRUTH_FILE, {**info, "files": files})


# ---------------------------------------------------------------- shots and status


@dataclasses.dataclass(frozen=True)
class Shot:
    """One shot of a scene. Angles in degrees (image-plane convention, see README)."""

    index: int
    file: str
    size: int
    sha256: str
    time: str
    angle_commanded_deg: float
    angle_measured_deg: float | None = None
    angle_calibrated_deg: float | None = None
    stage_position_deg: float | None = None
    camera: dict | None = None

    @property
    def angle_deg(self) -> float:
        """Best known polarizer angle: calibrated, else measured, else commanded (deg)."""
        for angle in (self.angle_calibrated_deg, self.angle_measured_deg, self.angle_commanded_deg):
            if angle is not None:
                return float(angle)
        raise AssertionError("a shot always has a commanded angle")

    def record(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class SceneStatus:
    """Where a scene stands. ``state``: broken, incomplete, captured, alignment failed, ingested."""

    name: str
    state: str
    shots: int
    expected: int
    angles_deg: list[float]
    methods: list[str]
    calibrated: bool = False
    problem: str | None = None
    stale: tuple[str, ...] = ()

    def describe(self) -> str:
        """One line for a terminal."""
        if self.state == "broken":
            return f"{self.name}: BROKEN ({self.problem})"
        angles = ",".join(f"{a:g}" for a in self.angles_deg)
        parts = [f"{self.name}: {self.shots} shots at {angles} deg"]
        if self.state == "incomplete":
            parts.append(f"INCOMPLETE ({self.shots} of {self.expected} shots; resume the capture)")
        else:
            parts.append({"captured": "not ingested", "ingested": "aligned",
                          "alignment failed": "ALIGNMENT FAILED"}[self.state])
        parts.append("angles calibrated" if self.calibrated else "nominal angles")
        methods = [f"{m} (STALE: from an earlier alignment; separate again with --force)" if m in self.stale else m
                   for m in self.methods]
        parts.append(", ".join(methods) if methods else "no results")
        return ", ".join(parts)


@dataclasses.dataclass(frozen=True)
class Result:
    """A method's stored results: files by name (``R.tiff`` → path), the reference angle it was
    given (deg), warnings about its input (and that the results are stale, computed from an
    earlier alignment, when they are), the TIFF full scale, PSNR/SSIM against ground truth
    (virtual scenes), and the rest of its record (parameters, weights, time) as ``description``."""

    method: str
    files: dict[str, Path]
    reference_deg: float | None
    warnings: list[str]
    full_scale: float
    truth_metrics: dict | None
    description: dict


@dataclasses.dataclass(frozen=True)
class OffsetCalibration:
    """The polarizer's mounting offset (deg) with its uncertainty, the sweep it was fitted to
    (a scene folder, or None), when, and the stage it was measured on (its identity, as
    `acquire.rig.stage_identity` gives it; None where not recorded)."""

    offset_deg: float
    uncertainty_deg: float
    modulation: float | None
    target_angle_deg: float
    time: str
    sweep: Path | None
    earlier: int
    stage: dict | None = None


# ---------------------------------------------------------------- hash cache


def _stamp(path: Path) -> list[int]:
    """What changes whenever a file's bytes can have changed: size, mtime and ctime (ns), inode
    (ctime cannot be set back, and a copied or restored file gets a new inode)."""
    stat = path.stat()
    return [stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino]


def _hash(scene_dir: Path, path: Path, cache: dict, full: bool) -> str:
    """SHA-256 of ``path``, taken from ``cache`` when its `_stamp` is unchanged (never with
    ``full``); the cache entry is refreshed from what was hashed."""
    key = path.relative_to(scene_dir).as_posix()
    stamp = _stamp(path)
    hit = cache.get(key)
    if not full and isinstance(hit, list) and len(hit) == 5 and hit[:4] == stamp and isinstance(hit[4], str):
        return hit[4]
    digest = sha256_file(path)
    if _stamp(path) == stamp:
        cache[key] = stamp + [digest]
    else:
        cache.pop(key, None)
    return digest


# ---------------------------------------------------------------- scene


class Scene:
    """One scene folder and its manifest. Construct through `Dataset` (or ``Scene(path)`` for
    a scene folder given directly); every change is saved atomically at once."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.name = self.path.name
        self._record: dict | None = None

    # -- reading

    @property
    def manifest_path(self) -> Path:
        return self.path / SCENE_MANIFEST

    def exists(self) -> bool:
        return self.manifest_path.is_file()

    def _data(self) -> dict:
        if self._record is None:
            self._record = validate_scene(read_json(self.manifest_path), str(self.manifest_path), self.path)
        return self._record

    def reload(self) -> "Scene":
        """Forget the cached manifest (another process may have changed it)."""
        self._record = None
        return self

    def load(self, verify: bool = True) -> dict:
        """A validated copy of the manifest, for inspection; with ``verify`` the RAW shots are
        checked against their hashes first."""
        self.reload()
        if verify:
            self.check_files(self._data()["shots"])
        return copy.deepcopy(self._data())

    def shots(self) -> list[Shot]:
        """The recorded shots, in index order."""
        known = {f.name for f in dataclasses.fields(Shot)}
        return [Shot(**{k: v for k, v in s.items() if k in known}) for s in sorted(self._data()["shots"], key=lambda s: s["index"])]

    def angles_deg(self) -> list[float]:
        """Best known polarizer angle of each shot (deg): calibrated, else measured, else commanded."""
        return [shot.angle_deg for shot in self.shots()]

    def uncalibrated_angles_deg(self) -> list[float]:
        """Each shot's measured, else commanded, angle (deg): the base of a calibration."""
        return [dataclasses.replace(s, angle_calibrated_deg=None).angle_deg for s in self.shots()]

    def capture_angles_deg(self) -> list[float] | None:
        """The angles the capture plan asked for (deg), or None for ingested RAW folders."""
        angles = self._data()["capture"].get("angles_deg")
        return None if angles is None else [float(a) for a in angles]

    def capture_settings(self) -> tuple[float, float]:
        """Mounting offset and read-back tolerance (deg) the capture runs with, for resuming it
        the same way."""
        capture = self._data()["capture"]
        return float(capture.get("offset_deg", 0.0)), float(capture.get("tolerance_deg", 0.5))

    def is_complete(self) -> bool:
        """True when every planned shot was taken (always for ingested RAW folders)."""
        return bool(self._data()["capture"].get("complete", True))

    def raw_paths(self) -> list[Path]:
        """Absolute paths of the RAW shots, in shot order (confined to the scene folder)."""
        return [confined_path(self.path, s.file, str(self.manifest_path)) for s in self.shots()]

    def raw_hashes(self) -> set[str]:
        """Content hashes of the RAW files this scene holds (or was ingested from)."""
        data = self._data()
        return {s["sha256"] for s in data["shots"]} | set(data.get("ingest", {}).get("shot_hashes", []))

    def ingest_outcome(self) -> tuple[bool, str | None] | None:
        """(aligned?, the error when not) of the last ingest, or None before any."""
        ingest = self._data().get("ingest")
        return None if ingest is None else (ingest["ok"], ingest.get("error"))

    def is_ingested(self) -> bool:
        return "ingest" in self._data()

    def ingest_options(self) -> dict:
        """The options of the last ingest (empty before any); a polarization-camera frame's
        record its ``mosaic`` layout, ``demosaic`` and ``transfer``."""
        return copy.deepcopy(self._data().get("ingest", {}).get("options", {}))

    def methods(self) -> list[str]:
        """Methods whose results the scene holds."""
        return sorted(self._data().get("results", {}))

    def result(self, method: str, verify: bool = True) -> Result:
        """A method's results; with ``verify`` its files are checked against their hashes."""
        entry = self._data().get("results", {}).get(method)
        if entry is None:
            raise DatasetError(f"{self.name} has no results of {method!r} (results: {self.methods()})")
        if verify:
            self.check_files(entry["files"])
        files = {Path(f["file"]).name: confined_path(self.path, f["file"], str(self.manifest_path)) for f in entry["files"]}
        known = ("files", "reference_deg", "warnings", "full_scale", "truth_metrics", "stale")
        warnings = list(entry.get("warnings", [])) + ([f"STALE: {entry['stale']}"] if "stale" in entry else [])
        return Result(method, files, entry.get("reference_deg"), warnings,
                      float(entry.get("full_scale", 2.0)), copy.deepcopy(entry.get("truth_metrics")),
                      {k: copy.deepcopy(v) for k, v in entry.items() if k not in known})

    def shot_errors_deg(self) -> list[float] | None:
        """Per-shot angle errors (deg) from `urd calibrate shots`, or None."""
        calibration = self._data().get("calibration")
        return None if calibration is None else [float(e) for e in calibration["errors_deg"]]

    def provenance(self) -> list[dict]:
        return copy.deepcopy(self._data()["provenance"])

    def truth_dir(self) -> Path:
        """Folder of the virtual camera's ground truth (may not exist)."""
        return self.path / "truth"

    def results_dir(self, method: str) -> Path:
        return self.path / "results" / method

    def _dataset_root(self) -> Path | None:
        """The dataset folder holding this scene (its parent, or a calibration sweep's
        grandparent), or None."""
        return next((root for root in (self.path.parent, self.path.parent.parent)
                     if (root / DATASET_MANIFEST).is_file()), None)

    def lock(self) -> contextlib.AbstractContextManager:
        """The write lock of the dataset holding this scene (see `Dataset.lock`)."""
        root = self._dataset_root()
        if root is None:
            raise DatasetError(f"{self.path} is not inside an urd dataset (no {DATASET_MANIFEST} above it)")
        return Dataset(root).lock()

    def refuse_links(self) -> None:
        """DatasetError naming a symbolic link in the scene: its folder, a folder between it and
        its dataset, or any file or folder below it. Checked before urd writes or deletes in a
        scene, so that a dataset from someone else cannot make it write, empty or delete a file
        outside (`urd.core.files.refuse_links`)."""
        refuse_links(self.path, self._dataset_root() or self.path.parent)

    def status(self) -> SceneStatus:
        """Where the scene stands; a scene whose manifest cannot be read is 'broken'."""
        try:
            data = self._data()
        except (ManifestError, OSError) as exc:
            return SceneStatus(self.name, "broken", 0, 0, [], [], problem=str(exc))
        shots = self.shots()
        planned = self.capture_angles_deg()
        expected = len(planned) if planned else len(shots)
        if not self.is_complete():
            state = "incomplete"
        elif "ingest" not in data:
            state = "captured"
        else:
            state = "ingested" if data["ingest"]["ok"] else "alignment failed"
        calibrated = bool(data.get("calibration", {}).get("applied"))
        results = data.get("results", {})
        return SceneStatus(self.name, state, len(shots), expected, [s.angle_commanded_deg for s in shots],
                           sorted(results), calibrated, stale=tuple(sorted(m for m, e in results.items() if "stale" in e)))

    # -- integrity

    def _load_cache(self) -> dict:
        """The hash cache (`_hash`); empty when missing or unreadable."""
        try:
            cache = read_json(self.path / HASH_CACHE)
        except (ManifestError, OSError):
            return {}
        return cache if isinstance(cache, dict) else {}

    def _save_cache(self, cache: dict) -> None:
        with contextlib.suppress(DatasetError, OSError):          # a read-only dataset (or one with links) still verifies
            self.refuse_links()
            write_json_atomic(self.path / HASH_CACHE, cache)

    def _check_intact(self, rec: dict, cache: dict, full: bool, hint: bool = True) -> None:
        """ManifestError unless the file of ``rec`` exists inside the scene with its size and SHA-256
        (``hint``: the message suggests 'urd verify', which `verify` itself does not)."""
        path = confined_path(self.path, rec["file"], str(self.manifest_path))
        if not path.is_file():
            raise ManifestError(f"{path}: listed in the manifest but missing")
        if path.stat().st_size != rec["size"] or _hash(self.path, path, cache, full) != rec["sha256"]:
            raise ManifestError(f"{path}: SHA-256 or size does not match the manifest (corrupted or changed)"
                                + ("; run 'urd verify' to check the whole dataset" if hint else ""))

    def check_files(self, records: list[dict], full: bool = False) -> None:
        """Every listed file exists inside the scene with its recorded size and SHA-256;
        ManifestError otherwise. Unchanged files are recognized by their `_stamp` unless
        ``full``, which hashes every byte."""
        cache = self._load_cache()
        before = copy.deepcopy(cache)
        try:
            for rec in records:
                self._check_intact(rec, cache, full)
        finally:
            if cache != before:
                self._save_cache(cache)

    def _listed_records(self, data: dict) -> list[dict]:
        """The file records of the shots, the aligned stack and the results."""
        records = data["shots"] + data.get("ingest", {}).get("aligned", [])
        return records + [rec for entry in data.get("results", {}).values() for rec in entry["files"]]

    def missing_files(self) -> list[str]:
        """Listed files (shots, aligned stack, results) that are missing or have another size than
        the manifest records: a quick look, no hashing (`verify` hashes)."""
        data = self._data()
        missing = []
        for rec in self._listed_records(data):
            path = self.path / rec["file"]
            if not path.is_file() or path.stat().st_size != rec["size"]:
                missing.append(rec["file"])
        return missing

    def verify(self) -> list[str]:
        """Problems of this scene (empty when every listed file is present and intact), every
        file hashed in full: shots, aligned stack, results and the virtual camera's ground truth.
        Takes no lock: when the manifest changed while it checked (a command swapping in new
        files meanwhile), it checks again against the new one, up to `VERIFY_TRIES` times."""
        for _ in range(VERIFY_TRIES):
            before = self._manifest_bytes()
            problems = self._verify_once()
            if not problems or self._manifest_bytes() == before:
                break
        return problems

    def _manifest_bytes(self) -> bytes | None:
        """The manifest as stored (None when unreadable), to tell whether it changed."""
        try:
            return self.manifest_path.read_bytes()
        except OSError:
            return None

    def _verify_once(self) -> list[str]:
        """`verify` against the manifest as it is now."""
        try:
            data = self.reload()._data()
        except (ManifestError, OSError) as exc:
            return [str(exc)]
        records = self._listed_records(data)
        problems = []
        try:
            self.refuse_links()
        except DatasetError as exc:
            problems.append(str(exc))
        try:
            records += self._truth_records()
        except (ManifestError, DatasetError) as exc:
            problems.append(str(exc))
        cache = {}
        for rec in records:
            try:
                self._check_intact(rec, cache, full=True, hint=False)
            except (ManifestError, OSError) as exc:
                problems.append(str(exc))
        self._save_cache(cache)
        return problems

    def _truth_records(self) -> list[dict]:
        """File records (relative to the scene) of the ground truth that ``truth/truth.json``
        lists; empty without a truth folder or for one of an older urd (no file list).
        DatasetError for a truth folder a stopped capture left incomplete."""
        folder = self.truth_dir()
        if not folder.is_dir():
            return []
        where = folder / TRUTH_FILE
        try:
            record = read_json(where)
        except ManifestError as exc:
            raise DatasetError(f"{folder}: incomplete ground truth ({exc}; a capture was stopped while writing it); "
                               f"move the folder away and resume the capture with 'urd capture --scene {self.name}' "
                               "to write it again") from exc
        validate_truth(record, str(where), folder)
        return [{**rec, "file": f"{folder.name}/{rec['file']}"} for rec in record.get("files", [])]

    def truth_files(self) -> dict[str, Path] | None:
        """The virtual camera's ground truth files by name (``R_obs.tiff`` → path), checked
        against the sizes and SHA-256 in ``truth/truth.json`` (not those of an older urd, which
        wrote none); None when the scene has no ground truth. ManifestError for a damaged file,
        DatasetError for an incomplete truth folder."""
        records = self._truth_records()
        if not self.truth_dir().is_dir():
            return None
        self.check_files(records)
        if records:
            return {Path(rec["file"]).name: self.path / rec["file"] for rec in records}
        return {p.name: p for p in sorted(self.truth_dir().glob("*.tiff"))}

    def load_stack(self, codes: bool = False) -> tuple["Any", list[float]]:
        """The aligned stack (N, H, W, 3) float32 linear, hash-verified, and its best known
        polarizer angles (deg); with ``codes`` the stored uint16 codes (65535 = 1.0; half the
        memory, `separate.optics.code_scale`)."""
        import numpy as np
        import tifffile

        from urd.core.images import u16_to_linear

        ingest = self._data().get("ingest")
        if not self.is_complete():
            raise DatasetError(f"{self.name} is an incomplete capture ({len(self.shots())} of "
                               f"{len(self.capture_angles_deg() or [])} shots); resume it with urd capture --scene {self.name}")
        if not ingest:
            raise DatasetError(f"{self.name} is not ingested yet; run: urd ingest {self.path}")
        if not ingest["ok"]:
            raise DatasetError(f"{self.name}: {ingest['error']}")
        self.check_files(ingest["aligned"])
        paths = [confined_path(self.path, f["file"], str(self.manifest_path)) for f in ingest["aligned"]]
        images = None
        with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:     # the next file decodes meanwhile
            for i, stored in enumerate(pool.map(tifffile.imread, paths)):
                if images is None:
                    dtype = np.uint16 if codes else np.float32
                    images = np.empty((len(paths),) + stored.shape, dtype)    # filled in place: no 2x peak
                if codes:
                    images[i] = stored
                else:
                    u16_to_linear(stored, out=images[i])
                del stored
        return images, self.angles_deg()

    # -- writing

    def _save(self) -> None:
        validate_scene(self._record, str(self.manifest_path), self.path)
        self.refuse_links()
        write_json_atomic(self.manifest_path, self._record)

    def file_record(self, path: Path) -> dict:
        """Size and SHA-256 of a file inside the scene, with its path relative to the scene."""
        path = Path(path)
        return {"file": path.relative_to(self.path).as_posix(), "size": path.stat().st_size, "sha256": sha256_file(path)}

    def add_shot(self, index: int, path: Path, angle_commanded_deg: float, time: str | None = None,
                 angle_measured_deg: float | None = None, stage_position_deg: float | None = None,
                 camera: dict | None = None) -> Shot:
        """Record a shot whose file is already in place inside the scene (hashed here)."""
        data = self._data()
        if any(s["index"] == index for s in data["shots"]):
            raise DatasetError(f"{self.name} already has shot {index}")
        shot = Shot(index=index, angle_commanded_deg=float(angle_commanded_deg), angle_measured_deg=angle_measured_deg,
                    angle_calibrated_deg=None, stage_position_deg=stage_position_deg, time=time or now_iso(),
                    camera=camera, **self.file_record(path))
        data["shots"].append(shot.record())
        data["shots"].sort(key=lambda s: s["index"])
        self._save()
        return shot

    def mark_complete(self, parameters: dict) -> None:
        """The capture has taken every planned shot."""
        data = self._data()
        data["capture"].update(complete=True, finished=now_iso())
        data["provenance"].append(provenance("capture", parameters))
        self._save()

    def note(self, step: str, parameters: dict) -> None:
        """Append a provenance entry and save."""
        self._data()["provenance"].append(provenance(step, parameters))
        self._save()

    def new_staging(self) -> Path:
        """A new hidden folder inside the scene for outputs being computed (the dataset's
        recovery removes it should the process die before they are recorded); DatasetError
        for a scene holding a symbolic link (`refuse_links`)."""
        self.refuse_links()
        return Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=self.path))

    @contextlib.contextmanager
    def staging(self) -> Iterator[Path]:
        """A hidden folder inside the scene for outputs being computed (`new_staging`); removed
        afterwards (files handed to `set_ingest` / `add_result` / ... have been moved out of it)."""
        folder = self.new_staging()
        try:
            yield folder
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def _output_path(self, relative: str) -> Path:
        """The final path of an output named ``relative`` (to the scene); DatasetError, before
        anything changes, when it would leave the scene or a file stands where a folder must be."""
        try:
            path = confined_path(self.path, relative, str(self.manifest_path))
        except ManifestError as exc:
            links = [p for p in _path_chain(self.path, relative) if p.is_symlink()]
            where = f"replace the link {links[0]} by a folder" if links else "fix the output name"
            raise DatasetError(f"{self.name}: cannot store {relative}: {exc}. Nothing was changed (the earlier "
                               f"outputs are kept); {where} and run the command again") from exc
        for parent in _path_chain(self.path, relative)[:-1]:
            if parent.exists() and not parent.is_dir():
                raise DatasetError(f"{self.name}: cannot store {relative}: {parent} is a file, not a folder. Nothing "
                                   "was changed (the earlier outputs are kept); move it away and run the command again")
        return path

    def _commit(self, staged: dict[str, Path], change: Callable[[list[dict]], None]) -> None:
        """Change the manifest and swap in new output files (final name relative to the scene →
        staged path) so that it never names a missing file, with the manifest as the commit point:

        1. the staged files move to ``.staging-XXXX/<final name>`` (the manifest still names the old files);
        2. ``change(records)`` stores their file records, the manifest saved with them and the old
           files no longer named listed in ``swap`` — the commit;
        3. `_finish_swap` links each to its final name, removes the old files and saves the final manifest.

        An error or interrupt before 2 changes nothing; after it, the swap is finished by the next
        `recover` (on taking the dataset's lock) if it was not here.
        """
        for relative in staged:
            self._output_path(relative)
        data = self._data()
        before = {rec["file"] for rec in _file_records(data)}
        folder = self.new_staging()
        try:
            records = []
            for relative, path in staged.items():
                target = folder / relative
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(path, target)
                records.append(self.file_record(target))
            change(records)
            after = {_final_name(rec["file"]) for rec in _file_records(data)}
            data["swap"] = {"remove": sorted(before - after)}
            self._save()
        except BaseException:
            self._record = None
            if not self._on_disk_names(folder.name):
                shutil.rmtree(folder, ignore_errors=True)
            raise
        self._finish_swap()
        shutil.rmtree(folder, ignore_errors=True)

    def _on_disk_names(self, folder: str) -> bool:
        """True when the saved manifest names a file inside the scene's folder ``folder`` (or
        cannot be read: then nothing may be removed)."""
        try:
            return any(rec["file"].startswith(f"{folder}/") for rec in _file_records(read_json(self.manifest_path)))
        except (ManifestError, OSError, TypeError, KeyError, AttributeError):
            return True

    def _finish_swap(self) -> None:
        """Finish a committed swap (see `_commit`): each file the manifest names under a staging
        folder gets its final name (a hard link, else a copy), the old files listed in ``swap``
        are removed, the manifest is saved without ``swap``, and the emptied staging folders go.
        DatasetError (the manifest still consistent) when a file cannot be put in place."""
        data = self._data()
        folders = set()
        try:
            for rec in _file_records(data):
                final = _final_name(rec["file"])
                if final == rec["file"]:
                    continue
                source = self.path / rec["file"]
                try:
                    target = self._output_path(final)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    _place(source, target)
                except OSError as exc:
                    raise DatasetError(f"{self.name}: the new {final} is stored as {source} but cannot be put in "
                                       f"place ({exc.strerror or exc}); fix that and run the command again "
                                       "(it finishes this first)") from exc
                folders.add(PurePosixPath(rec["file"]).parts[0])
                rec["file"] = final
            named = {rec["file"] for rec in _file_records(data)}
            emptied = set()
            for name in data.get("swap", {}).get("remove", []):
                if name not in named:
                    old = confined_path(self.path, name, str(self.manifest_path))
                    old.unlink(missing_ok=True)
                    emptied.add(old.parent)
            for folder in sorted(emptied, key=lambda p: len(p.parts), reverse=True):     # e.g. maps/ of an earlier --maps
                if folder != self.path and folder.is_dir() and not any(folder.iterdir()):
                    with contextlib.suppress(OSError):          # a file appeared meanwhile: the folder stays
                        folder.rmdir()
            data.pop("swap", None)
            self._save()
        except BaseException:
            self._record = None
            raise
        for name in folders:
            shutil.rmtree(self.path / name, ignore_errors=True)

    def set_ingest(self, ok: bool, options: dict, alignment: list | str, staged: dict[str, Path],
                   error: str | None = None, shot_hashes: list[str] | None = None) -> None:
        """Record an ingest: staged aligned files (final name → staged path) are swapped in;
        aligned files of an earlier ingest that are no longer named are removed. What was
        computed from an earlier alignment is superseded: results are marked stale (kept, with
        the command that renews them), a per-shot angle calibration is removed (its record and
        the calibrated angles are kept in the provenance)."""
        record = {"time": now_iso(), "ok": ok, "options": options, "alignment": alignment, "aligned": []}
        if error is not None:
            record["error"] = error
        if shot_hashes:
            record["shot_hashes"] = shot_hashes

        def change(files: list[dict]) -> None:
            data = self._data()
            earlier = self._supersede(data) if "ingest" in data else None
            data["ingest"] = {**record, "angles_deg": self.angles_deg(), "aligned": files}
            if earlier:
                data["provenance"].append(provenance("supersede", earlier))
            data["provenance"].append(provenance("ingest", options))

        self._commit(staged if ok else {}, change)

    def _supersede(self, data: dict) -> dict:
        """Mark results stale and remove the per-shot calibration of ``data`` (before a new
        alignment); returns what was superseded, for the provenance (empty when nothing)."""
        earlier = {}
        for method, entry in data.get("results", {}).items():
            if "stale" not in entry:
                entry["stale"] = (f"computed from an earlier alignment (the scene was ingested again at {now_iso()}); "
                                  f"renew with: urd separate {self.name} --method {method} --force")
                earlier.setdefault("stale_results", []).append(method)
        if "calibration" in data:
            earlier["calibration"] = data.pop("calibration")
            earlier["angles_calibrated_deg"] = [s.get("angle_calibrated_deg") for s in data["shots"]]
            for shot in data["shots"]:
                shot["angle_calibrated_deg"] = None
        if earlier:
            earlier["reason"] = "computed from the earlier alignment"
        return earlier

    def check_no_results(self, method: str) -> None:
        """DatasetError if the manifest already records results of ``method`` (replacing them takes --force)."""
        if method in self.methods():
            raise DatasetError(f"{self.name} already has {method} results ({self.results_dir(method)}); "
                               "pass --force to replace them")

    def add_result(self, method: str, staged: dict[str, Path], entry: dict, replace: bool = False) -> Result:
        """Record a method's results: staged files (final name → staged path) are swapped in
        over the previous results (only with ``replace``); ``entry`` holds the method's
        description (parameters, weights, metrics). Returns the stored entry."""
        if not replace:
            self.check_no_results(method)
        base = {**entry, "time": now_iso(), "method": method}

        def change(files: list[dict]) -> None:
            data = self._data()
            data.setdefault("results", {})[method] = {**base, "files": files}
            data["provenance"].append(provenance(f"separate {method}", entry.get("parameters", {})))

        self._commit(staged, change)
        return self.result(method, verify=False)

    def add_result_files(self, method: str, staged: dict[str, Path], step: str) -> Result:
        """Add staged files (final name → staged path) to a method's stored results, e.g. the
        polarization maps computed afterwards; files of the same name are replaced, the rest of
        the record kept. ``step`` names the work in the provenance. Returns the stored entry."""
        if method not in self.methods():
            raise DatasetError(f"{self.name} has no results of {method!r} to add to (results: {self.methods()})")

        def change(files: list[dict]) -> None:
            entry = self._data()["results"][method]
            added = {_final_name(rec["file"]) for rec in files}
            entry["files"] = [rec for rec in entry["files"] if rec["file"] not in added] + files
            self._data()["provenance"].append(provenance(step, {"method": method}))

        self._commit(staged, change)
        return self.result(method, verify=False)

    def set_shot_calibration(self, record: dict, calibrated_deg: list[float] | None) -> None:
        """Store per-shot angle errors; with ``calibrated_deg`` also each shot's calibrated angle."""
        data = self._data()
        data["calibration"] = {"time": now_iso(), "applied": calibrated_deg is not None, **record}
        if calibrated_deg is not None:
            for shot, angle in zip(sorted(data["shots"], key=lambda s: s["index"]), calibrated_deg):
                shot["angle_calibrated_deg"] = round(float(angle), 4)
        data["provenance"].append(provenance("calibrate shots", {"apply": calibrated_deg is not None}))
        self._save()

    def recover(self) -> list[Path]:
        """Finish what a killed run left (call with the dataset's lock held): a committed swap is
        rolled forward (`_finish_swap`); staging folders and temporary files that the manifest
        does not name are removed; a truth folder left incomplete is moved aside to
        ``truth-incomplete-N`` (so that resuming the capture writes it again). A scene whose
        manifest cannot be read is left as it is. Returns what was removed or moved. DatasetError,
        before anything changes, for a scene holding a symbolic link (`refuse_links`)."""
        self.refuse_links()
        inside = self.path.resolve()
        folders = [self.path, self.path / "raw", self.path / "aligned", self.truth_dir()]
        folders += [p for p in (self.path / "results").glob("*") if p.resolve().is_relative_to(inside)]
        staging = sorted(self.path.glob(f"{STAGING_PREFIX}*"))
        temporary = [p for folder in folders if folder.is_dir() and folder.resolve().is_relative_to(inside)
                     for p in folder.glob(".*") if TEMPORARY.match(p.name) and p.is_file()]
        truth = self.truth_dir()
        torn = truth.is_dir() and not (truth / TRUTH_FILE).is_file()
        if not (staging or temporary or torn) or not self.exists():
            return []
        try:
            data = self.reload()._data()
            if "swap" in data:
                self._finish_swap()
                data = self._data()
        except (ManifestError, DatasetError, OSError):
            return []
        named = {rec["file"] for rec in _file_records(data)}
        used = {PurePosixPath(name).parts[0] for name in named}
        removed = []
        for path in staging:
            if path.name not in used:
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
        for path in temporary:
            if path.exists() and path.relative_to(self.path).as_posix() not in named:
                path.unlink(missing_ok=True)
                removed.append(path)
        if torn:
            n = 1
            while (self.path / f"truth-incomplete-{n}").exists():
                n += 1
            truth.rename(self.path / f"truth-incomplete-{n}")
            removed.append(truth)
        return removed

    def remove_stale(self) -> list[Path]:
        """Remove what killed runs left (`recover`), and unrecorded hidden files in ``raw/`` and
        ``aligned/`` (e.g. a shot downloaded but not stored). Returns what was removed. Call
        with the dataset's lock held."""
        removed = self.recover()
        named = {rec["file"] for rec in _file_records(self._data())} if self.exists() else set()
        for folder in (self.path / "raw", self.path / "aligned"):
            for path in folder.glob(".*") if folder.is_dir() else []:
                if path.is_file() and path.relative_to(self.path).as_posix() not in named:
                    path.unlink()
                    removed.append(path)
        return removed

    def discard_if_empty(self) -> bool:
        """Remove the scene folder if no shot was ever recorded in it (a capture that failed
        before its first shot); True if removed."""
        if self.exists() and self._data()["shots"]:
            return False
        leftovers = [p for p in self.path.rglob("*") if p.is_file() and p.name != SCENE_MANIFEST and not p.name.startswith(".")]
        if leftovers:
            return False
        shutil.rmtree(self.path, ignore_errors=True)
        return True


def new_scene_record(name: str, source: str, capture: dict) -> dict:
    """An empty scene manifest (no shots yet)."""
    return {"schema": "urd.scene", "schema_version": SCHEMA_VERSION, "name": name, "created": now_iso(),
            "source": source, "capture": capture, "shots": [], "provenance": []}


def default_root(cwd: Path = Path(".")) -> Path:
    """The dataset a command uses when none is named: ``cwd`` if it holds a dataset manifest,
    else ``cwd/dataset`` (where ``urd capture`` and ``urd ingest`` put scenes by default)."""
    cwd = Path(cwd)
    return cwd if (cwd / DATASET_MANIFEST).is_file() else cwd / "dataset"


# ---------------------------------------------------------------- dataset

_HELD: dict[Path, int] = {}          # lock depth per dataset held by this process


def _is_dataset(folder: Path) -> bool:
    """Whether ``folder`` holds an urd dataset manifest (another tool's dataset.json is not one)."""
    try:
        return read_json(folder / DATASET_MANIFEST).get("schema") in (DATASET_SCHEMA, *DATASET_SCHEMA_ALIASES)
    except (ManifestError, OSError, AttributeError):
        return False


def enclosing_dataset(path: Path) -> Path | None:
    """The urd dataset folder that ``path`` is or lies in (links resolved), or None."""
    path = Path(path).resolve()
    return next((folder for folder in (path, *path.parents) if _is_dataset(folder)), None)


class Dataset:
    """A dataset root: ``dataset.json``, ``calibration.json`` and scene folders."""

    def __init__(self, root: Path):
        self.root = Path(root)

    @property
    def manifest_path(self) -> Path:
        return self.root / DATASET_MANIFEST

    @classmethod
    def open_or_create(cls, root: Path, description: str = "") -> "Dataset":
        """Open a dataset root, creating the folder and its manifest when new; a new one inside
        another dataset (a scene folder, or any folder below a ``dataset.json``) is refused."""
        root = Path(root)
        if not (root / DATASET_MANIFEST).exists():
            enclosing = next((p for p in root.resolve().parents if _is_dataset(p)), None)
            if enclosing is not None:
                raise DatasetError(f"{root} is inside the dataset {enclosing}; a dataset cannot hold another: "
                                   f"pass {enclosing} itself, or a folder outside it")
        try:
            root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create dataset folder {root}: {exc.strerror or exc}") from exc
        ds = cls(root)
        if ds.manifest_path.exists():
            validate_dataset(read_json(ds.manifest_path), str(ds.manifest_path))
        else:
            write_json_atomic(ds.manifest_path, {"schema": DATASET_SCHEMA, "schema_version": SCHEMA_VERSION,
                                                 "created": now_iso(), "urd_version": __version__,
                                                 "description": description}, overwrite=False)
        return ds

    def remove_if_unused(self, folder_is_new: bool) -> None:
        """Remove a dataset that holds nothing (no scene, none being staged, no calibration): its
        manifest, and its folder when this run made it and it is empty. For workflows that made
        the dataset and then failed on every input, so that a failure leaves nothing behind;
        a dataset another process is using (its lock held) is left alone."""
        try:
            with self.lock():
                if any(p.name != LOCK_FILE for p in self.root.iterdir() if p != self.manifest_path):
                    return                                    # scenes, staged scenes, calibration, anything
                self.manifest_path.unlink(missing_ok=True)
                (self.root / LOCK_FILE).unlink(missing_ok=True)          # still held: no one else has it
                if folder_is_new:
                    with contextlib.suppress(OSError):
                        self.root.rmdir()
        except DatasetBusyError:
            return

    @classmethod
    def open(cls, root: Path) -> "Dataset":
        """Open an existing dataset; DatasetError when there is none."""
        ds = cls(root)
        if not ds.manifest_path.is_file():
            raise DatasetError(f"{root} is not an urd dataset (no {DATASET_MANIFEST})")
        validate_dataset(read_json(ds.manifest_path), str(ds.manifest_path))
        return ds

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the dataset's write lock; DatasetBusyError naming the holder's pid when another
        process has it. Re-entrant within a process."""
        key = self.root.resolve()
        if _HELD.get(key):
            _HELD[key] += 1
            try:
                yield
            finally:
                _HELD[key] -= 1
            return
        with pid_lock(self.root / LOCK_FILE,
                      busy=lambda pid: DatasetBusyError(f"dataset {self.root} busy (held by pid {pid}); "
                                                        "wait for that command to finish"),
                      unopenable=lambda exc: DatasetError(f"cannot lock dataset {self.root}: {exc.strerror or exc}")):
            _HELD[key] = 1
            try:
                self.recover()
                yield
            finally:
                del _HELD[key]

    def recover(self) -> None:
        """Finish or clean up what killed runs left (called on taking the lock): staged scenes
        never adopted are removed; each scene and calibration sweep is recovered (`Scene.recover`)."""
        self.remove_stale()
        for scene in self.scenes() + self.sweeps():
            with contextlib.suppress(UrdError, OSError):
                scene.recover()

    def sweeps(self) -> list[Scene]:
        """The calibration sweeps (``calibration/sweep_NN``), oldest first."""
        return [Scene(path) for path in sorted((self.root / "calibration").glob("sweep_*")) if path.is_dir()]

    def scene_names(self) -> list[str]:
        """Names of the scene folders present (readable or not), sorted by number."""
        names = [p.name for p in self.root.iterdir() if p.is_dir() and SCENE_NAME.match(p.name)]
        return sorted(names, key=lambda n: int(SCENE_NAME.match(n).group(1)))

    def scenes(self) -> list[Scene]:
        """Every scene folder; a broken one reports itself through `Scene.status`."""
        return [Scene(self.root / name) for name in self.scene_names()]

    def scene(self, name: str) -> Scene:
        """The scene called ``name``; DatasetError if there is no such folder or no manifest."""
        path = self.root / name
        if not SCENE_NAME.match(name) or not path.is_dir():
            known = ", ".join(self.scene_names()) or "none"
            raise DatasetError(f"no scene '{name}' in {self.root} (scenes: {known})")
        scene = Scene(path)
        if not scene.exists():
            raise DatasetError(f"scene folder {path} has no {SCENE_MANIFEST} (an empty or broken scene)")
        return scene

    def next_scene_name(self) -> str:
        """The first unused name after the highest existing scene number."""
        numbers = [int(SCENE_NAME.match(n).group(1)) for n in self.scene_names()]
        return f"scene_{(max(numbers, default=0) + 1):02d}"

    def new_scene(self, source: str, capture: dict, name: str | None = None) -> Scene:
        """Create a scene folder with its manifest; never reuses an existing folder."""
        name = name or self.next_scene_name()
        if not SCENE_NAME.match(name):
            raise DatasetError(f"expected a scene name like scene_01, got {name!r}")
        return _create_scene(self.root / name, source, capture)

    def adopt_scene(self, staged: Path) -> Scene:
        """Move a scene assembled in a staging folder (see `staged_scene`) into place under the
        next free name."""
        name = self.next_scene_name()
        scene = Scene(staged)
        scene._data()["name"] = name
        scene._save()
        os.rename(staged, self.root / name)
        return Scene(self.root / name)

    @contextlib.contextmanager
    def staged_scene(self, source: str, capture: dict) -> Iterator[Scene]:
        """A new scene assembled in a hidden folder of the dataset; removed unless adopted."""
        folder = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=self.root))
        umask = os.umask(0)
        os.umask(umask)
        folder.chmod(0o777 & ~umask)                              # mkdtemp's 0700 would stay with the adopted scene
        try:
            yield _create_scene(folder, source, capture, exist_ok=True)
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def remove_stale(self) -> None:
        """Remove staging folders (scenes being assembled) left by killed runs (call with the lock
        held); DatasetError, before anything is removed, when one is a symbolic link."""
        staging = list(self.root.glob(f"{STAGING_PREFIX}*"))
        for path in staging:
            if path.is_symlink():
                raise link_error(path)
        for path in staging:
            shutil.rmtree(path, ignore_errors=True)

    def shot_index(self) -> dict[str, str]:
        """Content hash of every RAW shot already in the dataset → its scene's name."""
        index = {}
        for scene in self.scenes():
            with contextlib.suppress(ManifestError, OSError):
                index.update({digest: scene.name for digest in scene.raw_hashes()})
        return index

    def latest_incomplete(self) -> Scene | None:
        """The newest scene whose capture stopped before its last shot, if any."""
        for scene in reversed(self.scenes()):
            if scene.status().state == "incomplete":
                return scene
        return None

    # -- calibration

    @property
    def calibration_path(self) -> Path:
        return self.root / CALIBRATION_FILE

    def _calibration_record(self) -> dict | None:
        if not self.calibration_path.is_file():
            return None
        return validate_calibration(read_json(self.calibration_path), str(self.calibration_path))

    def calibration(self) -> OffsetCalibration | None:
        """The polarizer's mounting offset calibration, or None when not measured."""
        record = self._calibration_record()
        if record is None:
            return None
        sweep = confined_path(self.root, record["sweep"], str(self.calibration_path)) if "sweep" in record else None
        return OffsetCalibration(float(record["offset_deg"]), float(record["uncertainty_deg"]), record.get("modulation"),
                                 float(record["target_angle_deg"]), record["time"], sweep, len(record["history"]),
                                 record.get("stage"))

    def verify_calibration(self) -> list[str]:
        """Problems of the calibration (an unreadable or invalid ``calibration.json``, missing or
        changed files of its sweeps, each hashed in full); empty when intact or never measured."""
        problems = []
        try:
            self.calibration()
        except (ManifestError, OSError) as exc:
            problems.append(str(exc))
        for sweep in self.sweeps():
            problems += sweep.verify()
        return problems

    def offset_deg(self) -> float:
        """The polarizer's mounting offset (deg), 0 when not calibrated."""
        calibration = self.calibration()
        return calibration.offset_deg if calibration else 0.0

    def save_calibration(self, fit: dict, target_angle_deg: float, sweep: Scene) -> OffsetCalibration:
        """Write ``calibration.json`` from a fit record (offset_deg, uncertainty_deg, modulation,
        residual_rms); an earlier calibration moves into its ``history``."""
        old = self._calibration_record()
        record = {"schema": "urd.calibration", "schema_version": SCHEMA_VERSION, "time": now_iso(), **fit,
                  "target_angle_deg": float(target_angle_deg), "sweep": sweep.path.relative_to(self.root).as_posix(),
                  "history": (old["history"] + [{k: v for k, v in old.items() if k != "history"}]) if old else []}
        validate_calibration(record, str(self.calibration_path))
        refuse_links(self.calibration_path)
        write_json_atomic(self.calibration_path, record)
        return self.calibration()

    def new_sweep(self, capture: dict) -> Scene:
        """A new calibration sweep scene under ``calibration/sweep_NN``."""
        folder = self.root / "calibration"
        if folder.is_symlink():
            raise link_error(folder)
        folder.mkdir(exist_ok=True)
        n = 1
        while (folder / f"sweep_{n:02d}").exists():
            n += 1
        return _create_scene(folder / f"sweep_{n:02d}", "calibration sweep", capture)


def _create_scene(path: Path, source: str, capture: dict, exist_ok: bool = False) -> Scene:
    try:
        path.mkdir(exist_ok=exist_ok)
    except FileExistsError as exc:
        raise DatasetError(f"scene {path} already exists; refusing to overwrite it") from exc
    except OSError as exc:
        raise DatasetError(f"cannot create scene folder {path}: {exc.strerror or exc}") from exc
    scene = Scene(path)
    scene._record = new_scene_record(path.name, source, capture)
    scene._save()
    return scene
