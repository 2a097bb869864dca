"""Cameras: one interface, a gphoto2 driver for real cameras, and (in `virtual_camera`) a
simulated twin that renders a glass scene.

A camera's `capture` triggers one exposure and downloads its RAW file into a folder, under a
temporary name; the capture plan hashes it and renames it into place.
"""

from __future__ import annotations

import enum
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Protocol

from urd.core import raw as rawio
from urd.core.errors import DeviceError, DeviceTimeoutError, RawFormatError
from urd.core.processes import killed_with_this_process
from urd.core.swap import DOWNLOAD_PREFIX


class CameraKind(enum.Enum):
    """Camera drivers selectable with ``urd capture --camera``."""

    GPHOTO2 = "gphoto2"
    VIRTUAL = "virtual"


class Camera(Protocol):
    """What the capture plan needs from a camera."""

    def describe(self) -> dict:
        """Identity and settings for the manifest."""

    def capture(self, folder: Path, index: int) -> tuple[Path, dict]:
        """Trigger shot ``index`` of the scene and download its RAW into ``folder`` under a
        temporary name; return (file path, metadata)."""

    def write_truth(self, folder: Path) -> None:
        """Write the scene's ground truth into ``folder`` where the camera knows it (the
        virtual camera); a real camera writes nothing."""


class Gphoto2Camera:
    """A DSLR or mirrorless camera driven by the ``gphoto2`` command-line tool.

    Args:
        executable: the gphoto2 program (looked up on PATH).
        timeout_s: deadline for one trigger-and-download (s).
        port: gphoto2 ``--port`` (e.g. 'usb:001,004'), default: the first camera found.
    """

    def __init__(self, executable: str = "gphoto2", timeout_s: float = 60.0, port: str | None = None):
        found = shutil.which(executable)
        if found is None:
            raise DeviceError(f"camera driver gphoto2: program {executable!r} not found on PATH (install gphoto2)")
        self.executable = found
        self.timeout_s = timeout_s
        self.port = port
        self._summary = self._run(["--summary"], "read the camera summary")

    def _run(self, args: list[str], what: str, cwd: Path | None = None) -> str:
        cmd = [self.executable] + (["--port", self.port] if self.port else []) + args
        try:
            done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=self.timeout_s,
                                  preexec_fn=killed_with_this_process())
        except subprocess.TimeoutExpired as exc:
            raise DeviceTimeoutError(f"gphoto2 did not {what} within {self.timeout_s:.0f} s") from exc
        if done.returncode != 0:
            detail = (done.stderr or done.stdout).strip().splitlines()
            raise DeviceError(f"gphoto2 could not {what}: {detail[-1] if detail else f'exit status {done.returncode}'}")
        return done.stdout

    def describe(self) -> dict:
        lines = [line.strip() for line in self._summary.splitlines() if ":" in line]
        fields = dict(line.split(":", 1) for line in lines)
        return {"kind": CameraKind.GPHOTO2.value, "model": fields.get("Model", "").strip(),
                "serial": fields.get("Serial Number", "").strip()}

    def write_truth(self, folder: Path) -> None:
        """A real scene has no ground truth: nothing is written."""

    def capture(self, folder: Path, index: int) -> tuple[Path, dict]:
        with tempfile.TemporaryDirectory(dir=folder, prefix=DOWNLOAD_PREFIX) as tmp:     # a kill's leftover: `remove_stale`
            self._run(["--capture-image-and-download", "--keep", "--filename", "shot.%C", "--force-overwrite"],
                      "trigger and download", cwd=Path(tmp))           # --keep: the card keeps every shot too
            files = sorted(Path(tmp).iterdir())
            raws = [f for f in files if f.suffix.lower() in rawio.RAW_SUFFIXES]
            if not raws:
                names = [f.name for f in files] or "nothing"
                raise DeviceError(f"gphoto2 downloaded no RAW file (got {names}); set the camera to RAW or RAW+JPEG")
            fd, name = tempfile.mkstemp(dir=folder, prefix=".shot-", suffix=raws[0].suffix.lower())
            os.close(fd)
            shutil.move(raws[0], name)
        return Path(name), downloaded_metadata(Path(name))


def downloaded_metadata(path: Path) -> dict:
    """`urd.core.raw.metadata` of a RAW file just downloaded under a temporary name; when it is
    unreadable the download is removed (the camera's card keeps the shot: `GPhoto2Camera.capture`
    downloads with --keep) and the RawFormatError says why without naming it (the capture plan names the shot)."""
    try:
        return rawio.metadata(path)
    except RawFormatError as exc:
        path.unlink(missing_ok=True)
        reason = str(exc).removeprefix(f"{path}: ")
        raise RawFormatError(f"the camera's file is not a readable RAW file ({reason}); the download was removed, "
                             "the camera's card keeps the shot") from exc
