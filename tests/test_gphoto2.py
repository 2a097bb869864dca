"""The gphoto2 camera driver against a fake `gphoto2` program on PATH."""

import os
import stat
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import rawpy

from acquire.camera import Gphoto2Camera
from acquire.dng import write_dng
from urd.core.dataset import Dataset
from urd.core.errors import DeviceError


@pytest.fixture
def fake_gphoto2(tmp_path, monkeypatch):
    """A `gphoto2` that answers --summary and writes a DNG for --capture-image-and-download;
    FAKE_GPHOTO2_MODE=fail makes it fail like a camera that is off, =jpeg saves only a JPEG, =hang
    writes its pid into hung.pid and waits a minute (a camera that never answers)."""
    fixture = tmp_path / "fixture.dng"
    cfa = (np.random.default_rng(0).random((32, 48)) * 3000 + 300).astype(np.uint16)
    write_dng(fixture, cfa, 256, 4095, (0.5, 1.0, 0.7), exposure_s=1 / 250, model="fake")
    bindir = tmp_path / "bin"
    bindir.mkdir()
    script = bindir / "gphoto2"
    script.write_text(textwrap.dedent(f"""\
        #!{sys.executable}
        import os, shutil, sys
        args = sys.argv[1:]
        mode = os.environ.get("FAKE_GPHOTO2_MODE", "ok")
        with open({str(tmp_path / 'calls.log')!r}, "a") as log:
            log.write(" ".join(args) + "\\n")
        if mode == "fail":
            sys.stderr.write("*** Error: No camera found. ***\\n")
            sys.exit(1)
        if "--summary" in args:
            print("Camera summary:\\nManufacturer: Fake\\nModel: Alpha 6000\\nSerial Number: 1234")
        elif "--capture-image-and-download" in args:
            if mode == "hang":
                import time
                open({str(tmp_path / 'hung.pid')!r}, "w").write(str(os.getpid()))
                time.sleep(60)
            name = args[args.index("--filename") + 1]
            if mode == "jpeg":
                open(name.replace("%C", "jpg"), "wb").write(b"jpeg")
            else:
                shutil.copyfile({str(fixture)!r}, name.replace("%C", "dng"))
            print("Saving file as " + name)
        """))
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PATH", f"{bindir}{os.pathsep}{os.environ['PATH']}")
    return tmp_path


def test_trigger_download_and_metadata(fake_gphoto2, tmp_path):
    camera = Gphoto2Camera()
    assert camera.describe() == {"kind": "gphoto2", "model": "Alpha 6000", "serial": "1234"}
    path, meta = camera.capture(tmp_path, 0)
    assert path.suffix == ".dng" and path.parent == tmp_path
    with rawpy.imread(str(path)) as raw:
        assert raw.raw_image.shape == (32, 48)
    assert meta["exposure_s"] == pytest.approx(1 / 250, rel=1e-3)
    calls = (fake_gphoto2 / "calls.log").read_text()
    assert "--capture-image-and-download" in calls and "--keep" in calls     # the card keeps every shot too


def test_camera_errors_are_clear(fake_gphoto2, tmp_path, monkeypatch):
    monkeypatch.setenv("FAKE_GPHOTO2_MODE", "fail")
    with pytest.raises(DeviceError, match="No camera found"):
        Gphoto2Camera()
    monkeypatch.setenv("FAKE_GPHOTO2_MODE", "jpeg")
    with pytest.raises(DeviceError, match="no RAW file"):
        Gphoto2Camera().capture(tmp_path, 0)
    with pytest.raises(DeviceError, match="not found on PATH"):
        Gphoto2Camera(executable="no-such-gphoto2")


def test_urd_capture_with_gphoto2_and_the_simulated_stage(fake_gphoto2, tmp_path):
    out = subprocess.run([sys.executable, "-m", "urd.cli", "capture", str(tmp_path / "ds"), "--stage", "sim",
                          "--camera", "gphoto2"], capture_output=True, text=True, timeout=300, env=os.environ)
    assert out.returncode == 0, out.stderr
    record = Dataset.open(tmp_path / "ds").scene("scene_01").load()
    assert record["capture"]["camera"]["model"] == "Alpha 6000" and len(record["shots"]) == 3


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie (a container's init may not reap it)."""
    try:
        with open(f"/proc/{pid}/stat") as stat_file:
            return stat_file.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_gphoto2_dies_with_a_capture_killed_while_it_waits_for_the_camera(fake_gphoto2, tmp_path, monkeypatch):
    """gphoto2 is started so that Linux kills it when urd dies, even by SIGKILL (it would go on
    holding the camera's USB claim)."""
    import signal
    import time

    monkeypatch.setenv("FAKE_GPHOTO2_MODE", "ok")
    capture = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""\
        import os
        from pathlib import Path
        from acquire.camera import Gphoto2Camera
        camera = Gphoto2Camera()
        os.environ["FAKE_GPHOTO2_MODE"] = "hang"
        camera.capture(Path({str(tmp_path)!r}), 0)
        """)], env=os.environ)
    pid_file = tmp_path / "hung.pid"
    deadline = time.monotonic() + 60
    while not (pid_file.exists() and pid_file.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    hung = int(pid_file.read_text())
    assert _alive(hung)
    capture.send_signal(signal.SIGKILL)
    capture.wait()
    deadline = time.monotonic() + 10
    while _alive(hung) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(hung)


def test_a_download_folder_a_killed_capture_left_is_removed_with_the_other_leftovers(tmp_path):
    from rig import capture_virtual
    from urd.core.swap import DOWNLOAD_PREFIX

    ds = Dataset.open_or_create(tmp_path / "ds")
    scene, _ = capture_virtual(ds, size=(96, 64), shake_px=1.0, shake_deg=0.1)
    left = scene.path / "raw" / f"{DOWNLOAD_PREFIX}k2v9"
    left.mkdir()
    (left / "shot.arw").write_bytes(b"a RAW file half downloaded")
    shots = sorted(p.name for p in (scene.path / "raw").iterdir() if not p.name.startswith("."))
    removed = scene.remove_stale()
    assert left in removed and not left.exists()
    assert sorted(p.name for p in (scene.path / "raw").iterdir() if not p.name.startswith(".")) == shots
