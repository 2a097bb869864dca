"""The urd dataset format: a root folder with a dataset manifest and one folder per scene.

Layout::

    DATASET/
      dataset.json              dataset manifest (schema "urd.dataset")
      calibration.json          polarizer calibration, when measured (schema "urd.calibration")
      scene_01/
        scene.json              scene manifest (schema "urd.scene")
        raw/                    the RAW shots as captured, e.g. shot_00_000deg.dng
        aligned/                linear float32 TIFF per shot, aligned to the first shot
        truth/                  ground truth, for scenes from the virtual camera only
        results/METHOD/         R.tiff, T.tiff (linear 16-bit) and sRGB previews

Manifests are JSON with a schema name and version. Angles in manifests are degrees. Every
file a manifest lists carries its size and SHA-256. All writes are atomic: a temporary file
in the same folder, flushed and renamed over the target, so an interrupted write leaves the
previous version intact. Nothing is overwritten unless the caller asks for it.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Iterator

from urd import __version__
from urd.errors import DatasetError, ManifestError

SCHEMA_VERSION = 1
DATASET_MANIFEST = "dataset.json"
SCENE_MANIFEST = "scene.json"
SCENE_NAME = re.compile(r"^scene_(\d{2,})$")

#: Required fields of a scene manifest: name → type (dict means a nested record).
SCENE_FIELDS: dict[str, Any] = {
    "schema": str,
    "schema_version": int,
    "name": str,
    "created": str,
    "source": str,
    "capture": dict,
    "shots": list,
    "provenance": list,
}
SHOT_FIELDS: dict[str, Any] = {
    "index": int,
    "angle_commanded_deg": (int, float),
    "angle_measured_deg": (int, float, type(None)),
    "angle_calibrated_deg": (int, float, type(None)),
    "file": str,
    "size": int,
    "sha256": str,
    "time": str,
}
DATASET_FIELDS: dict[str, Any] = {
    "schema": str,
    "schema_version": int,
    "created": str,
    "urd_version": str,
}


def now_iso() -> str:
    """The current UTC time as ISO 8601 text."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def sha256_file(path: Path) -> str:
    """SHA-256 hex digest of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@contextlib.contextmanager
def atomic_path(path: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    On any exception the temporary file is removed and ``path`` is untouched. Raises
    DatasetError if ``path`` exists and ``overwrite`` is false.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise DatasetError(f"refusing to overwrite existing file {path}")
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    except OSError as exc:
        raise DatasetError(f"cannot write in {path.parent}: {exc.strerror or exc}") from exc
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        os.chmod(tmp, 0o644)
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: Path, data: bytes, overwrite: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (see `atomic_path`)."""
    with atomic_path(path, overwrite) as tmp:
        try:
            tmp.write_bytes(data)
        except OSError as exc:
            raise DatasetError(f"cannot write {path}: {exc.strerror or exc}") from exc


def write_json_atomic(path: Path, record: dict, overwrite: bool = True) -> None:
    """Write a JSON record atomically, replacing the old version only once complete."""
    write_bytes_atomic(path, (json.dumps(record, indent=2, sort_keys=False) + "\n").encode(), overwrite)


def _check_fields(record: Any, fields: dict[str, Any], where: str) -> None:
    if not isinstance(record, dict):
        raise ManifestError(f"{where}: expected an object, got {type(record).__name__}")
    for key, kind in fields.items():
        if key not in record:
            raise ManifestError(f"{where}: missing field '{key}'")
        if not isinstance(record[key], kind) or isinstance(record[key], bool) and kind is not bool:
            raise ManifestError(f"{where}: field '{key}' has type {type(record[key]).__name__}")


def validate_scene(record: Any, where: str = SCENE_MANIFEST) -> dict:
    """Check a scene manifest's schema; raise ManifestError naming the offending field."""
    _check_fields(record, SCENE_FIELDS, where)
    if record["schema"] != "urd.scene":
        raise ManifestError(f"{where}: field 'schema' is {record['schema']!r}, expected 'urd.scene'")
    if record["schema_version"] > SCHEMA_VERSION:
        raise ManifestError(
            f"{where}: field 'schema_version' is {record['schema_version']}, this urd reads up to {SCHEMA_VERSION}"
        )
    for i, shot in enumerate(record["shots"]):
        _check_fields(shot, SHOT_FIELDS, f"{where}: shots[{i}]")
        if not re.fullmatch(r"[0-9a-f]{64}", shot["sha256"]):
            raise ManifestError(f"{where}: shots[{i}].sha256 is not a SHA-256 hex digest")
    return record


def validate_dataset(record: Any, where: str = DATASET_MANIFEST) -> dict:
    """Check a dataset manifest's schema; raise ManifestError naming the offending field."""
    _check_fields(record, DATASET_FIELDS, where)
    if record["schema"] != "urd.dataset":
        raise ManifestError(f"{where}: field 'schema' is {record['schema']!r}, expected 'urd.dataset'")
    return record


def read_json(path: Path) -> Any:
    """Read a JSON file; ManifestError when missing or unparsable."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError as exc:
        raise ManifestError(f"{path}: manifest not found") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from exc


def file_record(scene_dir: Path, path: Path) -> dict:
    """Size and SHA-256 of a file, with its path relative to the scene folder."""
    path = Path(path)
    return {"file": path.relative_to(scene_dir).as_posix(), "size": path.stat().st_size, "sha256": sha256_file(path)}


def verify_files(scene_dir: Path, records: list[dict]) -> None:
    """Check that every listed file exists with the recorded size and SHA-256."""
    for rec in records:
        path = Path(scene_dir) / rec["file"]
        if not path.is_file():
            raise ManifestError(f"{path}: listed in the manifest but missing")
        if path.stat().st_size != rec["size"] or sha256_file(path) != rec["sha256"]:
            raise ManifestError(f"{path}: SHA-256 or size does not match the manifest (corrupted or changed)")


def provenance(step: str, parameters: dict) -> dict:
    """A provenance entry: which step ran, when, with which urd version and parameters."""
    return {"step": step, "time": now_iso(), "urd_version": __version__, "parameters": parameters}


def new_scene_manifest(name: str, source: str, capture: dict) -> dict:
    """An empty scene manifest (no shots yet)."""
    return {
        "schema": "urd.scene",
        "schema_version": SCHEMA_VERSION,
        "name": name,
        "created": now_iso(),
        "source": source,
        "capture": capture,
        "shots": [],
        "provenance": [],
    }


class Scene:
    """One scene folder of a dataset, addressed by name (``scene_12``)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.name = self.path.name

    @property
    def manifest_path(self) -> Path:
        return self.path / SCENE_MANIFEST

    def exists(self) -> bool:
        return self.manifest_path.is_file()

    def load(self, verify: bool = True) -> dict:
        """Read and validate the scene manifest; with ``verify``, re-hash every listed file."""
        record = validate_scene(read_json(self.manifest_path), str(self.manifest_path))
        if verify:
            verify_files(self.path, record["shots"])
        return record

    def save(self, record: dict) -> None:
        """Validate and atomically write the scene manifest."""
        validate_scene(record, str(self.manifest_path))
        write_json_atomic(self.manifest_path, record)

    def shot_paths(self, record: dict) -> list[Path]:
        """Absolute paths of the RAW shots, in shot order."""
        return [self.path / s["file"] for s in sorted(record["shots"], key=lambda s: s["index"])]


def default_root(cwd: Path = Path(".")) -> Path:
    """The dataset a command uses when none is named: ``cwd`` if it holds a dataset manifest,
    else ``cwd/dataset`` (where ``urd capture`` and ``urd ingest`` put scenes by default)."""
    cwd = Path(cwd)
    return cwd if (cwd / DATASET_MANIFEST).is_file() else cwd / "dataset"


class Dataset:
    """A dataset root: ``dataset.json`` plus scene folders."""

    def __init__(self, root: Path):
        self.root = Path(root)

    @property
    def manifest_path(self) -> Path:
        return self.root / DATASET_MANIFEST

    @classmethod
    def open_or_create(cls, root: Path, description: str = "") -> "Dataset":
        """Open a dataset root, creating the folder and its manifest when new."""
        root = Path(root)
        try:
            root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create dataset folder {root}: {exc.strerror or exc}") from exc
        ds = cls(root)
        if ds.manifest_path.exists():
            validate_dataset(read_json(ds.manifest_path), str(ds.manifest_path))
        else:
            write_json_atomic(
                ds.manifest_path,
                {
                    "schema": "urd.dataset",
                    "schema_version": SCHEMA_VERSION,
                    "created": now_iso(),
                    "urd_version": __version__,
                    "description": description,
                },
                overwrite=False,
            )
        return ds

    @classmethod
    def open(cls, root: Path) -> "Dataset":
        """Open an existing dataset; DatasetError when there is none."""
        ds = cls(root)
        if not ds.manifest_path.is_file():
            raise DatasetError(f"{root} is not an urd dataset (no {DATASET_MANIFEST})")
        validate_dataset(read_json(ds.manifest_path), str(ds.manifest_path))
        return ds

    def scene_names(self) -> list[str]:
        """Names of the scenes present, sorted by number."""
        names = [p.name for p in self.root.iterdir() if p.is_dir() and SCENE_NAME.match(p.name)]
        return sorted(names, key=lambda n: int(SCENE_NAME.match(n).group(1)))

    def scene(self, name: str) -> Scene:
        """The scene called ``name``; DatasetError if it has no manifest."""
        scene = Scene(self.root / name)
        if not scene.exists():
            known = ", ".join(self.scene_names()) or "none"
            raise DatasetError(f"no scene '{name}' in {self.root} (scenes: {known})")
        return scene

    def next_scene_name(self) -> str:
        """The first unused name after the highest existing scene number."""
        numbers = [int(SCENE_NAME.match(n).group(1)) for n in self.scene_names()]
        return f"scene_{(max(numbers, default=0) + 1):02d}"

    def new_scene(self, name: str | None = None) -> Scene:
        """Create an empty scene folder; never reuses an existing folder."""
        name = name or self.next_scene_name()
        if not SCENE_NAME.match(name):
            raise DatasetError(f"expected a scene name like scene_01, got {name!r}")
        path = self.root / name
        try:
            path.mkdir()
        except FileExistsError as exc:
            raise DatasetError(f"scene {path} already exists; refusing to overwrite it") from exc
        except OSError as exc:
            raise DatasetError(f"cannot create scene folder {path}: {exc.strerror or exc}") from exc
        return Scene(path)

    def read_calibration(self) -> dict | None:
        """The dataset's polarizer calibration record, or None when not measured."""
        path = self.root / "calibration.json"
        return read_json(path) if path.is_file() else None
