"""Files urd writes and reads: SHA-256 digests, atomic writes, JSON reading and PID locks.

Every write goes to a temporary file beside its target that is renamed into place once
complete (`atomic_path`), so that a reader, or a run killed half-way, never sees a partial file.
A folder someone else gave may hold symbolic links that point anywhere: `refuse_links` is the
one check made before writing or deleting in it, and the lock file is opened without following
a link (`pid_lock`). Knows nothing of manifests beyond refusing JSON nested deeper than any urd
writes.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import stat
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

from urd.core.errors import DatasetError, DiskFullError, ManifestError

MAX_DEPTH = 32                          # nesting levels a manifest may have (urd writes at most 5)
MIN_FREE_BYTES = 1 << 20                # less free space than this after a failed write: the disk was full


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
    used: numpy's "N requested and M written", libpng's "Write Error", torch.save's
    RuntimeError "unexpected pos"). The file and then its folder are synced, so that the
    rename survives a power loss.
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
        full = ((isinstance(exc, OSError) and not isinstance(exc, DatasetError) and disk_full(exc, path.parent))
                or (isinstance(exc, RuntimeError) and disk_full(None, path.parent)))
        tmp.unlink(missing_ok=True)
        if full:
            raise write_error(path, exc if isinstance(exc, OSError) else None, full=True) from exc
        raise
    with contextlib.suppress(OSError):                # the file is in place; some file systems cannot sync a folder
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)
        finally:
            os.close(folder)


def check_writable(folder: Path, then: str) -> None:
    """DatasetError unless a file can be made in ``folder`` (one is made and removed: permissions,
    a read-only mount or an immutable folder all show), saying so before the work ``then``."""
    try:
        fd, name = tempfile.mkstemp(prefix=".urd-probe-", dir=folder)
    except OSError as exc:
        raise DatasetError(f"cannot write in {folder} ({exc.strerror or exc}); {then} would fail at its end: "
                           "nothing was done") from None
    os.close(fd)
    os.unlink(name)


def disk_full(exc: OSError | None, folder: Path) -> bool:
    """Whether a failed write in ``folder`` was a full disk (or quota): ENOSPC or EDQUOT, or a
    failure without an errno (numpy's short write "N requested and M written", an image
    library's "write error") with less than `MIN_FREE_BYTES` left there. Ask before removing
    the partial file."""
    if exc is not None and exc.errno is not None:
        return exc.errno in (errno.ENOSPC, errno.EDQUOT)
    try:
        space = os.statvfs(folder)
    except OSError:
        return False
    return space.f_bavail * space.f_frsize < MIN_FREE_BYTES


def write_error(path: Path, exc: OSError | None, full: bool | None = None) -> DatasetError:
    """The error of a failed write of ``path``: "disk full: PATH" when it was (``full``, else
    `disk_full`), else "cannot write PATH" with the reason."""
    if disk_full(exc, path.parent) if full is None else full:
        return DiskFullError(f"disk full: {path} (nothing was changed; free some space and run the command again)")
    return DatasetError(f"cannot write {path}" + (f": {exc.strerror or exc}" if exc is not None else ""))


def write_bytes_atomic(path: Path, data: bytes, overwrite: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (see `atomic_path`)."""
    with atomic_path(path, overwrite) as tmp:
        try:
            tmp.write_bytes(data)
        except OSError as exc:
            raise write_error(path, exc) from exc


def write_json_atomic(path: Path, record: dict, overwrite: bool = True) -> None:
    """Write a JSON record atomically, replacing the old version only once complete."""
    write_bytes_atomic(path, (json.dumps(record, indent=2) + "\n").encode(), overwrite)


def read_json(path: Path) -> Any:
    """Read a JSON file; ManifestError when missing, a folder, unparsable, or nested deeper than
    `MAX_DEPTH` levels (no urd manifest is; such a file would overflow Python's stack)."""
    try:
        record = json.loads(Path(path).read_text())
    except FileNotFoundError as exc:
        raise ManifestError(f"{path}: manifest not found") from exc
    except IsADirectoryError as exc:
        raise ManifestError(f"{path}: is a folder, not a file (damaged or not written by urd); replace the folder "
                            "by the manifest from a backup") from exc
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


# ---------------------------------------------------------------- links


def link_error(link: Path) -> DatasetError:
    """The refusal of a symbolic link found where urd writes or deletes."""
    return DatasetError(f"{link} is a symbolic link inside the dataset; urd writes and deletes nothing through a "
                        "link in a dataset (one from someone else can point anywhere). Nothing was changed; replace "
                        "it by the file or folder itself, or remove it, and run the command again")


def refuse_links(path: Path, base: Path | None = None) -> None:
    """DatasetError (`link_error`) naming the first symbolic link among ``path``, every file
    and folder below it, and the folders between ``base`` (a trusted folder, not checked) and
    ``path``; no link is followed. A missing ``path`` has nothing below it."""
    path = Path(path)
    above = path.relative_to(base).parts[:-1] if base is not None else ()
    for i in range(len(above)):
        if Path(base, *above[: i + 1]).is_symlink():
            raise link_error(Path(base, *above[: i + 1]))
    if path.is_symlink():
        raise link_error(path)
    pending = [path] if path.is_dir() else []
    while pending:
        with os.scandir(pending.pop()) as entries:          # types from the directory itself: no stat per file
            for entry in entries:
                if entry.is_symlink():
                    raise link_error(Path(entry.path))
                if entry.is_dir(follow_symlinks=False):
                    pending.append(entry.path)


# ---------------------------------------------------------------- locks


def _foreign_lock(path: Path, what: str) -> OSError:
    """Why the lock file ``path`` cannot be used: it ``what`` (e.g. "is a folder, not a regular
    file"), which no lock file urd writes does."""
    return OSError(errno.EINVAL, f"its lock file {path} {what}; urd writes no such file. Remove it and run the "
                                 "command again")


@contextlib.contextmanager
def pid_lock(path: Path, busy: Callable[[str], Exception], unopenable: Callable[[OSError], Exception]) -> Iterator[None]:
    """Hold an exclusive lock on the file ``path`` (created if missing), with this process's
    pid written in it while held. Raises ``busy(holder pid)`` when another open of it holds the
    lock, ``unopenable(error)`` when it cannot be opened or is not a file of its own: a symbolic
    link (never followed, so that no file elsewhere is created, emptied or written), a hard
    link (its content is another name's too), a FIFO, device or folder."""
    flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise unopenable(OSError(exc.errno, f"its lock file {path} is a symbolic link, which urd does not "
                                                "follow (it can point anywhere); remove it and run the command "
                                                "again")) from exc
        if exc.errno == errno.EISDIR:
            raise unopenable(_foreign_lock(path, "is a folder, not a regular file")) from exc
        raise unopenable(exc) from exc
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_nlink > 1:
            raise unopenable(_foreign_lock(path, "has other hard links (its content is another file's too)"
                                           if stat.S_ISREG(info.st_mode) else
                                           "is not a regular file (a FIFO, device or folder)"))
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

