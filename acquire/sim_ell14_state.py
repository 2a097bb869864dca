"""The simulated ELL14's state machine: the commands it parses from the bytes it receives, its
motion, settings and faults, and the replies it makes; `acquire.sim_ell14.SimulatedEll14` serves
it on a pseudo-terminal.

Protocol followed: Thorlabs "Elliptec ELLx modules protocol manual", Issue 7 (the revision
Thorlabs links for the ELL14; Issue 5, Nov 2019, has the same messages for the commands below).
The manual's own text was not at hand offline: message codes, data lengths and reply formats
come from its message list as reproduced by open-source Elliptec clients, and the ELL14 ``IN``
reply matches one recorded from a real ELL14. Behaviour the manual leaves open is marked
*(sim)* below; it is this simulator's choice, not a documented device fact.

A command is the address ('0'-'F'), a two-letter lower-case code and a fixed amount of data;
no terminator is needed (CR and LF between commands are skipped). Positions and distances are
32-bit two's-complement encoder counts as 8 upper-case hex digits; 143360 counts per turn.
Every reply is the address, an upper-case code, data and CR LF.

=============  ====================================  =========================================
command        meaning                               reply
=============  ====================================  =========================================
``in``         device information                    ``IN`` type(2) serial(8) year(4) fw(2)
                                                     hw(2) travel(4 hex) counts/turn(8 hex)
``gs``         status                                ``GS00``; ``GS09`` while busy
``gp``         position                              ``PO`` counts(8)
``hoD``        home, D = 0 clockwise, 1 ccw          ``PO00000000`` when done
``maXXXXXXXX`` move absolute, counts in [0, turn)    ``PO`` counts(8) when done
``mrXXXXXXXX`` move relative, signed counts          ``PO`` counts(8) when done (wraps a turn)
``gj``         jog step size                         ``GJ`` counts(8)
``sjXXXXXXXX`` set jog step, counts in [0, turn)     ``GS00``
``fw``/``bw``  jog forward/backward one step;        ``PO`` counts(8) when done; with step 0
               with step 0 move until ``st``          no reply until ``st``
``st``         stop a move, jog, search or clean     ``PO`` counts(8) where it stopped, or
                                                     ``GS00`` (sim: the stopped command gets
                                                     no reply of its own)
``gv``         velocity, percent of maximum          ``GV`` percent(2 hex)
``svXX``       set velocity, 1-100 % (sim range)     ``GS00``
``go``         home offset                           ``HO`` counts(8)
``soXXXXXXXX`` set home offset, counts in [0, turn)  ``GS00`` (applies at the next home)
``caA``        change address to A                   ``GS00`` from the new address
``us``         save user data                        ``GS00``
``i1``/``i2``  motor 1/2 information                 ``I1``/``I2`` loop(1) motor on(1)
                                                     current(4) ramp up(4) ramp down(4)
                                                     forward period(4) backward period(4)
``f1XXXX`` …   set forward/backward period of        ``GS00``; ``8FFF`` restores the factory
``b2XXXX``     motor 1/2 (top bit is a flag)         period
``s1``/``s2``  search motor 1/2 frequency            ``GS00`` when done (sim: 0.2 s)
``om``/``cm``  optimize motors / clean mechanics     ``GS00`` when done (sim: 3 s; ``st`` stops)
``isXX``/      isolate / group address: accepted by  ``GS03`` (sim: parsed with their data
``gaA``        the ELL14, not modelled               length, not simulated)
=============  ====================================  =========================================

Errors, always exactly one ``GS`` reply: an unknown code or malformed data (not upper-case
hex, or cut short by CR/LF) answers ``GS03`` (command error or not supported) and the parser
drops the rest of that line: up to and including the next CR or LF, or all bytes received so
far when none came, so no stale byte is read as a new command. A value out of its range answers
``GS04``. A command left incomplete for 0.25 s answers ``GS01`` (communication time-out, sim).
While a move, jog, search or clean runs, queries (``in gs gp gj gv go i1 i2``) are answered and
``st`` stops it; any other command answers ``GS09`` (busy) and is ignored *(sim)*. Commands for
other addresses are parsed the same way and get no reply.

Moves take time: ``sim_speed_dps`` at 100 % velocity, scaled by the velocity, at most 2 s per
move. Positions are quantized to encoder counts. Simulation-only knobs carry the ``sim_``
prefix: a mounting offset and an angle jitter that the encoder does not see (they show only in
the light through the polarizer, `true_angle_deg`), and fault injection.

Fault kinds (probability per command, or forced for the next command with `sim_force`):

* ``drop`` — the reply is never sent;
* ``garble`` — the reply's bytes are corrupted;
* ``mech_timeout`` — a move answers ``GS02`` and stays where it was;
* ``miss`` — a move stops a few degrees short and reports where it stopped;
* ``vanish`` — the device stops answering anything until `sim_revive`.

Every command, reply and fault is appended to ``log``.
"""

from __future__ import annotations

import dataclasses
import enum

from acquire.ell14 import decode_counts, encode_counts

FAULTS = ("drop", "garble", "mech_timeout", "miss", "vanish")
ADDRESSES = "0123456789ABCDEF"
HEX_DIGITS = frozenset("0123456789ABCDEF")
TERMINATORS = b"\r\n"
FRAME_TIMEOUT_S = 0.25     # an incomplete command older than this answers GS01 (sim)
MAX_MOVE_S = 2.0           # longest simulated move
SEARCH_S = 0.2             # s1/s2 frequency search (sim; minutes-long operations scaled down)
MAINTENANCE_S = 3.0        # om/cm (sim)
MISS_DEG = 3.0             # how far short a ``miss`` fault stops
MOTOR_CURRENT = 0x0230     # I1/I2 current while moving, 1866 points per ampere (sim)
FACTORY_PERIODS = {"1": (0x00B7, 0x008D), "2": (0x00B3, 0x008B)}   # forward, backward (sim)
RESTORE_PERIOD = 0x8FFF    # f1/b1/f2/b2 data that restores the factory period
PERIOD_FLAG = 0x8000


class Status(enum.IntEnum):
    """``GS`` status codes the simulator sends (numbering of the protocol manual)."""

    OK = 0
    COMMUNICATION_TIMEOUT = 1
    MECHANICAL_TIMEOUT = 2
    COMMAND_ERROR = 3          # command error or not supported
    VALUE_OUT_OF_RANGE = 4
    BUSY = 9


def status_reply(status: Status) -> str:
    """``GS`` reply (without address and CR LF) for ``status``, e.g. ``GS03``."""
    return f"GS{int(status):02X}"


@dataclasses.dataclass(frozen=True)
class CommandSpec:
    """One command the ELL14 accepts: data length (characters) and whether it is a query,
    answered even while the mount is busy."""

    data_length: int
    query: bool


COMMANDS: dict[str, CommandSpec] = {
    "in": CommandSpec(0, True), "gs": CommandSpec(0, True), "gp": CommandSpec(0, True),
    "gj": CommandSpec(0, True), "gv": CommandSpec(0, True), "go": CommandSpec(0, True),
    "i1": CommandSpec(0, True), "i2": CommandSpec(0, True),
    "ho": CommandSpec(1, False), "ma": CommandSpec(8, False), "mr": CommandSpec(8, False),
    "fw": CommandSpec(0, False), "bw": CommandSpec(0, False), "st": CommandSpec(0, False),
    "sj": CommandSpec(8, False), "sv": CommandSpec(2, False), "so": CommandSpec(8, False),
    "ca": CommandSpec(1, False), "us": CommandSpec(0, False),
    "f1": CommandSpec(4, False), "b1": CommandSpec(4, False),
    "f2": CommandSpec(4, False), "b2": CommandSpec(4, False),
    "s1": CommandSpec(0, False), "s2": CommandSpec(0, False),
    "om": CommandSpec(0, False), "cm": CommandSpec(0, False),
    "is": CommandSpec(2, False), "ga": CommandSpec(1, False),
}
NOT_MODELLED = frozenset({"is", "ga"})


class OperationKind(enum.Enum):
    """What keeps the simulated mount busy."""

    MOVE = "move"              # home, move absolute/relative, jog step: ends by itself
    CONTINUOUS = "continuous"  # fw/bw with jog step 0: runs until st
    MAINTENANCE = "maintenance"  # frequency search, optimize, clean: ends by itself, no motion


@dataclasses.dataclass
class _Operation:
    kind: OperationKind
    entry: dict
    fault: str | None
    start_s: float
    duration_s: float | None           # None: until st
    start_counts: int = 0
    direction: int = 0                  # +1 forward, -1 backward
    distance: int = 0                   # counts to travel (MOVE)
    speed_cps: float = 0.0              # counts per second (CONTINUOUS)
    end_counts: int = 0                 # reported position when done (MOVE)
    new_frame: int | None = None        # frame after a home (counts of the new zero)


class Ell14StateMachine:
    """What the simulated ELL14 does with the commands it receives: parsing, motion, settings,
    faults. The serving class (`acquire.sim_ell14.SimulatedEll14`) holds the state it works on
    (``address``, ``counts``, ``pulses_per_rev``, ``sim_`` knobs, ``rng``, ``log``, ``_operation``,
    ``_lock``, ...) and sends the replies (``_send``, ``true_angle_deg``)."""

    # -- parsing -----------------------------------------------------------------------------
    def _consume(self, buffer: bytes, now: float) -> bytes:
        """Handle every complete command in ``buffer``; return the incomplete rest."""
        while True:
            buffer = buffer.lstrip(TERMINATORS)
            if not buffer:
                return buffer
            if chr(buffer[0]) not in ADDRESSES:          # not a command start: skip the byte
                buffer = buffer[1:]
                continue
            if len(buffer) < 3:
                return buffer
            addr, code = chr(buffer[0]), buffer[1:3].decode("latin-1")
            spec = COMMANDS.get(code)
            if spec is None:                             # unknown: one reply, drop the line
                text, buffer = _cut_line(buffer)
                self._handle(addr, code, "", text, Status.COMMAND_ERROR, now)
                continue
            frame = buffer[3:3 + spec.data_length]
            eol = next((i for i, b in enumerate(frame) if b in TERMINATORS), None)
            if eol is not None:                          # cut short by CR/LF
                text, buffer = buffer[:3 + eol].decode("latin-1"), buffer[3 + eol + 1:]
                self._handle(addr, code, "", text, Status.COMMAND_ERROR, now)
                continue
            if len(frame) < spec.data_length:
                return buffer
            text, buffer = buffer[:3 + spec.data_length].decode("latin-1"), buffer[3 + spec.data_length:]
            self._handle(addr, code, text[3:], text, None, now)

    def _expire(self, buffer: bytes, now: float) -> None:
        """An incomplete command timed out: answer GS01 if it was ours."""
        self._handle(chr(buffer[0]), buffer[1:3].decode("latin-1"), "", buffer.decode("latin-1"),
                     Status.COMMUNICATION_TIMEOUT, now)

    def _draw_fault(self) -> str | None:
        if self.forced:
            return self.forced.pop(0)
        for kind, prob in self.sim_faults.items():
            if self.rng.random() < prob:
                return kind
        return None

    def _handle(self, addr: str, code: str, data: str, text: str, error: Status | None, now: float) -> None:
        """Answer one parsed command (``error``: answer that status instead of executing it)."""
        if addr != self.address:
            return
        fault = None if self.vanished else self._draw_fault()
        if fault == "vanish":
            self.vanished = True
        entry = {"time": now, "command": text, "fault": fault, "reply": None}
        self.log.append(entry)
        if self.vanished:
            return
        if error is not None:
            reply = status_reply(error)
        elif code in NOT_MODELLED:
            reply = status_reply(Status.COMMAND_ERROR)
        elif self._operation is not None and not COMMANDS[code].query and code != "st":
            reply = status_reply(Status.BUSY)
        else:
            reply = getattr(self, f"_do_{code}")(data, entry, fault, now)
        if reply is not None:
            self._send(entry, reply, fault)

    # -- motion ------------------------------------------------------------------------------
    def _position(self, now: float) -> int:
        """Encoder counts now, in [0, pulses_per_rev); interpolated during a move."""
        return self._position_during(self._operation, now)

    def _position_during(self, op: _Operation | None, now: float) -> int:
        """Encoder counts at ``now`` while ``op`` runs (``None``: idle)."""
        if op is None or op.kind is OperationKind.MAINTENANCE:
            return self.counts
        if op.kind is OperationKind.CONTINUOUS:
            travelled = op.speed_cps * (now - op.start_s)
        else:
            fraction = 1.0 if op.duration_s <= 0 else min(1.0, (now - op.start_s) / op.duration_s)
            travelled = op.distance * fraction
        return (op.start_counts + op.direction * int(travelled)) % self.pulses_per_rev

    def _speed_cps(self) -> float:
        return self.sim_speed_dps * self.velocity_percent / 100.0 * self.pulses_per_rev / 360.0

    def _start_move(self, entry: dict, fault: str | None, now: float, path: int, end_counts: int,
                    new_frame: int | None = None) -> None:
        """Move ``path`` counts (signed) from here; report ``end_counts`` when done."""
        distance = abs(path)
        operation = _Operation(
            OperationKind.MOVE, entry, fault, now, min(distance / self._speed_cps(), MAX_MOVE_S),
            start_counts=self.counts, direction=1 if path >= 0 else -1, distance=distance,
            end_counts=end_counts % self.pulses_per_rev, new_frame=new_frame)
        with self._lock:
            self._operation = operation

    def _advance(self, now: float) -> None:
        """Finish the running operation if its time is up, and send its reply."""
        op = self._operation
        if op is None or op.duration_s is None or now < op.start_s + op.duration_s:
            return
        if op.kind is OperationKind.MAINTENANCE or op.fault == "mech_timeout":
            with self._lock:
                self._operation = None
            status = Status.OK if op.kind is OperationKind.MAINTENANCE else Status.MECHANICAL_TIMEOUT
            self._send(op.entry, status_reply(status), op.fault)
            return
        end = op.end_counts
        if op.fault == "miss":
            end = (end - int(self.pulses_per_rev * MISS_DEG / 360)) % self.pulses_per_rev
        self._settle(end, op.new_frame)
        self._send(op.entry, f"PO{encode_counts(self.counts)}", op.fault)

    def _settle(self, counts: int, frame: int | None = None) -> None:
        """End the running motion at ``counts`` (and, after a home, the new zero ``frame``)."""
        with self._lock:
            self._operation = None
            self.counts = counts
            if frame is not None:
                self._frame = frame
            self.error_deg = float(self.rng.normal(0.0, self.sim_jitter_deg)) if self.sim_jitter_deg else 0.0

    # -- commands (each returns its reply now, or None when it answers later) ----------------
    def _do_in(self, data, entry, fault, now) -> str:
        return f"IN{self.sim_device_type:02X}{12345678:08d}20261701{360:04X}{self.pulses_per_rev:08X}"

    def _do_gs(self, data, entry, fault, now) -> str:
        return status_reply(Status.BUSY if self._operation is not None else Status.OK)

    def _do_gp(self, data, entry, fault, now) -> str:
        return f"PO{encode_counts(self._position(now))}"

    def _do_gj(self, data, entry, fault, now) -> str:
        return f"GJ{encode_counts(self.jog_step)}"

    def _do_gv(self, data, entry, fault, now) -> str:
        return f"GV{self.velocity_percent:02X}"

    def _do_go(self, data, entry, fault, now) -> str:
        return f"HO{encode_counts(self.home_offset)}"

    def _motor_info(self, motor: str) -> str:
        moving = self._operation is not None and self._operation.kind is not OperationKind.MAINTENANCE
        forward, backward = self.periods[motor]
        current = MOTOR_CURRENT if moving else 0
        return f"I{motor}1{int(moving)}{current:04X}FFFFFFFF{forward:04X}{backward:04X}"

    def _do_i1(self, data, entry, fault, now) -> str:
        return self._motor_info("1")

    def _do_i2(self, data, entry, fault, now) -> str:
        return self._motor_info("2")

    def _do_ho(self, data, entry, fault, now) -> str | None:
        if data not in ("0", "1"):
            return status_reply(Status.VALUE_OUT_OF_RANGE)
        target = self.home_offset - self._frame          # the new zero, in today's counts
        self._start_move(entry, fault, now, target - self.counts, 0, new_frame=self.home_offset)
        return None

    def _do_ma(self, data, entry, fault, now) -> str | None:
        if not _is_hex(data):
            return status_reply(Status.COMMAND_ERROR)
        target = decode_counts(data)
        if not 0 <= target < self.pulses_per_rev:
            return status_reply(Status.VALUE_OUT_OF_RANGE)
        self._start_move(entry, fault, now, target - self.counts, target)
        return None

    def _do_mr(self, data, entry, fault, now) -> str | None:
        if not _is_hex(data):
            return status_reply(Status.COMMAND_ERROR)
        delta = decode_counts(data)
        self._start_move(entry, fault, now, delta, self.counts + delta)
        return None

    def _jog(self, direction: int, entry, fault, now) -> str | None:
        if self.jog_step == 0:
            operation = _Operation(OperationKind.CONTINUOUS, entry, fault, now, None, start_counts=self.counts,
                                   direction=direction, speed_cps=self._speed_cps())
            with self._lock:
                self._operation = operation
            return None
        self._start_move(entry, fault, now, direction * self.jog_step, self.counts + direction * self.jog_step)
        return None

    def _do_fw(self, data, entry, fault, now) -> str | None:
        return self._jog(1, entry, fault, now)

    def _do_bw(self, data, entry, fault, now) -> str | None:
        return self._jog(-1, entry, fault, now)

    def _do_st(self, data, entry, fault, now) -> str:
        op = self._operation
        if op is None or op.kind is OperationKind.MAINTENANCE:
            with self._lock:
                self._operation = None
            return status_reply(Status.OK)
        op.entry["stopped_by"] = entry["command"]
        self._settle(self._position_during(op, now))
        return f"PO{encode_counts(self.counts)}"

    def _set_counts(self, data: str, attribute: str) -> str:
        if not _is_hex(data):
            return status_reply(Status.COMMAND_ERROR)
        value = decode_counts(data)
        if not 0 <= value < self.pulses_per_rev:
            return status_reply(Status.VALUE_OUT_OF_RANGE)
        setattr(self, attribute, value)
        return status_reply(Status.OK)

    def _do_sj(self, data, entry, fault, now) -> str:
        return self._set_counts(data, "jog_step")

    def _do_so(self, data, entry, fault, now) -> str:
        return self._set_counts(data, "home_offset")

    def _do_sv(self, data, entry, fault, now) -> str:
        if not _is_hex(data, 2):
            return status_reply(Status.COMMAND_ERROR)
        percent = int(data, 16)
        if not 1 <= percent <= 100:
            return status_reply(Status.VALUE_OUT_OF_RANGE)
        self.velocity_percent = percent
        return status_reply(Status.OK)

    def _do_ca(self, data, entry, fault, now) -> str:
        if data not in ADDRESSES:
            return status_reply(Status.VALUE_OUT_OF_RANGE)
        self.address = data
        return status_reply(Status.OK)

    def _do_us(self, data, entry, fault, now) -> str:
        return status_reply(Status.OK)

    def _set_period(self, motor: str, index: int, data: str) -> str:
        if not _is_hex(data, 4):
            return status_reply(Status.COMMAND_ERROR)
        value = int(data, 16)
        period = FACTORY_PERIODS[motor][index] if value == RESTORE_PERIOD else value & ~PERIOD_FLAG
        if period == 0:
            return status_reply(Status.VALUE_OUT_OF_RANGE)
        self.periods[motor][index] = period
        return status_reply(Status.OK)

    def _do_f1(self, data, entry, fault, now) -> str:
        return self._set_period("1", 0, data)

    def _do_b1(self, data, entry, fault, now) -> str:
        return self._set_period("1", 1, data)

    def _do_f2(self, data, entry, fault, now) -> str:
        return self._set_period("2", 0, data)

    def _do_b2(self, data, entry, fault, now) -> str:
        return self._set_period("2", 1, data)

    def _maintain(self, duration_s: float, entry, fault, now) -> None:
        with self._lock:
            self._operation = _Operation(OperationKind.MAINTENANCE, entry, fault, now, duration_s)

    def _do_s1(self, data, entry, fault, now) -> None:
        self._maintain(SEARCH_S, entry, fault, now)

    def _do_s2(self, data, entry, fault, now) -> None:
        self._maintain(SEARCH_S, entry, fault, now)

    def _do_om(self, data, entry, fault, now) -> None:
        self._maintain(MAINTENANCE_S, entry, fault, now)

    def _do_cm(self, data, entry, fault, now) -> None:
        self._maintain(MAINTENANCE_S, entry, fault, now)


def _is_hex(text: str, length: int = 8) -> bool:
    return len(text) == length and all(c in HEX_DIGITS for c in text)


def _cut_line(buffer: bytes) -> tuple[str, bytes]:
    """Split off the line at the start of ``buffer``: (its text without the terminator, the
    bytes after the first CR or LF); all of ``buffer`` when it holds no terminator."""
    ends = [i for i in (buffer.find(b"\r"), buffer.find(b"\n")) if i >= 0]
    if not ends:
        return buffer.decode("latin-1"), b""
    end = min(ends)
    return buffer[:end].decode("latin-1"), buffer[end + 1:]
