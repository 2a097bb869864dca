"""Thorlabs Elliptec ELL14 rotation mount driver over pyserial.

The ELL14 speaks ASCII over a serial line (9600 baud, 8N1). A command is the device address
('0'–'F'), a two-letter lower-case code and optional data; a reply is the address, a two-letter
upper-case code, data and CR LF. Positions are 32-bit two's-complement counts as 8 upper-case
hex digits; the counts per revolution come from the ``IN`` reply.

=========  ====================  =====================================================
command    meaning               reply
=========  ====================  =====================================================
``in``     device information    ``IN`` type(2) serial(8) year(4) fw(2) thread+hw(2)
                                 travel(4, hex) pulses per revolution(8, hex)
``gs``     status                ``GS`` code(2, hex); 0 = OK, 9 = busy (see `STATUS`)
``ho0``    home (clockwise)      ``PO`` position when done, or ``GS`` code
``maXXXX`` move absolute         ``PO`` position when done, or ``GS`` code
``gp``     get position          ``PO`` position
=========  ====================  =====================================================

The driver is handed an open ``serial.SerialBase`` (a real port, a pseudo-terminal, or a
``loop://`` URL); it never opens ports itself. Every read has a deadline; commands whose
effect does not depend on repetition (all of the above) are retried a bounded number of
times after a lost or garbled reply.
"""

from __future__ import annotations

import dataclasses
import re
import time
from typing import Callable

import serial

from urd.core.errors import DeviceError, DeviceTimeoutError, ProtocolError

try:
    from termios import error as _TermiosError       # a pseudo-terminal whose other end closed
except ImportError:                                  # no termios (Windows): pyserial raises SerialException
    _TermiosError = OSError

#: What a serial link raises when the device or its adapter goes away (unplugged, powered off).
LINK_ERRORS = (serial.SerialException, OSError, _TermiosError)

#: ELL14 status codes of ``GS`` replies → meaning. 0 is OK and 9 is busy; the rest are faults.
STATUS: dict[int, str] = {
    1: "communication time-out",
    2: "mechanical time-out (the mount could not reach the position)",
    3: "command error or command not supported",
    4: "value out of range",
    5: "module isolated",
    6: "module out of isolation",
    7: "initialisation error",
    8: "thermal error",
    10: "sensor error",
    11: "motor error",
    12: "out of range",
    13: "over-current error",
}
BUSY = 9
REPLY = re.compile(rb"^([0-9A-F])([A-Z]{2})([0-9A-Za-z]*)\r\n$")
ELL14_TYPE = 0x0E
#: The data each reply urd reads must carry, and its description for a message: a reply with
#: other data is garbled (line noise) and is asked for again, like one that does not parse.
INFO_DATA = r"[0-9A-F]{2}[0-9A-Za-z]{8}[0-9]{4}[0-9A-F]{4}[0-9A-F]{4}[0-9A-F]{8}"
REPLY_DATA = {"PO": (r"[0-9A-F]{8}", "8 hex digits (a position)"), "GS": (r"[0-9A-F]{2}", "2 hex digits (a status)"),
              "IN": (INFO_DATA, "30 characters (type, serial, year, firmware, travel, pulses per turn)")}


class DeviceStatusError(DeviceError):
    """The device reported a fault status code (``code``, meaning from `STATUS`)."""

    def __init__(self, code: int, address: str):
        self.code = code
        super().__init__(f"ELL14 at address {address} reported status {code}: {STATUS.get(code, 'unknown status code')}")


@dataclasses.dataclass(frozen=True)
class Ell14Info:
    """Contents of the ``IN`` reply."""

    device_type: int
    serial_number: str
    year: str
    firmware: str
    travel: int
    pulses_per_rev: int


def parse_info(data: str) -> Ell14Info:
    """Parse the data of an ``IN`` reply (30 characters); ProtocolError if malformed."""
    if not re.fullmatch(INFO_DATA, data):
        raise ProtocolError(f"malformed ELL14 info reply {data!r}: expected {REPLY_DATA['IN'][1]}")
    return Ell14Info(
        device_type=int(data[0:2], 16),
        serial_number=data[2:10],
        year=data[10:14],
        firmware=data[14:16],
        travel=int(data[18:22], 16),
        pulses_per_rev=int(data[22:30], 16),
    )


def encode_counts(counts: int) -> str:
    """Signed 32-bit count → 8 upper-case hex digits (two's complement)."""
    return f"{counts & 0xFFFFFFFF:08X}"


def decode_counts(text: str) -> int:
    """8 hex digits (two's complement) → signed 32-bit count."""
    value = int(text, 16)
    return value - (1 << 32) if value & 0x80000000 else value


class Ell14:
    """An ELL14 rotation mount on a handed-in serial connection.

    Args:
        port: an open ``serial.SerialBase``.
        address: device address, '0'–'F'.
        timeout_s: deadline for a reply to a query (s).
        move_timeout_s: deadline for a home or move to finish (s).
        retries: extra attempts after a lost or garbled reply.

    Two optional hooks let a progress display tell the truth about the link: ``on_wait()`` is
    called about every 0.1 s while a reply is awaited (a lost reply is waited out for the whole
    time-out, up to ``move_timeout_s`` for a move), ``on_retry(message)`` before a command is sent
    again, with a line saying why.

    Use as a context manager; on exit the input buffer is drained and the port stays open
    (its owner closes it).
    """

    def __init__(self, port: serial.SerialBase, address: str = "0", timeout_s: float = 1.0,
                 move_timeout_s: float = 10.0, retries: int = 2):
        if not re.fullmatch(r"[0-9A-F]", address):
            raise ValueError(f"expected an address '0'..'F', got {address!r}")
        self.port = port
        self.address = address
        self.timeout_s = timeout_s
        self.move_timeout_s = move_timeout_s
        self.retries = retries
        self.on_wait: Callable[[], None] | None = None
        self.on_retry: Callable[[str], None] | None = None
        self._info: Ell14Info | None = None
        self._answered = False                       # a reply came on this link: a later silence is a stage gone away

    def __enter__(self) -> "Ell14":
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.port.reset_input_buffer()
        except LINK_ERRORS:
            pass                                     # the link is gone: nothing left to drain

    # -- transport ---------------------------------------------------------------------------
    def _read_reply(self, deadline: float) -> tuple[str, str]:
        """Read one CR LF-terminated reply before ``deadline``; return (code, data)."""
        line = b""
        while not line.endswith(b"\n"):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                partial = f" (partial reply {line!r})" if line else ""
                if self._answered:
                    raise DeviceTimeoutError(
                        f"ELL14 at address {self.address} stopped answering: no reply within the time-out{partial}, "
                        "though it answered earlier; check its cable or USB adapter and its power")
                raise DeviceTimeoutError(
                    f"ELL14 at address {self.address} did not answer within the time-out{partial}"
                    ": is it powered and cabled, on this port, and at this address (--address)?"
                )
            self.port.timeout = min(remaining, 0.1)
            line += self.port.read_until(b"\n")
            if self.on_wait is not None:
                self.on_wait()
        match = REPLY.match(line)
        if not match:
            raise ProtocolError(f"garbled reply from ELL14: {line!r}")
        addr, code, data = (g.decode() for g in match.groups())
        if addr != self.address:
            raise ProtocolError(f"reply from address {addr}, expected {self.address}: {line!r}")
        self._answered = True
        return code, data

    def _transact(self, command: str, expect: tuple[str, ...], timeout_s: float) -> tuple[str, str]:
        """Send a command and return the first reply whose code is in ``expect``.

        A ``GS`` reply with code 9 (busy) keeps waiting; other non-zero ``GS`` codes raise
        the error from `STATUS`. Lost and garbled replies are retried ``retries`` times; a link
        that fails (`LINK_ERRORS`) is a DeviceError.
        """
        try:
            return self._exchange(command, expect, timeout_s)
        except DeviceError:                          # a time-out is an OSError too: it stays what it is
            raise
        except LINK_ERRORS as exc:
            raise DeviceError(f"lost the connection to the ELL14 at address {self.address} ({exc}): "
                              "is its cable or USB adapter still plugged in and the stage powered?") from exc

    def _exchange(self, command: str, expect: tuple[str, ...], timeout_s: float) -> tuple[str, str]:
        """`_transact` over a working link."""
        attempt = 0
        while True:
            self.port.reset_input_buffer()
            self.port.write(f"{self.address}{command}".encode())
            self.port.flush()
            deadline = time.monotonic() + timeout_s
            try:
                while True:
                    code, data = self._read_reply(deadline)
                    pattern, meaning = REPLY_DATA.get(code, (r".*", ""))
                    if not re.fullmatch(pattern, data):
                        raise ProtocolError(f"garbled reply {code}{data} to command {command!r}: expected {code} with {meaning}")
                    if code == "GS" and "GS" not in expect:
                        status = int(data, 16)
                        if status == BUSY or status == 0:
                            continue
                        raise DeviceStatusError(status, self.address)
                    if code in expect:
                        return code, data
                    raise ProtocolError(f"unexpected reply {code}{data} to command {command!r}: expected {' or '.join(expect)}")
            except (DeviceTimeoutError, ProtocolError) as exc:
                if attempt >= self.retries:
                    raise
                attempt += 1
                if self.on_retry is not None:
                    why = f"no reply within {timeout_s:g} s" if isinstance(exc, DeviceTimeoutError) else "a garbled reply"
                    self.on_retry(f"{why} to {command!r}; sending it again (retry {attempt} of {self.retries})")

    # -- device API --------------------------------------------------------------------------
    def info(self) -> Ell14Info:
        """Device information; ProtocolError if the device is not an ELL14."""
        _, data = self._transact("in", ("IN",), self.timeout_s)
        info = parse_info(data)
        if info.device_type != ELL14_TYPE or info.pulses_per_rev <= 0:
            raise ProtocolError(f"device at address {self.address} is type {info.device_type:02X}, not an ELL14 (0E)")
        self._info = info
        return info

    @property
    def pulses_per_rev(self) -> int:
        """Encoder counts per revolution (from the ``IN`` reply)."""
        return (self._info or self.info()).pulses_per_rev

    def status(self) -> int:
        """The status code; raises the mapped error for fault codes, returns 0 or 9 (busy)."""
        _, data = self._transact("gs", ("GS",), self.timeout_s)
        status = int(data, 16)
        if status not in (0, BUSY):
            raise DeviceStatusError(status, self.address)
        return status

    def home(self) -> float:
        """Home clockwise; returns the position (deg) reported when done."""
        _, data = self._transact("ho0", ("PO",), self.move_timeout_s)
        return self.counts_to_deg(decode_counts(data))

    def move_to(self, angle_deg: float) -> float:
        """Move to ``angle_deg`` (stage frame, degrees, wrapped to [0, 360)); returns the
        position (deg) the device reports when done."""
        counts = round((angle_deg % 360.0) / 360.0 * self.pulses_per_rev) % self.pulses_per_rev
        _, data = self._transact(f"ma{encode_counts(counts)}", ("PO",), self.move_timeout_s)
        return self.counts_to_deg(decode_counts(data))

    def position(self) -> float:
        """Current position (deg)."""
        _, data = self._transact("gp", ("PO",), self.timeout_s)
        return self.counts_to_deg(decode_counts(data))

    def counts_to_deg(self, counts: int) -> float:
        return counts * 360.0 / self.pulses_per_rev
