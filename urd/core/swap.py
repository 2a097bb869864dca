"""The staged swap of a scene's new outputs and the recovery of killed runs: the `SceneSwap` part
of `urd.core.dataset.Scene`. New files are staged beside the old ones and the manifest is the
commit point (`SceneSwap._commit`); a swap that a killed run left committed is finished by
`SceneSwap.recover`."""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
import re
import shutil
import tempfile
from pathlib import Path, PurePosixPath
from typing import Callable, Iterator

from urd.core.errors import DatasetError, ManifestError
from urd.core.files import read_json
from urd.core.manifest import confined_path
from urd.core.truth import TRUTH_FILE

STAGING_PREFIX = ".staging-"
#: Prefix of the folder a camera downloads one shot into, inside ``raw/`` (`acquire.camera`).
DOWNLOAD_PREFIX = ".gphoto2-"
TEMPORARY = re.compile(r"^\..+(\.tmp(\.[^.]+)?|\.\d+\.link)$")   # `urd.core.files.atomic_path` and `_place` leftovers


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
    finally:
        link.unlink(missing_ok=True)        # still there when target was already a hard link of source: rename does nothing


class SceneSwap:
    """Staging, the swap of new outputs and the recovery of a `urd.core.dataset.Scene` (uses the
    scene's ``path``, ``name``, ``manifest_path``, ``_data``, ``_save``, ``reload``, ``exists``,
    ``file_record``, ``refuse_links``, ``truth_dir`` and ``_dataset_root``)."""

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
        anything changes, when it would leave the scene, a file stands where a folder must be or a
        folder where the file must be."""
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
        if path.is_dir():
            raise DatasetError(f"{self.name}: cannot store {relative}: {path} is a folder, not a file. Nothing was "
                               "changed (the earlier outputs are kept); remove it and run the command again")
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
            targets = [folder / relative for relative in staged]
            for path, target in zip(staged.values(), targets):
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(path, target)
            with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:    # hashing releases the GIL
                records = list(pool.map(self.file_record, targets))
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

    def unfinished_swap(self) -> str | None:
        """What `urd report` says of a scene whose manifest records a swap of new outputs that was
        committed but not finished (a killed run, see `_commit`; its files are whole, so `urd verify`
        finds nothing wrong), else None (also for a manifest that cannot be read: that is reported
        on its own)."""
        try:
            data = self._data()
        except (ManifestError, OSError):
            return None
        staged = sorted(rec["file"] for rec in _file_records(data) if _final_name(rec["file"]) != rec["file"])
        if "swap" not in data and not staged:
            return None
        names = ", ".join(_final_name(name) for name in staged[:3]) + (", …" if len(staged) > 3 else "")
        return (f"new outputs{f' ({names})' if staged else ''} were recorded but not put in place (a command was stopped or "
                f"failed); any command that writes to the dataset finishes it, e.g. "
                f"'urd ingest {self._dataset_root() or self.path.parent}'")

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
        """Remove what killed runs left (`recover`), unrecorded hidden files in ``raw/`` and
        ``aligned/`` (e.g. a shot downloaded but not stored) and a camera's download folders
        (`DOWNLOAD_PREFIX`). Returns what was removed. Call with the dataset's lock held."""
        removed = self.recover()
        named = {rec["file"] for rec in _file_records(self._data())} if self.exists() else set()
        for folder in (self.path / "raw", self.path / "aligned"):
            for path in folder.glob(".*") if folder.is_dir() else []:
                if path.is_file() and path.relative_to(self.path).as_posix() not in named:
                    path.unlink()
                    removed.append(path)
                elif path.name.startswith(DOWNLOAD_PREFIX) and path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                    removed.append(path)
        return removed
