"""A simulated ELL14 served behind a real pseudo-terminal.

The driver opens the pty's slave path with pyserial exactly as it opens /dev/ttyUSB0, so every
byte goes through the real serial code path. The twin answers ``in``, ``gs``, ``gp``, ``ho`` and
``ma`` like the device, takes time to move, quantizes positions to encoder counts, and has
simulation-only knobs (``sim_`` prefix): a mounting offset and angle jitter that the encoder
does not see (they show only in the light through the polarizer), and fault injection.

Fault kinds (probability per command, or forced for the next command with `sim_force`):

* ``drop`` — the reply is never sent;
* ``garble`` — the reply's bytes are corrupted;
* ``mech_timeout`` — a move answers ``GS02`` and stays where it was;
* ``miss`` — a move stops a few degrees short and reports where it stopped;
* ``vanish`` — the device stops answering anything until `sim_revive`.

Every command, reply and fault is appended to ``log``.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import numpy as np

from acquire.ell14 import decode_counts, encode_counts

FAULTS = ("drop", "garble", "mech_timeout", "miss", "vanish")
DATA_LENGTH = {"in": 0, "gs": 0, "gp": 0, "ho": 1, "ma": 8}


class SimulatedEll14:
    """ELL14 twin on a pseudo-terminal; use as a context manager (starts and stops its thread).

    Args:
        address: device address.
        pulses_per_rev: encoder counts per revolution (reported by ``in``).
        sim_offset_deg: polarizer axis angle at stage zero (mounting offset), degrees.
        sim_jitter_deg: standard deviation of the unseen angle error of each move, degrees.
        sim_speed_dps: rotation speed, degrees per second.
        sim_faults: fault kind → probability per command.
        sim_device_type: device type reported by ``in`` (0x0E is an ELL14).
        seed: seed of the jitter and fault draws.
    """

    def __init__(self, address: str = "0", pulses_per_rev: int = 143360, sim_offset_deg: float = 0.0,
                 sim_jitter_deg: float = 0.0, sim_speed_dps: float = 2000.0,
                 sim_faults: dict[str, float] | None = None, sim_device_type: int = 0x0E, seed: int = 0):
        unknown = set(sim_faults or {}) - set(FAULTS)
        if unknown:
            raise ValueError(f"expected fault kinds among {FAULTS}, got {sorted(unknown)}")
        self.address = address
        self.pulses_per_rev = pulses_per_rev
        self.sim_offset_deg = sim_offset_deg
        self.sim_jitter_deg = sim_jitter_deg
        self.sim_speed_dps = sim_speed_dps
        self.sim_faults = dict(sim_faults or {})
        self.sim_device_type = sim_device_type
        self.rng = np.random.default_rng(seed)
        self.counts = 0
        self.error_deg = 0.0
        self.vanished = False
        self.forced: list[str] = []
        self.log: list[dict] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.port_name = os.ttyname(slave)
        self._slave = slave
        self._thread = threading.Thread(target=self._serve, name="sim-ell14", daemon=True)

    def __enter__(self) -> "SimulatedEll14":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop serving and close the pseudo-terminal."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    # -- simulation-only controls -----------------------------------------------------------
    def true_angle_deg(self) -> float:
        """The polarizer's physical axis angle now (degrees, image-plane convention)."""
        with self._lock:
            return self.counts * 360.0 / self.pulses_per_rev + self.sim_offset_deg + self.error_deg

    def sim_force(self, kind: str) -> None:
        """Make the next command suffer fault ``kind``."""
        if kind not in FAULTS:
            raise ValueError(f"expected a fault kind among {FAULTS}, got {kind!r}")
        self.forced.append(kind)

    def sim_revive(self) -> None:
        """Bring a vanished device back."""
        self.vanished = False

    # -- the device ------------------------------------------------------------------------
    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            try:
                buffer += os.read(self.master, 256)
            except OSError:
                return
            buffer = self._consume(buffer)

    def _consume(self, buffer: bytes) -> bytes:
        """Handle every complete command in ``buffer``; return the unparsed rest."""
        while buffer:
            buffer = buffer.lstrip(b"\r\n")
            if len(buffer) < 3:
                return buffer
            addr, code = chr(buffer[0]), buffer[1:3].decode("ascii", "replace")
            length = 3 + DATA_LENGTH.get(code, 0)
            if len(buffer) < length:
                return buffer
            command, buffer = buffer[:length].decode("ascii", "replace"), buffer[length:]
            if addr == self.address:
                self._handle(command)
        return buffer

    def _draw_fault(self) -> str | None:
        if self.forced:
            return self.forced.pop(0)
        for kind, prob in self.sim_faults.items():
            if self.rng.random() < prob:
                return kind
        return None

    def _handle(self, command: str) -> None:
        code, data = command[1:3], command[3:]
        fault = None if self.vanished else self._draw_fault()
        if fault == "vanish":
            self.vanished = True
        entry = {"time": time.monotonic(), "command": command, "fault": fault, "reply": None}
        self.log.append(entry)
        if self.vanished:
            return
        if code == "in":
            reply = f"IN{self.sim_device_type:02X}{12345678:08d}20261701{360:04X}{self.pulses_per_rev:08X}"
        elif code == "gs":
            reply = "GS00"
        elif code == "gp":
            reply = f"PO{encode_counts(self.counts)}"
        elif code in ("ho", "ma"):
            target = 0 if code == "ho" else decode_counts(data) if _is_hex(data) else None
            reply = self._move(target, fault) if target is not None else "GS04"
        else:
            reply = "GS03"
        entry.update(reply=reply, counts=self.counts, true_angle_deg=self.true_angle_deg())
        if fault == "drop":
            return
        raw = f"{self.address}{reply}\r\n".encode()
        if fault == "garble":
            raw = bytes(b ^ 0x55 if i in (1, 4) else b for i, b in enumerate(raw))
        os.write(self.master, raw)

    def _move(self, target: int, fault: str | None) -> str:
        """Move to ``target`` counts, taking time; returns the reply."""
        if not 0 <= target < self.pulses_per_rev:
            return "GS04"
        distance_deg = abs(target - self.counts) * 360.0 / self.pulses_per_rev
        time.sleep(min(distance_deg / self.sim_speed_dps, 2.0))
        if fault == "mech_timeout":
            return "GS02"
        if fault == "miss":
            target = (target - int(self.pulses_per_rev * 3 / 360)) % self.pulses_per_rev
        with self._lock:
            self.counts = target
            self.error_deg = float(self.rng.normal(0.0, self.sim_jitter_deg)) if self.sim_jitter_deg else 0.0
        return f"PO{encode_counts(self.counts)}"


def _is_hex(text: str) -> bool:
    return len(text) == 8 and all(c in "0123456789ABCDEF" for c in text)
