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
    FAKE_GPHOTO2_MODE=fail makes it fail like a camera that is off, =jpeg saves only a JPEG."""
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
