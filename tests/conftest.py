"""Shared fixtures: the shared data folder, a scripted serial peer on a real pty, a wide terminal
for the CLI's messages, a small ingested dataset and a tmpfs mounted for a test; and, where
pytest-xdist runs the suite in several processes (``-n auto``, the default: one per core and one
more), the CPU's cores shared out among them rather than each process's torch taking every core."""

import contextlib
import os
import select
import subprocess
import threading
import tty
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"

#: What ../shared/data is, for the reasons of the tests that skip without it.
SHARED_DATA_NOTE = ("../shared/data is the developers' folder of third-party research data beside the checkout "
                    "(BSDS500 photos, real polarization-camera captures; licences in its README.md): urd does not "
                    "ship it, so a user's checkout lacks it and these tests skip; the rest of the suite needs none of it")


@pytest.hookimpl(optionalhook=True)                  # pytest-xdist's hook: no error where it is not loaded
def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (the default, pyproject's addopts): one worker per core and one more. Many tests
    wait (on a subprocess, a serial time-out, a killed batch's delay) and the extra worker fills
    that time: the suite on 2 cores 201-218 s with 2 workers, 173-195 s with 3, 200 s with 4. Sending
    the slow-marked tests first (longest first) made it slower: 211 s against 173 s."""
    return len(os.sched_getaffinity(0)) + 1


def pytest_configure(config):
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        import torch                      # only here: a serial run does not pay for it at start-up

        torch.set_num_threads(max(1, len(os.sched_getaffinity(0)) // workers))


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data; skips the test when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is not present. {SHARED_DATA_NOTE}")
    return path


class ScriptedPeer:
    """A serial peer behind a pseudo-terminal that expects an exact byte conversation.

    ``script`` is a list of (bytes the driver must send, bytes to answer). Any unexpected
    write is recorded as a mismatch; `check` fails on mismatches and unused pairs.
    """

    def __init__(self, script):
        self.script = list(script)
        self.mismatch = None
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port_name = os.ttyname(self.slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self):
        buffer = b""
        while not self._stop.is_set() and self.mismatch is None:
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            buffer += os.read(self.master, 256)
            while buffer and self.mismatch is None:
                if not self.script:
                    self.mismatch = f"unexpected write {buffer!r} after the script ended"
                    break
                expected, reply = self.script[0]
                if len(buffer) < len(expected):
                    if not expected.startswith(buffer):
                        self.mismatch = f"expected {expected!r}, got {buffer!r}"
                    break
                if buffer[: len(expected)] != expected:
                    self.mismatch = f"expected {expected!r}, got {buffer[:len(expected)]!r}"
                    break
                buffer = buffer[len(expected):]
                self.script.pop(0)
                if reply:
                    os.write(self.master, reply)

    def check(self):
        self._stop.set()
        self._thread.join(timeout=1)
        assert self.mismatch is None, self.mismatch
        assert not self.script, f"unused conversation pairs: {self.script}"

    def close(self):
        self._stop.set()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


@pytest.fixture
def scripted_peer():
    peers = []

    def make(script):
        peer = ScriptedPeer(script)
        peers.append(peer)
        return peer

    yield make
    for peer in peers:
        peer.close()


@pytest.fixture
def wide_terminal(monkeypatch):
    """COLUMNS=200, so that the CLI's messages are not wrapped (use with ``pytest.mark.usefixtures``)."""
    monkeypatch.setenv("COLUMNS", "200")


def ingested_dataset(tmp_path_factory, name: str) -> Path:
    """A dataset (``ds`` in a new temporary folder named after ``name``) with one scene, scene_01:
    256×192, captured on the simulated rig and ingested through the CLI."""
    from typer.testing import CliRunner

    from urd.cli import app

    root = tmp_path_factory.mktemp(name) / "ds"
    for args in (["capture", str(root), "--stage", "sim", "--camera", "virtual", "--sim-size", "256x192"], ["ingest", str(root)]):
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
    return root


@contextlib.contextmanager
def mounted_tmpfs(folder: Path, options: str, what: str):
    """A tmpfs mounted on ``folder`` (created here) with mount ``options`` (e.g. ``ro,size=1m``)
    for the block, unmounted after it; skips the test where it cannot be mounted (needs root),
    saying it cannot mount ``what``."""
    folder.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True).returncode:
        pytest.skip(f"cannot mount {what} here (needs root)")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)])


def stop_capture_before_shot(monkeypatch, index: int = 1) -> None:
    """Make the virtual camera raise KeyboardInterrupt (a Ctrl-C) when shot ``index`` is triggered:
    the capture stops there, incomplete (`monkeypatch.undo()` lets the next capture go on)."""
    from acquire.virtual_camera import VirtualCamera

    capture = VirtualCamera.capture

    def stopping(self, folder, shot):
        if shot == index:
            raise KeyboardInterrupt
        return capture(self, folder, shot)

    monkeypatch.setattr(VirtualCamera, "capture", stopping)
