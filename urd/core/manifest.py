"""The manifest schema: the version urd writes, and the checks every manifest passes on load.

`validate_scene`, `validate_dataset`, `validate_calibration` and `validate_truth` check each
field by type, angles by range, file records by their SHA-256 form and file paths by
`confined_path` (relative, inside their folder); their ManifestErrors name the file and the
field. A manifest of a newer schema version is refused. `provenance` makes the entries of a
scene's history.
"""

from __future__ import annotations

import datetime as _dt
import math
import re
from pathlib import Path, PurePosixPath
from typing import Any

from urd.core import __version__
from urd.core.errors import ManifestError

SCHEMA_VERSION = 1
MAX_ANGLE_DEG = 720.0                   # largest |angle| a manifest may hold (deg): two turns
SHA256 = re.compile(r"^[0-9a-f]{64}$")


def now_iso() -> str:
    """The current UTC time as ISO 8601 text."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def stale_note(scene: Path, method: str, why: str) -> str:
    """The ``stale`` field of a result of ``method`` in the scene folder ``scene``: ``why`` it no
    longer matches the scene, when, and the command that renews it."""
    return (f"{why} ({now_iso()}); renew with: urd separate {scene.name} --dataset {scene.parent} "
            f"--method {method} --force")


def stale_reason(note: str) -> str:
    """The ``why`` of a `stale_note` (the text itself for a note of another form)."""
    return re.sub(r" \([^()]*\)$", "", note.split("; renew with:")[0])


# ---------------------------------------------------------------- validation

NUMBER = (int, float)
OPTIONAL_NUMBER = (int, float, type(None))


def _check(record: Any, where: str, required: dict[str, Any], optional: dict[str, Any] | None = None) -> dict:
    """Check an object's fields by type; ManifestError naming ``where`` and the field."""
    if not isinstance(record, dict):
        raise ManifestError(f"{where}: expected an object, got {type(record).__name__}")
    for key, kind in {**required, **(optional or {})}.items():
        if key not in record:
            if key in required:
                raise ManifestError(f"{where}: missing field '{key}'")
            continue
        value = record[key]
        if not isinstance(value, kind) or (isinstance(value, bool) and bool not in _as_tuple(kind)):
            raise ManifestError(f"{where}: field '{key}' has type {type(value).__name__}, "
                                f"expected {' or '.join(t.__name__ for t in _as_tuple(kind))}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ManifestError(f"{where}: field '{key}' is {value}, expected a finite number")
    return record


def _as_tuple(kind: Any) -> tuple:
    return kind if isinstance(kind, tuple) else (kind,)


def _check_numbers(values: Any, where: str, limit: float = math.inf) -> None:
    """A list of finite numbers of magnitude at most ``limit``; ManifestError otherwise."""
    if not isinstance(values, list) or not all(isinstance(v, NUMBER) and not isinstance(v, bool) for v in values):
        raise ManifestError(f"{where}: expected a list of numbers, got {values!r:.80}")
    for i, value in enumerate(values):
        if not (math.isfinite(value) and abs(value) <= limit):
            raise ManifestError(f"{where}[{i}]: is {value!r:.40}, expected a finite number"
                                + (f" within ±{limit:g}" if math.isfinite(limit) else ""))


def _check_angles(record: dict, where: str, keys: tuple[str, ...]) -> None:
    """The angle fields ``keys`` of ``record`` (deg; absent or None allowed) lie within ±`MAX_ANGLE_DEG`."""
    for key in keys:
        value = record.get(key)
        if value is not None and not abs(value) <= MAX_ANGLE_DEG:
            raise ManifestError(f"{where}: field '{key}' is {value!r:.40} deg, expected an angle within ±{MAX_ANGLE_DEG:g} deg")


#: The dataset manifest's schema name (like "urd.scene" and "urd.calibration", a format name,
#: not a module path), and the earlier name urd 0.1 wrote for a while, read too.
DATASET_SCHEMA = "urd.dataset"
DATASET_SCHEMA_ALIASES = ("urd.core.dataset",)


def _check_schema(record: dict, where: str, schema: str, aliases: tuple[str, ...] = ()) -> None:
    """The record's schema is ``schema`` (or one of its earlier ``aliases``) at a version this urd reads."""
    if record["schema"] != schema and record["schema"] not in aliases:
        raise ManifestError(f"{where}: field 'schema' is {record['schema']!r}, expected {schema!r}")
    version = record["schema_version"]
    if version < 1:
        raise ManifestError(f"{where}: field 'schema_version' is {version}, expected 1 to {SCHEMA_VERSION}")
    if version > SCHEMA_VERSION:
        raise ManifestError(f"{where}: field 'schema_version' is {version}, written by a newer urd; "
                            f"this urd {__version__} reads up to {SCHEMA_VERSION}: upgrade urd")


def confined_path(base: Path, relative: Any, where: str) -> Path:
    """``base / relative`` for a manifest path that stays inside ``base``; ManifestError for an
    absolute path, a ``..`` component, or a link leading outside."""
    if not isinstance(relative, str) or not relative:
        raise ManifestError(f"{where}: expected a relative file path, got {relative!r}")
    pure = PurePosixPath(relative)
    if pure.is_absolute() or ".." in pure.parts or "\\" in relative or relative.startswith("~"):
        raise ManifestError(f"{where}: file path {relative!r} leaves the scene folder "
                            "(manifest paths must be relative, without '..')")
    path = Path(base) / pure
    if not path.resolve().is_relative_to(Path(base).resolve()):
        chain = [Path(base).joinpath(*pure.parts[: i + 1]) for i in range(len(pure.parts))]
        link = next((p for p in chain if p.is_symlink()), path)
        raise ManifestError(f"{where}: file path {relative!r} leads outside the scene folder: {link} is a symbolic "
                            "link")
    return path


def _check_file(record: Any, where: str, base: Path) -> None:
    _check(record, where, {"file": str, "size": int, "sha256": str})
    confined_path(base, record["file"], f"{where}.file")
    if not SHA256.match(record["sha256"]):
        raise ManifestError(f"{where}: field 'sha256' is not a SHA-256 hex digest")
    if record["size"] < 0:
        raise ManifestError(f"{where}: field 'size' is negative")


#: The files every method's results hold (`urd.separation.write_results`).
RESULT_LAYERS = ("R.tiff", "T.tiff")

SHOT_REQUIRED = {"index": int, "angle_commanded_deg": NUMBER, "angle_measured_deg": OPTIONAL_NUMBER,
                 "angle_calibrated_deg": OPTIONAL_NUMBER, "file": str, "size": int, "sha256": str, "time": str}
SHOT_OPTIONAL = {"stage_position_deg": OPTIONAL_NUMBER, "camera": (dict, type(None))}
SHOT_ANGLES = ("angle_commanded_deg", "angle_measured_deg", "angle_calibrated_deg", "stage_position_deg")


def validate_scene(record: Any, where: str, base: Path) -> dict:
    """Check every field of a scene manifest; ManifestError naming file and field."""
    _check(record, where, {"schema": str, "schema_version": int, "name": str, "created": str, "source": str,
                           "capture": dict, "shots": list, "provenance": list},
           {"ingest": dict, "results": dict, "calibration": dict, "swap": dict})
    _check_schema(record, where, "urd.scene")
    capture = _check(record["capture"], f"{where}: capture", {}, {"angles_deg": list, "complete": bool,
                                                                   "offset_deg": NUMBER, "tolerance_deg": NUMBER})
    if "angles_deg" in capture:
        _check_numbers(capture["angles_deg"], f"{where}: capture.angles_deg", MAX_ANGLE_DEG)
    _check_angles(capture, f"{where}: capture", ("offset_deg",))
    indices = []
    for i, shot in enumerate(record["shots"]):
        _check(shot, f"{where}: shots[{i}]", SHOT_REQUIRED, SHOT_OPTIONAL)
        _check_file(shot, f"{where}: shots[{i}]", base)
        _check_angles(shot, f"{where}: shots[{i}]", SHOT_ANGLES)
        if shot["index"] < 0:
            raise ManifestError(f"{where}: shots[{i}]: field 'index' is {shot['index']}, expected 0 or more")
        indices.append(shot["index"])
    if len(set(indices)) != len(indices):
        raise ManifestError(f"{where}: shots: duplicate shot indices {sorted(indices)}")
    for i, entry in enumerate(record["provenance"]):
        _check(entry, f"{where}: provenance[{i}]", {"step": str, "time": str, "urd_version": str, "parameters": dict})
    if "ingest" in record:
        ingest = _check(record["ingest"], f"{where}: ingest", {"time": str, "ok": bool, "options": dict,
                                                              "angles_deg": list, "aligned": list},
                        {"alignment": (list, str), "error": str, "shot_hashes": list})
        _check_numbers(ingest["angles_deg"], f"{where}: ingest.angles_deg", MAX_ANGLE_DEG)
        for i, entry in enumerate(ingest["aligned"]):
            _check_file(entry, f"{where}: ingest.aligned[{i}]", base)
        if ingest["ok"] and len(ingest["aligned"]) < 3:
            raise ManifestError(f"{where}: ingest.aligned: expected at least 3 aligned shots, got {len(ingest['aligned'])}")
        if not ingest["ok"] and "error" not in ingest:
            raise ManifestError(f"{where}: ingest: missing field 'error' of a failed ingest")
    for method, entry in record.get("results", {}).items():
        _check(entry, f"{where}: results.{method}", {"time": str, "method": str, "files": list},
               {"angles_deg": list, "parameters": dict, "truth_metrics": (dict, type(None)), "stale": str,
                "reference_deg": NUMBER, "full_scale": NUMBER, "warnings": list})
        if "angles_deg" in entry:
            _check_numbers(entry["angles_deg"], f"{where}: results.{method}.angles_deg", MAX_ANGLE_DEG)
        if not all(isinstance(line, str) for line in entry.get("warnings", [])):
            raise ManifestError(f"{where}: results.{method}.warnings: expected a list of texts")
        for i, f in enumerate(entry["files"]):
            _check_file(f, f"{where}: results.{method}.files[{i}]", base)
        missing = [name for name in RESULT_LAYERS if name not in {PurePosixPath(f["file"]).name for f in entry["files"]}]
        if missing:
            raise ManifestError(f"{where}: results.{method}.files: expected the layers {' and '.join(RESULT_LAYERS)}, "
                                f"missing {', '.join(missing)}")
    if "calibration" in record:
        calib = _check(record["calibration"], f"{where}: calibration", {"time": str, "applied": bool, "errors_deg": list,
                                                                        "uncertainty_deg": list})
        _check_numbers(calib["errors_deg"], f"{where}: calibration.errors_deg", MAX_ANGLE_DEG)
        _check_numbers(calib["uncertainty_deg"], f"{where}: calibration.uncertainty_deg")
    if "swap" in record:
        swap = _check(record["swap"], f"{where}: swap", {"remove": list})
        for i, name in enumerate(swap["remove"]):
            confined_path(base, name, f"{where}: swap.remove[{i}]")
    return record


def validate_dataset(record: Any, where: str) -> dict:
    """Check a dataset manifest; ManifestError naming file and field."""
    _check(record, where, {"schema": str, "schema_version": int, "created": str, "urd_version": str},
           {"description": str})
    _check_schema(record, where, DATASET_SCHEMA, DATASET_SCHEMA_ALIASES)
    return record


def validate_calibration(record: Any, where: str) -> dict:
    """Check a calibration record (``calibration.json``); ManifestError naming file and field."""
    fields = {"schema": str, "schema_version": int, "time": str, "offset_deg": NUMBER, "uncertainty_deg": NUMBER,
              "target_angle_deg": NUMBER, "history": list}
    _check(record, where, fields, {"modulation": NUMBER, "sweep": str, "residual_rms": NUMBER})
    _check_schema(record, where, "urd.calibration")
    _check_angles(record, where, ("offset_deg", "target_angle_deg"))
    for i, old in enumerate(record["history"]):
        _check(old, f"{where}: history[{i}]", {"time": str, "offset_deg": NUMBER})
    return record


def validate_truth(record: Any, where: str, folder: Path) -> dict:
    """Check a ground-truth record (``truth.json``): its optional list of files inside
    ``folder``; ManifestError naming file and field."""
    _check(record, where, {}, {"files": list})
    for i, rec in enumerate(record.get("files", [])):
        _check_file(rec, f"{where}: files[{i}]", folder)
    return record


def provenance(step: str, parameters: dict) -> dict:
    """A provenance entry: which step ran, when, with which urd version and parameters."""
    return {"step": step, "time": now_iso(), "urd_version": __version__, "parameters": parameters}
