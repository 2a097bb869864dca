"""QA of the rig's command line: options that do not fit the rig are usage errors before any port is
opened, angles that cannot determine S0, S1, S2 are refused up front, a corrupt download or a vanished
stage is reported in words a user can act on, ingest of nothing but incomplete captures fails, and
progress written to a log is plain lines."""

import io
import math
import os
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import serial
from typer.testing import CliRunner

import acquire.plan
import acquire.rig
from conftest import stop_capture_before_shot
from acquire.ell14 import Ell14
from acquire.plan import MAX_TOLERANCE_DEG, capture_scene, shot_name
from acquire.sim_ell14 import SimulatedEll14
from separate.optics import check_angles
from urd.cli import app
from urd.core.dataset import Dataset
from urd.core.errors import DeviceTimeoutError
from urd.core.progress import TerminalProgress

SIM = ("--stage", "sim", "--camera", "virtual", "--sim-size", "96x64")
INFO = b"0IN0E1140051720231701016800023000\r\n"          # ELL14, 360 deg travel, 143360 counts per turn


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def said(out) -> str:
    """The command's output with its line wrapping undone."""
    return " ".join(out.output.split())


@pytest.fixture
def no_capture(monkeypatch):
    """Replace the capture workflow by a stub that records its arguments: what reaches it passed
    every check of the command line."""
    calls = []

    class Done:
        path = Path("scene_01")

    def stub(*args, **kwargs):
        calls.append((args, kwargs))
        return Done()

    monkeypatch.setattr(acquire.plan, "capture_scene", stub)
    return calls


# 1. angles that cannot determine S0, S1, S2 are refused by capture and ingest, with separation's message

@pytest.mark.parametrize("angles", ["0,1,2", "0,0.1,0.2"])
def test_angles_bunched_together_are_refused_up_front_with_separations_message(tmp_path, angles):
    with pytest.raises(ValueError) as separation:
        check_angles([math.radians(float(a)) for a in angles.split(",")])
    for args in (("capture", tmp_path / "ds", *SIM, "--sim-shake", "0", "--angles", angles),
                 ("ingest", tmp_path / "raw", tmp_path / "ds", "--angles", angles)):
        out = invoke(*args)
        assert out.exit_code == 2, out.output
        assert "Invalid value for '--angles'" in said(out) and str(separation.value) in said(out)
        assert "spread over the half turn" in said(out)
    assert not (tmp_path / "ds").exists()


def test_well_spread_angles_still_pass(no_capture, tmp_path):
    out = invoke("capture", tmp_path / "ds", *SIM, "--angles", "0,60,120")
    assert out.exit_code == 0, out.output
    assert no_capture[0][0][3] == [0.0, 60.0, 120.0]


# 2. and 3. simulation options and the virtual camera with a real port: usage errors, the port untouched

@pytest.mark.parametrize("options, named, needs", [
    (("--sim-offset", "3"), "--sim-offset", "needs --stage sim"),
    (("--sim-jitter", "0.2"), "--sim-jitter", "needs --stage sim"),
    (("--sim-faults", "drop=0.1"), "--sim-faults", "needs --stage sim"),
    (("--seed", "4"), "--seed", "needs --stage sim"),
    (("--sim-offset", "3", "--sim-faults", "drop=0.1"), "--sim-offset, --sim-faults", "need --stage sim"),
    (("--sim-size", "64x64"), "--sim-size", "needs --camera virtual"),
    (("--sim-shake", "0"), "--sim-shake", "needs --camera virtual"),
    (("--reflection", "README.md"), "--reflection", "needs --camera virtual"),
    (("--transmission", "README.md"), "--transmission", "needs --camera virtual"),
])
def test_simulation_options_with_a_real_port_are_usage_errors(tmp_path, scripted_peer, monkeypatch, options, named, needs):
    monkeypatch.chdir(os.path.dirname(os.path.dirname(__file__)))          # README.md: an existing image path for the check
    peer = scripted_peer([])                                               # a real serial line that must not be written to
    out = invoke("capture", tmp_path / "ds", "--stage", peer.port_name, "--camera", "gphoto2", *options)
    assert out.exit_code == 2, out.output
    assert f"{named} {needs}" in said(out)
    peer.check()
    assert not (tmp_path / "ds").exists()


def test_virtual_camera_options_with_the_simulated_stage_and_a_real_camera_are_usage_errors(tmp_path):
    out = invoke("capture", tmp_path / "ds", "--stage", "sim", "--camera", "gphoto2", "--sim-size", "64x64")
    assert out.exit_code == 2 and "--sim-size needs --camera virtual: it sets the virtual camera" in said(out)


def test_options_left_at_their_defaults_do_not_count(no_capture, tmp_path, scripted_peer):
    peer = scripted_peer([])
    out = invoke("capture", tmp_path / "ds", "--stage", peer.port_name, "--camera", "gphoto2")
    assert out.exit_code == 0, out.output
    assert len(no_capture) == 1 and no_capture[0][0][1] == peer.port_name
    peer.check()
    out = invoke("capture", tmp_path / "ds", "--stage", "sim", "--camera", "gphoto2", "--sim-offset", "2", "--seed", "1")
    assert out.exit_code == 0, out.output                                  # they set the simulated stage in use


def test_the_virtual_camera_with_a_real_port_is_refused_before_the_port_is_opened(tmp_path, scripted_peer):
    peer = scripted_peer([])
    start = time.monotonic()
    out = invoke("capture", tmp_path / "ds", "--stage", peer.port_name, "--camera", "virtual")
    assert out.exit_code == 2, out.output
    assert "--camera virtual needs --stage sim" in said(out) and "did not answer" not in said(out)
    assert time.monotonic() - start < 1.0                                  # no time-out waited for
    peer.check()
    other = scripted_peer([])
    with pytest.raises(acquire.rig.DeviceError, match="virtual camera needs the simulated stage"):
        with acquire.rig.open_rig(other.port_name, "virtual"):
            pass
    other.check()


def test_calibrate_offset_checks_its_rig_too(tmp_path, scripted_peer):
    peer = scripted_peer([])
    for options, message in ((("--camera", "virtual"), "--camera virtual needs --stage sim"),
                             (("--sim-offset", "2"), "--sim-offset needs --stage sim")):
        out = invoke("calibrate", "offset", tmp_path / "ds", "--stage", peer.port_name, *options)
        assert out.exit_code == 2 and message in said(out), out.output
    peer.check()


# 4. --scene with --new-scene

def test_scene_and_new_scene_together_are_a_usage_error(tmp_path, no_capture):
    out = invoke("capture", tmp_path / "ds", *SIM, "--scene", "scene_02", "--new-scene")
    assert out.exit_code == 2 and "--scene scene_02 and --new-scene do not go together" in said(out)
    assert not no_capture
    with pytest.raises(ValueError, match="not both"):
        capture_scene(tmp_path / "ds", "sim", "virtual", scene_name="scene_02", new=True)
    assert not (tmp_path / "ds").exists()


# 5. the tolerance has an upper bound

@pytest.mark.parametrize("value, message", [("1000", "expected at most 10, got 1000"), ("10.5", "expected at most 10"),
                                            ("0", "expected at least 0.01")])
def test_a_tolerance_outside_its_range_is_refused(tmp_path, no_capture, value, message):
    out = invoke("capture", tmp_path / "ds", *SIM, "--tolerance", value)
    assert out.exit_code == 2 and "Invalid value for '--tolerance'" in said(out) and message in said(out)
    assert not no_capture


def test_the_largest_tolerance_is_accepted_and_the_range_is_in_the_help(tmp_path, no_capture):
    out = invoke("capture", tmp_path / "ds", *SIM, "--tolerance", f"{MAX_TOLERANCE_DEG:g}")
    assert out.exit_code == 0 and no_capture[0][0][6] == MAX_TOLERANCE_DEG
    assert "(deg), 0.01 to 10:" in said(invoke("capture", "--help"))
    with pytest.raises(ValueError, match="tolerance between 0.01 and 10 deg, got 1000"):
        capture_scene(tmp_path / "ds", "sim", "virtual", tolerance_deg=1000.0)


# 6. and 7. what the help says

def test_capture_help_says_what_is_written_and_what_its_values_look_like():
    text = said(invoke("capture", "--help"))
    assert "raw/shot_NN_ANGLEdeg.dng" in text and f"e.g. {shot_name(1, 45.0, '.dng')}" in text
    assert "scene.json" in text and "truth/" in text
    assert "Scene name scene_NN, like scene_01" in text
    assert "each side an even number from 32 to 20000" in text


def test_calibrate_offset_help_states_the_step_range_and_what_is_written():
    text = said(invoke("calibrate", "offset", "--help"))
    assert "Sweep step (deg), 1 to 45" in text
    assert "calibration.json" in text and "calibration/sweep_NN/" in text
    assert "--sim-size" in text and "each side an even number from 32 to 20000" in text


def test_calibrate_offset_checks_sim_size_like_capture(tmp_path):
    for args in (("calibrate", "offset", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "65x49"),
                 ("capture", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "65x49")):
        out = invoke(*args)
        assert out.exit_code == 2 and "Invalid value for '--sim-size'" in said(out)
        assert "even number of px between 32 and 20000, got '65x49'" in said(out)


@pytest.mark.slow
def test_calibrate_offset_sweeps_at_the_given_size(tmp_path):
    out = invoke("calibrate", "offset", tmp_path / "ds", "--stage", "sim", "--camera", "virtual", "--sim-size", "64x48",
                 "--step", "30", "--sim-offset", "4")
    assert out.exit_code == 0, out.output
    sweep = Dataset.open(tmp_path / "ds").sweeps()[-1]
    assert sweep.path.relative_to(tmp_path / "ds").as_posix() == "calibration/sweep_01"
    camera = sweep.load()["capture"]["camera"]
    assert (camera["width"], camera["height"]) == (64, 48) and len(sweep.shots()) == 6
    assert (tmp_path / "ds" / "calibration.json").is_file()


# 8. --demosaic without --mosaic, and an invalid --demosaic

def test_demosaic_without_mosaic_says_it_needs_mosaic_and_a_bad_value_is_invalid(tmp_path):
    (tmp_path / "raw").mkdir()
    out = invoke("ingest", tmp_path / "raw", tmp_path / "ds", "--demosaic", "bilinear")
    assert out.exit_code == 2 and "--demosaic needs --mosaic" in said(out)
    out = invoke("ingest", tmp_path / "raw", tmp_path / "ds", "--demosaic", "magic")
    assert out.exit_code == 2 and "Invalid value for '--demosaic'" in said(out)
    assert "expected one of none, bilinear, newton, got 'magic'" in said(out)
    assert not (tmp_path / "ds").exists()


# 9. a corrupt download is reported by shot and angle, not by the temporary file it was

@pytest.fixture
def corrupt_gphoto2(tmp_path, monkeypatch):
    """A `gphoto2` on PATH whose downloads are truncated DNG files."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    script = bindir / "gphoto2"
    script.write_text(textwrap.dedent(f"""\
        #!{sys.executable}
        import sys
        args = sys.argv[1:]
        if "--summary" in args:
            print("Camera summary:\\nManufacturer: Fake\\nModel: Alpha 6000\\nSerial Number: 1234")
        elif "--capture-image-and-download" in args:
            name = args[args.index("--filename") + 1]
            open(name.replace("%C", "dng"), "wb").write(b"II*\\x00" + b"\\x00" * 64)
        """))
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PATH", f"{bindir}{os.pathsep}{os.environ['PATH']}")


def test_a_corrupt_download_names_the_shot_and_says_it_was_removed(tmp_path, corrupt_gphoto2):
    out = invoke("capture", tmp_path / "ds", "--stage", "sim", "--camera", "gphoto2", "--angles", "30,75,120")
    assert out.exit_code == 1, out.output
    text = said(out)
    assert "shot 0 at 30 deg: the camera's file is not a readable RAW file" in text and "the download was removed" in text
    assert ".shot-" not in text and "Traceback" not in text
    assert not list(tmp_path.rglob(".shot-*"))


# 10. ingest of nothing but an incomplete capture fails

def test_ingest_of_only_an_incomplete_capture_exits_1_and_of_a_complete_one_beside_it_0(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    stop_capture_before_shot(monkeypatch)
    assert invoke("capture", root, *SIM).exit_code == 130
    monkeypatch.undo()
    for source in (root, root / "scene_01"):
        out = invoke("ingest", source)
        assert out.exit_code == 1, out.output
        assert "incomplete capture (1 of 3 shots); resume it with: urd capture" in said(out)
        assert "nothing to ingest: 1 incomplete capture (scene_01)" in said(out)
    assert invoke("capture", root, *SIM, "--new-scene").exit_code == 0
    out = invoke("ingest", root)
    assert out.exit_code == 0 and "ingested scene_02" in said(out) and "incomplete capture" in said(out)


# 11. a stage that is no serial device

def test_a_stage_that_is_a_file_or_dev_null_is_not_a_serial_device(tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("not a port")
    for port in (notes, "/dev/null", tmp_path):
        out = invoke("capture", tmp_path / "ds", "--stage", port, "--camera", "gphoto2")
        assert out.exit_code == 1, out.output
        assert f"{port} is not a serial device" in said(out) and "ioctl" not in said(out)
    assert notes.read_text() == "not a port"
    with pytest.raises(acquire.rig.DeviceError, match="/dev/null is not a serial device"):
        acquire.rig.open_serial("/dev/null")
    assert not (tmp_path / "ds").exists()


# 12. a stage that stops answering is not taken for one that never answered

def test_a_stage_that_answered_and_then_went_silent_is_said_to_have_stopped(scripted_peer):
    peer = scripted_peer([(b"0in", INFO), (b"0gp", b"")])
    with serial.Serial(peer.port_name, 9600, timeout=0.05) as port:
        stage = Ell14(port, timeout_s=0.2, retries=0)
        stage.info()
        with pytest.raises(DeviceTimeoutError, match="stopped answering") as stopped:
            stage.position()
    assert "check its cable or USB adapter and its power" in str(stopped.value) and "--address" not in str(stopped.value)
    peer.check()
    silent = scripted_peer([(b"0in", b"")])
    with serial.Serial(silent.port_name, 9600, timeout=0.05) as port:
        with pytest.raises(DeviceTimeoutError, match=r"did not answer .* at this address \(--address\)"):
            Ell14(port, timeout_s=0.2, retries=0).info()
    silent.check()


def test_a_stage_that_vanishes_mid_capture_says_so_and_how_to_resume(tmp_path, monkeypatch):
    twins = []

    class Watched(SimulatedEll14):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            twins.append(self)

    monkeypatch.setattr(acquire.rig, "SimulatedEll14", Watched)
    monkeypatch.setattr(acquire.rig, "Ell14", lambda port, address: Ell14(port, address, timeout_s=0.2, move_timeout_s=0.4, retries=0))
    show = TerminalProgress.__call__

    def vanishing(self, done, total, label):
        show(self, done, total, label)
        if label.startswith("capture") and done == 6:                        # shot 0 recorded
            twins[0].sim_force("vanish")

    monkeypatch.setattr(TerminalProgress, "__call__", vanishing)
    out = invoke("capture", tmp_path / "ds", *SIM)
    assert out.exit_code == 1, out.output
    text = said(out)
    assert "stopped answering" in text and "check its cable or USB adapter and its power" in text
    assert "(--address)" not in text and "Resume with: urd capture" in text


# 13. progress in a log is plain lines

class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_to_a_log_is_plain_occasional_lines_and_to_a_terminal_one_redrawn_line(monkeypatch):
    now = [0.0]
    monkeypatch.setattr("urd.core.progress.time.monotonic", lambda: now[0])
    log, terminal = io.StringIO(), Terminal()
    bars = TerminalProgress(log), TerminalProgress(terminal)
    for step in range(101):                                                # one step a second
        for bar in bars:
            bar(step, 100, "train")
        now[0] += 1.0
    for bar in bars:
        bar(100, 100, "train")                                             # the last call again: no second last line
        bar.close()
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and log.getvalue().endswith("\n")
    assert [line.split()[3] for line in lines] == [f"{k}/100" for k in range(0, 101, 10)]
    assert lines[-1].rstrip().endswith("done")
    assert terminal.getvalue().count("\r") > 20 and terminal.getvalue().count("\n") == 1


def test_a_capture_logged_to_a_file_has_no_carriage_returns(tmp_path):
    with open(tmp_path / "log", "w") as log:
        done = subprocess.run([sys.executable, "-m", "urd.cli", "capture", str(tmp_path / "ds"), *SIM],
                              stdout=subprocess.DEVNULL, stderr=log, timeout=300)
    text = (tmp_path / "log").read_text()
    assert done.returncode == 0, text
    assert "\r" not in text
    assert [line for line in text.splitlines() if line.startswith("capture scene_01")][-1].rstrip().endswith("done")
