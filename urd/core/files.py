"""Files urd writes and reads: SHA-256 digests, atomic writes, JSON reading and PID locks.

Every write goes to a temporary file beside its target that is renamed into place once
complete (`atomic_path`), so that a reader, or a run killed half-way, never sees a partial file.
Knows nothing of manifests beyond refusing JSON nested deeper than any urd writes.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

from urd.core.errors import DatasetError, DiskFullError, ManifestError

MAX_DEPTH = 32                          # nesting levels a manifest may have (urd writes at most 5)


def sha256_file(path: Path) -> str:
    """SHA-256 hex digest of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# ---------------------------------------------------------------- atomic writes


@contextlib.contextmanager
def atomic_path(path: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    On any exception the temporary file is removed and ``path`` is untouched. Raises
    DatasetError if ``path`` exists and ``overwrite`` is false, and DiskFullError naming
    ``path`` when writing it failed for want of room on its disk (whatever words the writer
    used: numpy's "N requested and M written", libpng's "Write Error").
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
    except BaseException as exc:
        full = isinstance(exc, OSError) and not isinstance(exc, DiskFullError) and _out_of_space(path.parent, exc)
        tmp.unlink(missing_ok=True)
        if full:
            raise DiskFullError(f"disk full: cannot write {path} (no room left on its disk); nothing was replaced. "
                                "Make room there, or write elsewhere, and run the command again") from exc
        raise


#: Free bytes on a disk below which a failed write is put down to a full disk.
LOW_SPACE = 1 << 20


def _out_of_space(folder: Path, exc: OSError) -> bool:
    """Whether a write into ``folder`` that raised ``exc`` failed for want of room (checked
    before the partial file is removed)."""
    if exc.errno == errno.ENOSPC or (exc.__cause__ is not None and getattr(exc.__cause__, "errno", None) == errno.ENOSPC):
        return True
    try:
        return shutil.disk_usage(folder).free < LOW_SPACE
    except OSError:
        return False


def write_bytes_atomic(path: Path, data: bytes, overwrite: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (see `atomic_path`)."""
    with atomic_path(path, overwrite) as tmp:
        try:
            tmp.write_bytes(data)
        except OSError as exc:
            raise DatasetError(f"cannot write {path}: {exc.strerror or exc}") from exc


def write_json_atomic(path: Path, record: dict, overwrite: bool = True) -> None:
    """Write a JSON record atomically, replacing the old version only once complete."""
    write_bytes_atomic(path, (json.dumps(record, indent=2) + "\n").encode(), overwrite)


def read_json(path: Path) -> Any:
    """Read a JSON file; ManifestError when missing, unparsable, or nested deeper than
    `MAX_DEPTH` levels (no urd manifest is; such a file would overflow Python's stack)."""
    try:
        record = json.loads(Path(path).read_text())
    except FileNotFoundError as exc:
        raise ManifestError(f"{path}: manifest not found") from exc
    except RecursionError:
        record = None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from exc
    if record is None or not _nesting_within(record, MAX_DEPTH):
        raise ManifestError(f"{path}: nested more than {MAX_DEPTH} levels deep, which no urd manifest is "
                            "(damaged or not written by urd); restore it from a backup")
    return record


def _nesting_within(value: Any, limit: int) -> bool:
    """True when lists and objects in ``value`` nest at most ``limit`` levels (no recursion)."""
    pending = [(value, 1)]
    while pending:
        item, depth = pending.pop()
        if isinstance(item, (dict, list)):
            if depth > limit:
                return False
            pending.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return True


# ---------------------------------------------------------------- locks


@contextlib.contextmanager
def pid_lock(path: Path, busy: Callable[[str], Exception], unopenable: Callable[[OSError], Exception]) -> Iterator[None]:
    """Hold an exclusive lock on the file ``path`` (created if missing), with this process's
    pid written in it while held. Raises ``busy(holder pid)`` when another open of it holds the
    lock, ``unopenable(error)`` when it cannot be opened."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise unopenable(exc) from exc
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise busy(os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)
