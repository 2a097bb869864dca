"""The manifest schema: the version urd writes, and the checks every manifest passes on load.

`validate_scene`, `validate_dataset`, `validate_calibration` and `validate_truth` check each
field by type, angles by range, file records by their SHA-256 form and file paths by
`confined_path` (relative, inside their folder); names urd makes (file paths, method names)
hold no `CONTROL` character, which a terminal would act on. Their ManifestErrors name the file
and the field. A manifest of a newer schema version is refused. `provenance` makes the entries
of a scene's history; `printable` escapes text urd did not make (RAW metadata) for a terminal.
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
SHA256 = re.compile(r"^[0-9a-f]{64}\Z")
#: Characters a terminal acts on or that reorder the text it shows: C0 and C1 controls (ESC, BEL,
#: NUL, newline …), DEL, and the bidirectional marks and overrides.
CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def now_iso() -> str:
    """The current UTC time as ISO 8601 text."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def stale_note(scene: Path, method: str, why: str) -> str:
    """The ``stale`` field of a result of ``method`` in the scene folder ``scene``: ``why`` it no
    longer matches the scene, when, and the command that renews it."""
    return f"{why} ({now_iso()}); renew with: {renew_command(scene, method)}"


def renew_command(scene: Path, method: str) -> str:
    """The command that separates ``method`` again in the scene folder ``scene``."""
    return f"urd separate {scene.name} --dataset {scene.parent} --method {method} --force"


def printable(text: str) -> str:
    """``text`` with each `CONTROL` character escaped as Python writes it (ESC as ``\\x1b``), for
    a terminal: text urd did not make, such as a RAW file's camera make and model."""
    return CONTROL.sub(lambda match: repr(match.group())[1:-1], text)


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


def _check_name(value: Any, where: str) -> None:
    """A name urd makes (a method, a file path, a device's port) holds no `CONTROL` character;
    ManifestError naming ``where`` otherwise."""
    if isinstance(value, str) and CONTROL.search(value):
        raise ManifestError(f"{where}: {value!r} holds a control character, which no name urd writes has")


def _check_texts(record: dict, where: str) -> None:
    """The text fields of ``record`` (names, times, a device's description) hold no `CONTROL` character."""
    for key, value in record.items():
        _check_name(value, f"{where}: field '{key}'")


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
    _check_name(relative, where)
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
OPTIONAL_TEXT = (str, type(None))
#: The fields of a shot's RAW metadata (`urd.core.raw.metadata`) that urd reads back: exposure
#: time (s), ISO speed, aperture (f-number), focal length (mm), capture time, camera make and model.
SHOT_CAMERA = {"exposure_s": OPTIONAL_NUMBER, "iso": OPTIONAL_NUMBER, "aperture": OPTIONAL_NUMBER,
               "focal_length_mm": OPTIONAL_NUMBER, "time": OPTIONAL_TEXT, "make": OPTIONAL_TEXT, "model": OPTIONAL_TEXT}
#: A capture's stage (`acquire.rig.open_rig`'s ``info["stage"]``), its simulated twin's settings,
#: and its camera (``info["camera"]``; the virtual camera's settings are required of it).
CAPTURE_STAGE = {"kind": str, "port": str, "address": str, "serial": OPTIONAL_TEXT, "firmware": OPTIONAL_TEXT,
                 "pulses_per_rev": int, "simulated": dict}
SIMULATED_STAGE = ({"offset_deg": NUMBER, "jitter_deg": NUMBER, "faults": dict}, {"seed": int, "reversed": bool})
CAPTURE_CAMERA = {"kind": str, "model": str, "serial": str, "width": int, "height": int, "shake_px": NUMBER,
                  "shake_deg": NUMBER, "seed": int, "reflection": OPTIONAL_TEXT, "transmission": OPTIONAL_TEXT}
VIRTUAL_CAMERA = ("width", "height", "shake_px", "seed")


def validate_scene(record: Any, where: str, base: Path) -> dict:
    """Check every field of a scene manifest; ManifestError naming file and field."""
    _check(record, where, {"schema": str, "schema_version": int, "name": str, "created": str, "source": str,
                           "capture": dict, "shots": list, "provenance": list},
           {"ingest": dict, "results": dict, "calibration": dict, "swap": dict})
    _check_schema(record, where, "urd.scene")
    _check_texts(record, where)
    _check_capture(record["capture"], f"{where}: capture")
    indices = []
    for i, shot in enumerate(record["shots"]):
        _check(shot, f"{where}: shots[{i}]", SHOT_REQUIRED, SHOT_OPTIONAL)
        _check_file(shot, f"{where}: shots[{i}]", base)
        _check_angles(shot, f"{where}: shots[{i}]", SHOT_ANGLES)
        if shot.get("camera") is not None:
            _check(shot["camera"], f"{where}: shots[{i}].camera", {}, SHOT_CAMERA)
        if shot["index"] < 0:
            raise ManifestError(f"{where}: shots[{i}]: field 'index' is {shot['index']}, expected 0 or more")
        indices.append(shot["index"])
    if len(set(indices)) != len(indices):
        raise ManifestError(f"{where}: shots: duplicate shot indices {sorted(indices)}")
    for i, entry in enumerate(record["provenance"]):
        _check(entry, f"{where}: provenance[{i}]", {"step": str, "time": str, "urd_version": str, "parameters": dict})
    if "ingest" in record:
        _check_ingest(record["ingest"], f"{where}: ingest", base, len(indices))
    for method, entry in record.get("results", {}).items():
        _check_result(method, entry, f"{where}: results", base)
    if "calibration" in record:
        calib = _check(record["calibration"], f"{where}: calibration", {"time": str, "applied": bool, "errors_deg": list,
                                                                        "uncertainty_deg": list})
        _check_numbers(calib["errors_deg"], f"{where}: calibration.errors_deg", MAX_ANGLE_DEG)
        _check_numbers(calib["uncertainty_deg"], f"{where}: calibration.uncertainty_deg")
        for key in ("errors_deg", "uncertainty_deg"):
            if len(calib[key]) != len(indices):
                raise ManifestError(f"{where}: calibration.{key}: expected one value per shot ({len(indices)}), "
                                    f"got {len(calib[key])}")
    if "swap" in record:
        swap = _check(record["swap"], f"{where}: swap", {"remove": list})
        for i, name in enumerate(swap["remove"]):
            confined_path(base, name, f"{where}: swap.remove[{i}]")
    return record


def _check_capture(capture: Any, where: str) -> None:
    """A scene's capture record: the plan's angles (required of an unfinished capture, which is
    resumed with them), offset and tolerance (deg), the stage and camera it was taken with."""
    _check(capture, where, {}, {"angles_deg": list, "complete": bool, "offset_deg": NUMBER, "tolerance_deg": NUMBER,
                                "stage": dict, "camera": dict, "finished": str, "source_files": list, "gap_s": NUMBER})
    if "angles_deg" in capture:
        _check_numbers(capture["angles_deg"], f"{where}.angles_deg", MAX_ANGLE_DEG)
    elif capture.get("complete") is False:
        raise ManifestError(f"{where}: missing field 'angles_deg' of an unfinished capture")
    _check_angles(capture, where, ("offset_deg",))
    if "stage" in capture:
        stage = _check(capture["stage"], f"{where}.stage", {}, CAPTURE_STAGE)
        _check_texts(stage, f"{where}.stage")
        if "simulated" in stage:
            simulated = _check(stage["simulated"], f"{where}.stage.simulated", *SIMULATED_STAGE)
            for kind, probability in simulated["faults"].items():
                _check_name(kind, f"{where}.stage.simulated.faults")
                _check({kind: probability}, f"{where}.stage.simulated.faults", {kind: NUMBER})
    if "camera" in capture:
        camera = _check(capture["camera"], f"{where}.camera", {}, CAPTURE_CAMERA)
        _check_texts(camera, f"{where}.camera")
        if camera.get("kind") == "virtual":
            _check(camera, f"{where}.camera", {key: CAPTURE_CAMERA[key] for key in VIRTUAL_CAMERA})


def _check_ingest(ingest: Any, where: str, base: Path, shots: int) -> None:
    """A scene's ingest record: how it was done, the aligned shots (one per shot where it
    aligned) and the content hashes of the RAW files it was made from."""
    _check(ingest, where, {"time": str, "ok": bool, "options": dict, "angles_deg": list, "aligned": list},
           {"alignment": (list, str), "error": str, "shot_hashes": list})
    _check_numbers(ingest["angles_deg"], f"{where}.angles_deg", MAX_ANGLE_DEG)
    for i, entry in enumerate(ingest["aligned"]):
        _check_file(entry, f"{where}.aligned[{i}]", base)
    if ingest["ok"] and len(ingest["aligned"]) < 3:
        raise ManifestError(f"{where}.aligned: expected at least 3 aligned shots, got {len(ingest['aligned'])}")
    if ingest["ok"] and len(ingest["aligned"]) != shots:
        raise ManifestError(f"{where}.aligned: expected one aligned shot per shot ({shots}), got {len(ingest['aligned'])}")
    if not ingest["ok"] and "error" not in ingest:
        raise ManifestError(f"{where}: missing field 'error' of a failed ingest")
    for i, entry in enumerate(ingest["alignment"] if isinstance(ingest.get("alignment"), list) else []):
        _check_alignment(entry, f"{where}.alignment[{i}]")
    for i, digest in enumerate(ingest.get("shot_hashes", [])):
        if not (isinstance(digest, str) and SHA256.match(digest)):
            raise ManifestError(f"{where}.shot_hashes[{i}]: expected a SHA-256 hex digest, got {digest!r:.80}")
    if "mosaic" in ingest["options"]:
        _check(ingest["options"], f"{where}.options", {"mosaic": str, "demosaic": str, "transfer": str})


def _check_alignment(entry: Any, where: str) -> None:
    """One shot's alignment: its index and, where it was aligned, its warp (2×3 or 3×3 finite
    numbers, with W₀₀ and W₁₀ not both 0) and its turn (deg)."""
    _check(entry, where, {"shot": int}, {"warp": list, "reference": bool, "ecc_correlation": NUMBER, "ok": bool,
                                         "reason": str, "turn_deg": NUMBER})
    _check_angles(entry, where, ("turn_deg",))
    warp = entry.get("warp")
    if warp is None:
        return
    if len(warp) not in (2, 3):
        raise ManifestError(f"{where}.warp: expected 2 or 3 rows, got {len(warp)}")
    for k, row in enumerate(warp):
        _check_numbers(row, f"{where}.warp[{k}]")
        if len(row) != 3:
            raise ManifestError(f"{where}.warp[{k}]: expected 3 numbers, got {len(row)}")
    if warp[0][0] == 0 and warp[1][0] == 0:
        raise ManifestError(f"{where}.warp: a warp that flattens the image (W00 = W10 = 0)")


def _check_result(method: Any, entry: Any, where: str, base: Path) -> None:
    """One method's results record: its name, files (the `RESULT_LAYERS` among them), angles,
    warnings and figures against the ground truth (PSNR in dB and SSIM of each layer)."""
    _check_name(method, f"{where}: method name")
    where = f"{where}.{method}"
    _check(entry, where, {"time": str, "method": str, "files": list},
           {"angles_deg": list, "parameters": dict, "truth_metrics": (dict, type(None)), "stale": str,
            "reference_deg": NUMBER, "full_scale": NUMBER, "warnings": list, "weights": dict, "incidence": dict,
            "reference_policy": str, "reference": str, "paper": str})
    _check_name(entry["method"], f"{where}: field 'method'")
    if "angles_deg" in entry:
        _check_numbers(entry["angles_deg"], f"{where}.angles_deg", MAX_ANGLE_DEG)
    if not all(isinstance(line, str) for line in entry.get("warnings", [])):
        raise ManifestError(f"{where}.warnings: expected a list of texts")
    for i, f in enumerate(entry["files"]):
        _check_file(f, f"{where}.files[{i}]", base)
    missing = [name for name in RESULT_LAYERS if name not in {PurePosixPath(f["file"]).name for f in entry["files"]}]
    if missing:
        raise ManifestError(f"{where}.files: expected the layers {' and '.join(RESULT_LAYERS)}, "
                            f"missing {', '.join(missing)}")
    for layer, figures in (entry.get("truth_metrics") or {}).items():
        _check_name(layer, f"{where}.truth_metrics")
        _check(figures, f"{where}.truth_metrics.{layer}", {}, {"psnr_db": NUMBER, "ssim": NUMBER})


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
    _check(record, where, fields, {"modulation": NUMBER, "sweep": str, "residual_rms": NUMBER, "stage": dict,
                                   "direction": dict})
    if "direction" in record:
        _check(record["direction"], f"{where}: direction", {"target_angle_deg": NUMBER, "offset_deg": NUMBER,
                                                             "difference_deg": NUMBER, "sweep": str})
        _check_texts(record["direction"], f"{where}: direction")
        _check_angles(record["direction"], f"{where}: direction", ("target_angle_deg", "offset_deg"))
    _check_schema(record, where, "urd.calibration")
    _check_texts(record, where)
    _check_angles(record, where, ("offset_deg", "target_angle_deg"))
    if "stage" in record:
        _check_stage_identity(record["stage"], f"{where}: stage")
    for i, old in enumerate(record["history"]):
        _check(old, f"{where}: history[{i}]", {"time": str, "offset_deg": NUMBER})
        _check_texts(old, f"{where}: history[{i}]")
    return record


def _check_stage_identity(stage: Any, where: str) -> None:
    """The stage a calibration was measured on (`acquire.rig.stage_identity`): a real ELL14 by
    serial number and address, the simulated one by its mounting offset (deg)."""
    _check(stage, where, {"kind": str}, {"serial": OPTIONAL_TEXT, "address": OPTIONAL_TEXT})
    _check_texts(stage, where)
    if stage["kind"] == "ELL14 simulator":
        _check(stage, where, {"sim_offset_deg": NUMBER}, {"sim_reversed": bool})
        _check_angles(stage, where, ("sim_offset_deg",))


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
