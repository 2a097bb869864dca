"""The simulated ELL14 as a separate process (``python -m acquire.sim_ell14``): byte-exact
conversations for every supported command, exactly one reply to unknown or unsupported ones,
the urd driver against it, clean stops, and the reusable parts (parse_faults, main)."""

import re
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from acquire.ell14 import Ell14
from acquire.sim_ell14 import FAULTS, main, parse_faults

ROOT = Path(__file__).resolve().parent.parent
ANNOUNCE = re.compile(r"^simulated ELL14 on (\S+) \(address ([0-9A-F])\); Ctrl-C to stop$")
REPLY_S = 2.5          # deadline for one reply (moves take at most 2 s)
QUIET_S = 0.05         # a read this long must find nothing left over
TURN = 143360          # counts per revolution


class SimProcess:
    """``python -m acquire.sim_ell14 ARGS`` with its announced pty path and address."""

    def __init__(self, *args: str, sigint_ignored: bool = False):
        ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if sigint_ignored else None   # a shell's background job
        self.proc = subprocess.Popen([sys.executable, "-m", "acquire.sim_ell14", *args], cwd=ROOT, preexec_fn=ignore,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self._first_line(timeout_s=20)
        match = ANNOUNCE.match(line)
        if not match:
            self.proc.kill()
            raise AssertionError(f"unexpected announcement {line!r}; stderr: {self.proc.stderr.read()}")
        self.path, self.address = match.groups()

    def _first_line(self, timeout_s: float) -> str:
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            if not sel.select(timeout_s):
                self.proc.kill()
                raise AssertionError(f"no announcement within {timeout_s} s")
        return self.proc.stdout.readline().rstrip("\n")

    def stop(self, signum: int = signal.SIGINT, timeout_s: float = 10) -> tuple[int, str, str]:
        """Send ``signum``; return (exit status, rest of stdout, stderr)."""
        self.proc.send_signal(signum)
        try:
            out, err = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise
        return self.proc.returncode, out, err


def read_reply(port: serial.Serial, timeout_s: float = REPLY_S) -> bytes:
    """One CR LF-terminated reply, or what arrived before the deadline."""
    line, deadline = b"", time.monotonic() + timeout_s
    while not line.endswith(b"\r\n") and time.monotonic() < deadline:
        port.timeout = max(0.0, min(0.1, deadline - time.monotonic()))
        line += port.read_until(b"\r\n")
    return line


def quiet(port: serial.Serial) -> bytes:
    """What arrives within QUIET_S (must be b'' after a complete conversation)."""
    port.timeout = QUIET_S
    return port.read(256)


def converse(port: serial.Serial, script: list[tuple[bytes, bytes]], then_silence: bool = True) -> None:
    """Send each command and expect exactly its reply bytes (b'': no reply); then (by default)
    nothing more."""
    for command, expected in script:
        port.write(command)
        got = read_reply(port) if expected else quiet(port)
        assert got == expected, f"{command!r}: expected {expected!r}, got {got!r}"
    if then_silence:
        assert quiet(port) == b"", "bytes left over after the conversation"


@pytest.fixture(scope="module")
def stage():
    sim = SimProcess("--seed", "1")
    yield sim
    if sim.proc.poll() is None:
        sim.stop()


@pytest.fixture
def port(stage):
    with serial.Serial(stage.path, baudrate=9600, timeout=QUIET_S) as port:
        port.write(b"0st")                  # whatever a failed test left moving
        read_reply(port)
        port.reset_input_buffer()
        converse(port, [(b"0ho0", b"0PO00000000\r\n"), (b"0sv64", b"0GS00\r\n"), (b"0sj000007C7", b"0GS00\r\n")],
                 then_silence=False)
        yield port                          # every test ends with a silence check of its own


def test_information_status_and_position(port):
    converse(port, [
        (b"0in", b"0IN0E1234567820261701016800023000\r\n"),   # ELL14, 360°, 143360 counts/turn
        (b"0gs", b"0GS00\r\n"),
        (b"0gp", b"0PO00000000\r\n"),
    ])


def test_home_absolute_and_relative_moves(port):
    converse(port, [
        (b"0ma00008C00", b"0PO00008C00\r\n"),           # 90°
        (b"0gp", b"0PO00008C00\r\n"),
        (b"0mr00001000", b"0PO00009C00\r\n"),
        (b"0mrFFFFF000", b"0PO00008C00\r\n"),           # -4096: two's complement
        (b"0mrFFFF7000", b"0PO00022C00\r\n"),           # -0x9000 wraps below zero
        (b"0mr00000400", b"0PO00000000\r\n"),           # and back through zero
        (b"0ho1", b"0PO00000000\r\n"),
    ])


def test_jog_step_and_jogs(port):
    converse(port, [
        (b"0gj", b"0GJ000007C7\r\n"),
        (b"0sj00002000", b"0GS00\r\n"),
        (b"0gj", b"0GJ00002000\r\n"),
        (b"0fw", b"0PO00002000\r\n"),
        (b"0bw", b"0PO00000000\r\n"),
        (b"0bw", b"0PO00021000\r\n"),
        (b"0sj00023000", b"0GS04\r\n"),                 # a full turn is out of range
        (b"0gj", b"0GJ00002000\r\n"),
    ])


def test_velocity_scales_move_time(port):
    converse(port, [(b"0gv", b"0GV64\r\n"), (b"0sv19", b"0GS00\r\n"), (b"0gv", b"0GV19\r\n"),
                    (b"0sv65", b"0GS04\r\n"), (b"0sv00", b"0GS04\r\n"), (b"0gv", b"0GV19\r\n")])
    start = time.monotonic()
    converse(port, [(b"0ma00008C00", b"0PO00008C00\r\n")])       # 90° at 25 % of 2000 °/s: 0.18 s
    assert time.monotonic() - start >= 0.17


def test_continuous_jog_stops_where_it_is_and_busy_refuses_moves(port):
    converse(port, [(b"0sj00000000", b"0GS00\r\n"), (b"0fw", b"")])      # step 0: no reply until st
    converse(port, [(b"0gs", b"0GS09\r\n"), (b"0ma00000000", b"0GS09\r\n")])
    port.write(b"0gp")
    moving = read_reply(port)
    port.write(b"0st")
    stopped = read_reply(port)
    assert re.fullmatch(rb"0PO[0-9A-F]{8}\r\n", moving) and re.fullmatch(rb"0PO[0-9A-F]{8}\r\n", stopped)
    assert int(stopped[3:11], 16) > 0
    converse(port, [(b"0gp", stopped), (b"0gs", b"0GS00\r\n"), (b"0st", b"0GS00\r\n")])


def test_home_offset_save_and_address_change(port):
    converse(port, [
        (b"0go", b"0HO00000000\r\n"),
        (b"0so00001000", b"0GS00\r\n"),
        (b"0go", b"0HO00001000\r\n"),
        (b"0ho0", b"0PO00000000\r\n"),                  # the new zero reads 0
        (b"0so00000000", b"0GS00\r\n"),
        (b"0ho0", b"0PO00000000\r\n"),
        (b"0us", b"0GS00\r\n"),
        (b"0ca3", b"3GS00\r\n"),                        # answered from the new address
        (b"0gs", b""),
        (b"3gs", b"3GS00\r\n"),
        (b"3ca0", b"0GS00\r\n"),
        (b"0gs", b"0GS00\r\n"),
    ])


def test_motor_information_periods_search_and_maintenance(port):
    converse(port, [
        (b"0i1", b"0I1100000FFFFFFFF00B7008D\r\n"),
        (b"0i2", b"0I2100000FFFFFFFF00B3008B\r\n"),
        (b"0f18100", b"0GS00\r\n"),
        (b"0b28090", b"0GS00\r\n"),
        (b"0i1", b"0I1100000FFFFFFFF0100008D\r\n"),
        (b"0i2", b"0I2100000FFFFFFFF00B30090\r\n"),
        (b"0f18FFF", b"0GS00\r\n"),                     # factory period back
        (b"0b28FFF", b"0GS00\r\n"),
        (b"0i1", b"0I1100000FFFFFFFF00B7008D\r\n"),
        (b"0f18000", b"0GS04\r\n"),
        (b"0s1", b"0GS00\r\n"),                         # frequency search, answered when done
        (b"0s2", b"0GS00\r\n"),
        (b"0om", b""),                                  # optimize: busy until done or st
        (b"0gs", b"0GS09\r\n"),
        (b"0st", b"0GS00\r\n"),
        (b"0cm", b""),
        (b"0st", b"0GS00\r\n"),
        (b"0gs", b"0GS00\r\n"),
    ])


@pytest.mark.parametrize("command,reply", [
    (b"0xx", b"0GS03\r\n"),                            # unknown code
    (b"0xx12345678", b"0GS03\r\n"),                    # unknown code with data: all dropped
    (b"0zz\r\n", b"0GS03\r\n"),
    (b"0zz12\r\n0gs", b"0GS03\r\n0GS00\r\n"),          # resynchronized after CR LF
    (b"0ma12\r\n", b"0GS03\r\n"),                      # data cut short by a terminator
    (b"0maZZZZZZZZ", b"0GS03\r\n"),                    # data not upper-case hex
    (b"0ma0000a000", b"0GS03\r\n"),
    (b"0ma00023000", b"0GS04\r\n"),                    # a full turn is out of range
    (b"0hoX", b"0GS04\r\n"),
    (b"0caZ", b"0GS04\r\n"),
    (b"0is05", b"0GS03\r\n"),                          # accepted by the ELL14, not modelled
    (b"0ga3", b"0GS03\r\n"),
    (b"5gs", b""),                                     # other addresses: no reply
    (b"5xx1234\r\n", b""),
    (b"\xff\x00\r\n", b""),                            # line noise
])
def test_unknown_or_unsupported_gets_exactly_one_reply(port, command, reply):
    port.write(command)
    got = b""
    while len(got) < len(reply):
        part = read_reply(port)
        assert part, f"{command!r}: expected {reply!r}, got {got!r}"
        got += part
    assert got == reply
    assert quiet(port) == b"", f"{command!r}: more than one reply or stale bytes"
    converse(port, [(b"0gs", b"0GS00\r\n"), (b"0gp", b"0PO00000000\r\n")])


def test_incomplete_command_times_out_with_one_reply(port):
    port.write(b"0ma0000")
    assert read_reply(port) == b"0GS01\r\n"
    converse(port, [(b"0gs", b"0GS00\r\n")])


def test_old_parser_bug_relative_move_gets_one_reply(port):
    """Issue 15: '0mr00001000' used to get four GS03 replies and leave bytes behind."""
    converse(port, [(b"0mr00001000", b"0PO00001000\r\n")])


def test_urd_driver_against_the_separate_process(port):
    with Ell14(port, timeout_s=1.0, move_timeout_s=3.0) as driver:
        info = driver.info()
        assert (info.device_type, info.pulses_per_rev, info.travel) == (0x0E, TURN, 360)
        assert driver.home() == 0.0
        assert driver.move_to(90.0) == pytest.approx(90.0, abs=360 / TURN)
        assert driver.position() == pytest.approx(90.0, abs=360 / TURN)
        assert driver.move_to(359.9) == pytest.approx(359.9, abs=360 / TURN)
        assert driver.status() == 0
        assert driver.home() == 0.0


def test_options_and_sigint_stop_cleanly():
    sim = SimProcess("--address", "3", "--offset-deg", "2.5", "--jitter-deg", "0.1", "--seed", "7")
    assert sim.address == "3" and sim.path.startswith("/dev/")
    with serial.Serial(sim.path, baudrate=9600, timeout=QUIET_S) as port:
        converse(port, [(b"0gs", b""), (b"3gs", b"3GS00\r\n"), (b"3ma00004600", b"3PO00004600\r\n")])
    status, out, err = sim.stop(signal.SIGINT)
    assert status == 0 and "Traceback" not in err, err


def test_sigint_stops_a_simulator_started_as_a_background_job():
    # a non-interactive shell starts background jobs (`urd sim-stage &`) with SIGINT ignored and
    # Python keeps it so; the simulator must still stop on Ctrl-C / kill -INT
    sim = SimProcess("--seed", "3", sigint_ignored=True)
    status, out, err = sim.stop(signal.SIGINT)
    assert status == 0 and "Traceback" not in err, err


def test_sigterm_stops_cleanly_and_faults_are_injected():
    sim = SimProcess("--faults", "drop=1.0")
    with serial.Serial(sim.path, baudrate=9600, timeout=QUIET_S) as port:
        port.write(b"0gs")
        port.timeout = 0.15
        assert port.read(64) == b""                   # every reply dropped
    status, out, err = sim.stop(signal.SIGTERM)
    assert status == 0 and "Traceback" not in err, err


def test_parse_faults():
    assert parse_faults("") == {} and parse_faults(" ") == {}
    assert parse_faults("drop=0.05, garble=0.01") == {"drop": 0.05, "garble": 0.01}
    assert parse_faults(",".join(f"{k}=1" for k in FAULTS)) == dict.fromkeys(FAULTS, 1.0)
    for bad, message in [("bogus=0.1", "KIND among drop"), ("drop", "KIND=PROBABILITY"),
                         ("drop=x", "probability in \\[0, 1\\] for drop, got 'x'"),
                         ("drop=1.5", "got '1.5'"), ("drop=nan", "got 'nan'"),
                         ("drop=0.1,drop=0.2", "once")]:
        with pytest.raises(ValueError, match=message):
            parse_faults(bad)


@pytest.mark.parametrize("argv,message", [
    (["--faults", "bogus=1"], "KIND among"),
    (["--address", "G"], "address"),
    (["--jitter-deg", "-1"], "sim_jitter_deg"),
])
def test_main_rejects_bad_arguments(capsys, argv, message):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err
