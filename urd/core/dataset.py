"""The urd dataset: `Dataset` and `Scene`, the one place that reads and writes manifests.

`Scene` is assembled from its jobs, each in its own module: shots and the hashes that guard its
files (`urd.core.shots`), the aligned stack and results (`urd.core.results`), ground truth
(`urd.core.truth`), the staged swap of new outputs and the recovery of killed runs
(`urd.core.swap`); here are what ties them together (the manifest, the lock, `refuse_links`,
the scene's status) and `Dataset`.

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

import contextlib
import copy
import dataclasses
import os
import re
import shlex
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from urd.core import __version__
from urd.core.errors import DatasetBusyError, DatasetError, ManifestError, UrdError
from urd.core.files import link_error, pid_lock, read_json, refuse_links, sha256_file, write_json_atomic
from urd.core.manifest import (
    DATASET_SCHEMA,
    DATASET_SCHEMA_ALIASES,
    SCHEMA_VERSION,
    confined_path,
    now_iso,
    printable,
    provenance,
    validate_calibration,
    validate_dataset,
    validate_scene,
)
from urd.core.progress import plural
from urd.core.results import SceneResults
from urd.core.shots import SceneShots
from urd.core.swap import STAGING_PREFIX, SceneSwap
from urd.core.truth import SceneTruth

DATASET_MANIFEST = "dataset.json"
SCENE_MANIFEST = "scene.json"
CALIBRATION_FILE = "calibration.json"
SWEEP_FOLDER = "calibration"       # the calibration sweeps behind calibration.json
LOCK_FILE = ".urd.lock"
SCENE_NAME = re.compile(r"^scene_([0-9]{2,})\Z")        # \Z: "scene_01\n" is no scene


@dataclasses.dataclass(frozen=True)
class SceneStatus:
    """Where a scene stands. ``state``: broken, incomplete, captured, alignment failed, ingested;
    ``angles_deg`` the commanded ones; ``turned_deg`` the largest turn of a shot against the
    reference that its ingest recorded (the polarizer turns with the camera)."""

    name: str
    state: str
    shots: int
    expected: int
    angles_deg: list[float]
    methods: list[str]
    calibrated: bool = False
    problem: str | None = None
    stale: tuple[str, ...] = ()
    turned_deg: float = 0.0

    def describe(self) -> str:
        """One line for a terminal."""
        if self.state == "broken":
            return f"{self.name}: BROKEN ({self.problem})"
        angles = ",".join(f"{a:g}" for a in self.angles_deg)
        parts = [f"{self.name}: {plural(self.shots, 'shot')}" + (f" at {angles} deg" if angles else "")]
        if self.state == "incomplete":
            parts.append(f"INCOMPLETE ({self.shots} of {plural(self.expected, 'shot')}; resume the capture)")
        else:
            parts.append({"captured": "not ingested", "ingested": "aligned",
                          "alignment failed": "ALIGNMENT FAILED"}[self.state])
        if self.calibrated:
            parts.append("angles calibrated")
        elif self.turned_deg >= 0.005:
            parts.append(f"the stage's angles turned with the camera by up to {self.turned_deg:.2f} deg")
        else:
            parts.append("nominal angles")
        methods = [f"{m} (STALE: separate again with --force)" if m in self.stale else m
                   for m in self.methods]
        parts.append(", ".join(methods) if methods else "no results")
        return ", ".join(parts)


@dataclasses.dataclass(frozen=True)
class OffsetCalibration:
    """The polarizer's mounting offset (deg) with its uncertainty, the sweep it was fitted to
    (a scene folder, or None), when, the stage it was measured on (its identity, as
    `acquire.rig.stage_identity` gives it; None where not recorded), and the check of the
    stage's sense of rotation (`calib.polarizer.check_direction`: the second target angle, its
    offset and their difference, deg; None where not checked)."""

    offset_deg: float
    uncertainty_deg: float
    modulation: float | None
    target_angle_deg: float
    time: str
    sweep: Path | None
    earlier: int
    stage: dict | None = None
    direction: dict | None = None


# ---------------------------------------------------------------- scene


class Scene(SceneShots, SceneResults, SceneTruth, SceneSwap):
    """One scene folder and its manifest. Construct through `Dataset` (or ``Scene(path)`` for
    a scene folder given directly); every change is saved atomically at once."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if self.path.name in ("", ".."):                  # "." or "..": the folder's own name, and its parent
            self.path = Path(os.path.abspath(self.path))
        self.name = self.path.name
        self._record: dict | None = None

    def __repr__(self) -> str:
        return f"Scene({str(self.path)!r})"

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

    def provenance(self) -> list[dict]:
        return copy.deepcopy(self._data()["provenance"])

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
                           sorted(results), calibrated, stale=tuple(sorted(m for m, e in results.items() if "stale" in e)),
                           turned_deg=max((abs(t) for t in self.frame_turns_deg()), default=0.0) if state == "ingested" else 0.0)

    def _save(self) -> None:
        validate_scene(self._record, str(self.manifest_path), self.path)
        self.refuse_links()
        write_json_atomic(self.manifest_path, self._record)

    def file_record(self, path: Path) -> dict:
        """Size and SHA-256 of a file inside the scene, with its path relative to the scene."""
        path = Path(path)
        return {"file": path.relative_to(self.path).as_posix(), "size": path.stat().st_size, "sha256": sha256_file(path)}

    def note(self, step: str, parameters: dict) -> None:
        """Append a provenance entry and save."""
        self._data()["provenance"].append(provenance(step, parameters))
        self._save()

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

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r})"

    @property
    def manifest_path(self) -> Path:
        return self.root / DATASET_MANIFEST

    @classmethod
    @contextlib.contextmanager
    def made_for(cls, root: Path) -> Iterator["Dataset"]:
        """`open_or_create` for a workflow that adds scenes: a dataset this call made is removed
        again at the end of the block when it got nothing (`remove_if_unused`), so a workflow that
        failed on every input leaves nothing behind."""
        made, folder_is_new = not (Path(root) / DATASET_MANIFEST).exists(), not Path(root).exists()
        ds = cls.open_or_create(root)
        try:
            yield ds
        finally:
            if made:
                ds.remove_if_unused(folder_is_new)

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
        """Remove a dataset that holds nothing of urd's (no scene, none being staged, no calibration,
        no sweep): its manifest, lock and empty sweep folder, and its folder when this run made it and
        it is empty (other files in it are left). For workflows that made the dataset and then failed
        on every input, so that a failure leaves nothing behind; a dataset another process is using
        (its lock held) is left alone."""
        sweeps = self.root / SWEEP_FOLDER
        try:
            with self.lock():
                if any(SCENE_NAME.match(p.name) or p.name.startswith(STAGING_PREFIX) or p.name == CALIBRATION_FILE
                       for p in self.root.iterdir()) or (sweeps.is_dir() and any(sweeps.iterdir())):
                    return
                self.manifest_path.unlink(missing_ok=True)
                (self.root / LOCK_FILE).unlink(missing_ok=True)          # still held: no one else has it
                with contextlib.suppress(OSError):
                    sweeps.rmdir()
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
        return [Scene(path) for path in sorted((self.root / SWEEP_FOLDER).glob("sweep_*")) if path.is_dir()]

    def scene_names(self) -> list[str]:
        """Names of the scene folders present (readable or not), sorted by number."""
        names = [p.name for p in self.root.iterdir() if p.is_dir() and SCENE_NAME.match(p.name)]
        return sorted(names, key=lambda n: int(SCENE_NAME.match(n).group(1)))

    def misnamed_scenes(self) -> dict[str, str]:
        """Folders holding a scene manifest under a name that is not a scene's (``kitchen``,
        ``scene_1``, ``scene_01.bak``), which no command takes for a scene: folder name → what
        `urd verify` and `urd report` say of it (rename it, with a free name), both `printable`. A
        folder that cannot be read (a root-owned lost+found) is none."""
        folders = sorted(p for p in self.root.iterdir() if p.is_dir() and not SCENE_NAME.match(p.name)
                         and not p.name.startswith(STAGING_PREFIX) and os.path.isfile(p / SCENE_MANIFEST))
        first = int(SCENE_NAME.match(self.next_scene_name()).group(1))
        return {printable(path.name): printable(f"holds a {SCENE_MANIFEST} but is not named scene_NN, so no command sees "
                                                f"it as a scene; rename it: mv {shlex.quote(str(path))} "
                                                f"{shlex.quote(str(self.root / f'scene_{n:02d}'))}")
                for n, path in enumerate(folders, first)}

    def scenes(self) -> list[Scene]:
        """Every scene folder; a broken one reports itself through `Scene.status`."""
        return [Scene(self.root / name) for name in self.scene_names()]

    def scene(self, name: str) -> Scene:
        """The scene called ``name``; TypeError unless it is a string, DatasetError if there is no
        such folder or no manifest."""
        if not isinstance(name, str):
            raise TypeError(f"expected a scene name such as 'scene_01', got {name!r}")
        path = self.root / name
        if not SCENE_NAME.match(name) or not path.is_dir():
            known = ", ".join(self.scene_names()) or "none"
            raise DatasetError(f"no scene '{name}' in {self.root} (scenes: {known})")
        scene = Scene(path)
        if not scene.exists():
            raise DatasetError(f"scene folder {path} has no {SCENE_MANIFEST} (an empty or broken scene)")
        return scene

    def next_scene_name(self) -> str:
        """The first unused name after the highest scene number of any entry of the dataset's
        folder (a stray file named like a scene included: a scene cannot take its name)."""
        numbers = [int(match.group(1)) for path in self.root.iterdir() if (match := SCENE_NAME.match(path.name))]
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
                                 record.get("stage"), record.get("direction"))

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
        folder = self.root / SWEEP_FOLDER
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
    try:
        scene._record = new_scene_record(path.name, source, capture)
        scene._save()
    except BaseException:
        if not exist_ok:                                    # a refused record leaves no scene without a manifest
            shutil.rmtree(path, ignore_errors=True)
        raise
    return scene
