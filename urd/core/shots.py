"""A scene's shots and the hashes that guard its files: `Shot`, the `SceneShots` part of
`urd.core.dataset.Scene` (reading and recording shots and their per-shot calibration, checking
listed files against their size and SHA-256, `verify`), and the hash cache behind the checks."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
from pathlib import Path

from urd.core.errors import DatasetError, ManifestError
from urd.core.files import read_json, sha256_file, write_json_atomic
from urd.core.manifest import confined_path, now_iso, provenance, stale_note

HASH_CACHE = ".urd-hashes.json"
VERIFY_TRIES = 5                        # checks of a scene whose manifest a concurrent command keeps changing


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


def recorded_turns(alignment: list | str | None) -> dict[int, float]:
    """Shot index → its turn against the reference (deg) as an ingest's alignment record holds
    it (`urd.core.align.Alignment.record`); 0 where none is recorded, none for a mosaic's text."""
    return {entry["shot"]: float(entry.get("turn_deg", 0.0)) for entry in alignment} if isinstance(alignment, list) else {}


class SceneShots:
    """The shots of a `urd.core.dataset.Scene` and the integrity checks of its files (uses the
    scene's ``path``, ``name``, ``manifest_path``, ``_data``, ``reload``, ``_save``,
    ``file_record``, ``refuse_links``, ``_truth_records`` and ``lost_truth``)."""

    def shots(self) -> list[Shot]:
        """The recorded shots, in index order."""
        known = {f.name for f in dataclasses.fields(Shot)}
        return [Shot(**{k: v for k, v in s.items() if k in known}) for s in sorted(self._data()["shots"], key=lambda s: s["index"])]

    def angles_deg(self) -> list[float]:
        """Best known polarizer angle of each shot in the aligned stack (deg): calibrated, else
        `uncalibrated_angles_deg`."""
        return [s.angle_calibrated_deg if s.angle_calibrated_deg is not None else float(angle)
                for s, angle in zip(self.shots(), self.uncalibrated_angles_deg())]

    def stage_angles_deg(self) -> list[float]:
        """Each shot's measured, else commanded, angle (deg): the polarizer's against the camera."""
        return [dataclasses.replace(s, angle_calibrated_deg=None).angle_deg for s in self.shots()]

    def uncalibrated_angles_deg(self) -> list[float]:
        """Each shot's angle in the aligned stack (deg), the base of a calibration: its stage angle
        plus its turn against the reference shot (`frame_turns_deg`)."""
        return [round(angle + turn, 4) if turn else angle for angle, turn in zip(self.stage_angles_deg(), self.frame_turns_deg())]

    def frame_turns_deg(self) -> list[float]:
        """Each shot's turn against the reference shot (deg, counter-clockwise in urd's convention),
        as its ingest recorded it from the accepted alignment warp (`urd.core.align.Alignment.turn_deg`).
        The polarizer sits in front of the lens and turns with the camera, so in the aligned stack
        (the reference's frame) its angle is the stage's plus this. Zero before an ingest, for the
        reference, and for an ingest that recorded no turns (urd before 2026-11-29: its results
        were made at the stage's angles, and stay consistent with them until ``--redo``)."""
        turns = recorded_turns((self._data().get("ingest") or {}).get("alignment"))
        return [turns.get(s.index, 0.0) for s in self.shots()]

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

    def shot_errors_deg(self) -> list[float] | None:
        """Per-shot angle errors (deg) from `urd calibrate shots`, or None."""
        calibration = self._data().get("calibration")
        return None if calibration is None else [float(e) for e in calibration["errors_deg"]]

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

    def set_shot_calibration(self, record: dict, calibrated_deg: list[float] | None) -> None:
        """Store per-shot angle errors; with ``calibrated_deg`` also each shot's calibrated angle,
        and results separated at other angles are marked stale (kept, with the command that renews them)."""
        data = self._data()
        data["calibration"] = {"time": now_iso(), "applied": calibrated_deg is not None, **record}
        if calibrated_deg is not None:
            for shot, angle in zip(sorted(data["shots"], key=lambda s: s["index"]), calibrated_deg):
                shot["angle_calibrated_deg"] = round(float(angle), 4)
            angles = [shot["angle_calibrated_deg"] for shot in sorted(data["shots"], key=lambda s: s["index"])]
            for method, entry in data.get("results", {}).items():
                if "stale" not in entry and entry.get("angles_deg") != angles:
                    entry["stale"] = stale_note(self.path, method, "separated at other angles than the shots' calibrated ones")
        data["provenance"].append(provenance("calibrate shots", {"apply": calibrated_deg is not None}))
        self._save()

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
        lost = self.lost_truth()
        if lost:
            problems.append(lost)
        cache = {}
        for rec in records:
            try:
                self._check_intact(rec, cache, full=True, hint=False)
            except (ManifestError, OSError) as exc:
                problems.append(str(exc))
        self._save_cache(cache)
        return problems
