"""Ground truth of scenes from the virtual camera: ``truth/truth.json``, written last with each
file's size and SHA-256 (`write_truth_record`), read back and checked by the `SceneTruth` part
of `urd.core.dataset.Scene`."""

from __future__ import annotations

from pathlib import Path

from urd.core.errors import DatasetError, ManifestError
from urd.core.files import read_json, sha256_file, write_json_atomic
from urd.core.manifest import validate_truth

TRUTH_FILE = "truth.json"


def write_truth_record(folder: Path, info: dict) -> None:
    """Write a ground-truth folder's ``truth.json``: ``info`` (gain, camera, ...) and the size
    and SHA-256 of every other file in ``folder``. Write it last: its presence marks the folder
    complete, and `Scene.verify` checks the files against it."""
    folder = Path(folder)
    files = [{"file": p.name, "size": p.stat().st_size, "sha256": sha256_file(p)}
             for p in sorted(folder.iterdir()) if p.is_file() and p.name != TRUTH_FILE and not p.name.startswith(".")]
    write_json_atomic(folder / TRUTH_FILE, {**info, "files": files})


class SceneTruth:
    """The ground truth of a `urd.core.dataset.Scene` (uses the scene's ``path``, ``name`` and
    ``check_files``)."""

    def truth_dir(self) -> Path:
        """Folder of the virtual camera's ground truth (may not exist)."""
        return self.path / "truth"

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
                               f"move the folder away and resume the capture with 'urd capture {self.path.parent} --scene {self.name}' "
                               "and the options it was started with, to write it again") from exc
        validate_truth(record, str(where), folder)
        return [{**rec, "file": f"{folder.name}/{rec['file']}"} for rec in record.get("files", [])]

    def lost_truth(self) -> str | None:
        """What `urd verify` says of a scene without its ground truth where a stopped capture left
        it incomplete (set aside as ``truth-incomplete-N`` by the dataset's recovery), else None.
        Separation goes on without it; resuming the capture writes it again."""
        aside = sorted(self.path.glob("truth-incomplete-*"))
        if self.truth_dir().is_dir() or not aside:
            return None
        return (f"no ground truth: a capture was stopped while writing it (set aside as {aside[-1]}); write it "
                f"again with 'urd capture {self.path.parent}' and the options the scene was captured with, or "
                "remove that folder to go on without it")

    def truth_files(self) -> dict[str, Path] | None:
        """The virtual camera's ground truth files by name (``R_obs.tiff`` → path), checked
        against the sizes and SHA-256 in ``truth/truth.json`` (not those of an older urd, which
        wrote none); None when the scene has no ground truth. ManifestError for a damaged file,
        DatasetError for an incomplete truth folder."""
        records = self._truth_records()
        if not self.truth_dir().is_dir():
            return None
        try:
            self.check_files(records)
        except ManifestError as exc:
            raise ManifestError(f"{exc}; the ground truth feeds only the figures against it: move {self.truth_dir()} "
                                "away to separate without them") from exc
        if records:
            return {Path(rec["file"]).name: self.path / rec["file"] for rec in records}
        return {p.name: p for p in sorted(self.truth_dir().glob("*.tiff"))}
