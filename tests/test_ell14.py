"""ELL14 driver: byte-exact conversations over a real pty, and the simulated twin."""

import pytest
import serial

from acquire.ell14 import Ell14, DeviceStatusError, decode_counts, encode_counts, parse_info
from acquire.sim_ell14 import SimulatedEll14
from urd.core.errors import DeviceTimeoutError, ProtocolError

INFO = b"0IN0E1140051720231701016800023000\r\n"  # ELL14, 360° travel, 143360 counts per turn


def open_port(name):
    return serial.Serial(name, 9600, timeout=0.1)


def test_counts_codec():
    assert encode_counts(0x8C00) == "00008C00"
    assert encode_counts(-1) == "FFFFFFFF"
    assert decode_counts("FFFFFFFF") == -1
    assert decode_counts("00023000") == 143360


def test_parse_info():
    info = parse_info(INFO[3:-2].decode())
    assert (info.device_type, info.serial_number, info.year, info.travel, info.pulses_per_rev) == (
        0x0E, "11400517", "2023", 360, 143360)


def test_info_home_move_position_conversation(scripted_peer):
    peer = scripted_peer([
        (b"0in", INFO),
        (b"0ho0", b"0GS09\r\n0PO00000000\r\n"),          # busy, then done
        (b"0ma00008C00", b"0PO00008C00\r\n"),             # 90° = 143360/4 = 0x8C00
        (b"0gp", b"0PO00008C00\r\n"),
        (b"0gs", b"0GS00\r\n"),
    ])
    with open_port(peer.port_name) as port, Ell14(port) as stage:
        assert stage.info().pulses_per_rev == 143360
        assert stage.home() == 0.0
        assert stage.move_to(90.0) == pytest.approx(90.0)
        assert stage.position() == pytest.approx(90.0)
        assert stage.status() == 0
    peer.check()


def test_status_fault_maps_to_a_clear_error(scripted_peer):
    peer = scripted_peer([(b"0in", INFO), (b"0ma00004600", b"0GS02\r\n")])
    with open_port(peer.port_name) as port, Ell14(port) as stage:
        stage.info()
        with pytest.raises(DeviceStatusError, match="status 2: mechanical time-out") as err:
            stage.move_to(45.0)
        assert err.value.code == 2
    peer.check()


def test_garbled_reply_is_retried(scripted_peer):
    peer = scripted_peer([(b"0gp", b"0P#\x00garbage\r\n"), (b"0gp", b"0PO00004600\r\n"), (b"0in", INFO)])
    with open_port(peer.port_name) as port:
        stage = Ell14(port, retries=1)
        assert stage.position() == pytest.approx(45.0)
    peer.check()


@pytest.mark.parametrize("reply", [b"0PO0000AKCD\r\n", b"0PO\r\n", b"0PO000046\r\n", b"0GSZZ\r\n"])
def test_a_reply_whose_data_is_garbled_is_asked_for_again(scripted_peer, reply):
    """Line noise inside the data (the frame still parses) is a garbled reply, retried like one
    that does not parse; without retries it is a ProtocolError saying what was expected."""
    retried = []
    peer = scripted_peer([(b"0in", INFO), (b"0ma00004600", reply), (b"0ma00004600", b"0PO00004600\r\n")])
    with open_port(peer.port_name) as port:
        stage = Ell14(port, retries=1)
        stage.info()
        stage.on_retry = retried.append
        assert stage.move_to(45.0) == pytest.approx(45.0)
    peer.check()
    assert len(retried) == 1 and "a garbled reply to 'ma00004600'" in retried[0]
    peer = scripted_peer([(b"0gp", reply)])
    with open_port(peer.port_name) as port:
        with pytest.raises(ProtocolError, match=r"garbled reply .* to command 'gp': expected (PO with 8 hex digits|GS with 2)"):
            Ell14(port, retries=0).position()
    peer.check()


def test_lost_reply_times_out_after_bounded_retries(scripted_peer):
    peer = scripted_peer([(b"0gs", b""), (b"0gs", b""), (b"0gs", b"")])
    with open_port(peer.port_name) as port:
        with pytest.raises(DeviceTimeoutError, match="did not answer"):
            Ell14(port, timeout_s=0.2, retries=2).status()
    peer.check()


def test_not_an_ell14(scripted_peer):
    peer = scripted_peer([(b"0in", b"0IN061140051720231701001F00000200\r\n")])
    with open_port(peer.port_name) as port:
        with pytest.raises(ProtocolError, match="not an ELL14"):
            Ell14(port, retries=0).info()
    peer.check()


def test_reply_from_wrong_address_is_a_protocol_error(scripted_peer):
    peer = scripted_peer([(b"0gs", b"3GS00\r\n")])
    with open_port(peer.port_name) as port:
        with pytest.raises(ProtocolError, match="address 3"):
            Ell14(port, retries=0).status()
    peer.check()


def test_bad_address_argument():
    with pytest.raises(ValueError, match="address"):
        Ell14(None, address="G")


def test_simulator_quantizes_offsets_and_moves():
    with SimulatedEll14(sim_offset_deg=3.0, pulses_per_rev=143360) as sim, open_port(sim.port_name) as port:
        stage = Ell14(port)
        stage.info()
        stage.home()
        measured = stage.move_to(45.001)
        assert measured == pytest.approx(45.0, abs=360 / 143360)
        assert sim.true_angle_deg() == pytest.approx(measured + 3.0)
        assert [e["command"] for e in sim.log] == ["0in", "0ho0", f"0ma{encode_counts(round(45.001 / 360 * 143360))}"]


@pytest.mark.parametrize("fault", ["drop", "garble"])
def test_simulator_transient_faults_are_absorbed_by_retries(fault):
    with SimulatedEll14() as sim, open_port(sim.port_name) as port:
        stage = Ell14(port, timeout_s=0.3, move_timeout_s=1.0)
        stage.info()
        sim.sim_force(fault)
        assert stage.move_to(90.0) == pytest.approx(90.0)
        assert [e["fault"] for e in sim.log].count(fault) == 1


def test_simulator_vanishing_device_times_out():
    with SimulatedEll14() as sim, open_port(sim.port_name) as port:
        stage = Ell14(port, timeout_s=0.2, move_timeout_s=0.5, retries=1)
        stage.info()
        sim.sim_force("vanish")
        with pytest.raises(DeviceTimeoutError):
            stage.move_to(45.0)
        sim.sim_revive()
        assert stage.move_to(45.0) == pytest.approx(45.0)


def test_a_stage_port_is_opened_by_one_capture_at_a_time(tmp_path):
    from acquire.rig import open_serial
    from urd.core.errors import DeviceError

    with SimulatedEll14() as sim, open_serial(sim.port_name) as first:
        with pytest.raises(DeviceError, match="another program .* is using it"):
            open_serial(sim.port_name)
        assert first.is_open
    with pytest.raises(DeviceError, match="is the stage connected and powered"):
        open_serial(str(tmp_path / "ttyUSB9"))


def test_a_port_that_takes_no_more_bytes_is_a_lost_connection_not_a_hang():
    import os
    from acquire.rig import WRITE_TIMEOUT_S, open_serial
    from urd.core.errors import DeviceError

    controller, line = os.openpty()                 # nothing reads the far end: a hung adapter
    try:
        with open_serial(os.ttyname(line)) as port:
            assert port.write_timeout == WRITE_TIMEOUT_S
            port.write_timeout = 0.05
            for chunk in (b"x" * 1024, b"x"):            # fill the line's buffer to its last byte
                with pytest.raises(serial.SerialTimeoutException):
                    while True:
                        port.write(chunk)
            with pytest.raises(DeviceError, match="lost the connection to the ELL14 .*Write timeout"):
                Ell14(port, timeout_s=0.2).move_to(45.0)
    finally:
        os.close(controller)
        os.close(line)


def test_a_stage_that_goes_away_mid_capture_is_a_device_error():
    from urd.core.errors import DeviceError

    sim = SimulatedEll14().__enter__()
    with open_port(sim.port_name) as port:
        with Ell14(port, timeout_s=0.2, retries=0) as stage:
            stage.info()
            sim.__exit__(None, None, None)          # the far end closes, as an unplugged USB adapter does
            with pytest.raises(DeviceError, match="lost the connection to the ELL14 .* still plugged in"):
                stage.move_to(45.0)
