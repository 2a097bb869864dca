"""A simulated ELL14 served behind a real pseudo-terminal, usable as a tool.

The driver (or any third-party Elliptec client) opens the pty's slave path with pyserial exactly
as it opens /dev/ttyUSB0, so every byte goes through the real serial code path. Run it alone with
``python -m acquire.sim_ell14`` (or ``urd sim-stage``); it prints the slave path and serves until
Ctrl-C or SIGTERM.

What the device does with each command (the protocol followed, its errors, timing and fault
kinds) is its state machine, `acquire.sim_ell14_state`; this module holds its state, serves it on
the pty and adds the simulation-only controls (`SimulatedEll14.true_angle_deg`, `sim_force`,
`sim_revive`).
"""

from __future__ import annotations

import argparse
import math
import os
import select
import signal
import sys
import threading
import time
import tty
from typing import Callable

import numpy as np

from acquire.sim_ell14_state import ADDRESSES, FACTORY_PERIODS, FAULTS, FRAME_TIMEOUT_S, Ell14StateMachine, _Operation
from urd.core.errors import DeviceError, UrdError


class SimulatedEll14(Ell14StateMachine):
    """ELL14 twin on a pseudo-terminal; use as a context manager (starts and stops its thread).

    Args:
        address: device address, '0'-'F'.
        pulses_per_rev: encoder counts per revolution (reported by ``in``), > 0.
        sim_offset_deg: polarizer axis angle at stage zero (mounting offset), degrees.
        sim_jitter_deg: standard deviation of the unseen angle error of each move, degrees, ≥ 0.
        sim_speed_dps: rotation speed at 100 % velocity, degrees per second, > 0.
        sim_faults: fault kind → probability per command, each in [0, 1].
        sim_device_type: device type reported by ``in`` (0x0E is an ELL14).
        seed: seed of the jitter and fault draws.
        sim_reversed: the mount turned round: a positive move turns the polarizer clockwise as
            the camera sees it (urd takes stage angles counter-clockwise; `urd calibrate offset
            --check-direction` finds this out).
    """

    def __init__(self, address: str = "0", pulses_per_rev: int = 143360, sim_offset_deg: float = 0.0,
                 sim_jitter_deg: float = 0.0, sim_speed_dps: float = 2000.0,
                 sim_faults: dict[str, float] | None = None, sim_device_type: int = 0x0E, seed: int = 0,
                 sim_reversed: bool = False):
        if not isinstance(address, str) or len(address) != 1 or address not in ADDRESSES:
            raise ValueError(f"expected an address '0'..'F', got {address!r}")
        if pulses_per_rev <= 0:
            raise ValueError(f"expected pulses_per_rev > 0, got {pulses_per_rev}")
        if not math.isfinite(sim_offset_deg):
            raise ValueError(f"expected a finite sim_offset_deg, got {sim_offset_deg}")
        if not (math.isfinite(sim_jitter_deg) and sim_jitter_deg >= 0):
            raise ValueError(f"expected sim_jitter_deg ≥ 0, got {sim_jitter_deg}")
        if not (math.isfinite(sim_speed_dps) and sim_speed_dps > 0):
            raise ValueError(f"expected sim_speed_dps > 0, got {sim_speed_dps}")
        unknown = set(sim_faults or {}) - set(FAULTS)
        if unknown:
            raise ValueError(f"expected fault kinds among {FAULTS}, got {sorted(unknown)}")
        self.address = address
        self.pulses_per_rev = pulses_per_rev
        self.sim_offset_deg = sim_offset_deg
        self.sim_direction = -1.0 if sim_reversed else 1.0
        self.sim_jitter_deg = sim_jitter_deg
        self.sim_speed_dps = sim_speed_dps
        self.sim_faults = dict(sim_faults or {})
        self.sim_device_type = sim_device_type
        self.rng = np.random.default_rng(seed)
        self.counts = 0
        self.error_deg = 0.0
        self.velocity_percent = 100
        self.jog_step = pulses_per_rev // 72          # 5° (sim default)
        self.home_offset = 0
        self.periods = {motor: list(periods) for motor, periods in FACTORY_PERIODS.items()}
        self.vanished = False
        self.forced: list[str] = []
        self.log: list[dict] = []
        self._frame = 0                # counts of the current zero from the factory home
        self._operation: _Operation | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.port_name = os.ttyname(slave)
        self._slave = slave
        self._thread = threading.Thread(target=self._run, name="sim-ell14", daemon=True)

    def __enter__(self) -> "SimulatedEll14":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        """Start serving (once; later calls do nothing)."""
        if self._thread.ident is None and not self._stop.is_set():
            self._thread.start()

    @property
    def serving(self) -> bool:
        """Whether the serving thread runs."""
        return self._thread.is_alive()

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
        """The polarizer's physical axis angle now (degrees, image-plane convention): the
        mounting offset plus the stage's angle, or minus it on a reversed mount (``sim_reversed``:
        a positive move turns the polarizer clockwise as the camera sees it)."""
        with self._lock:
            counts = self._position(time.monotonic())
            stage_deg = (counts + self._frame) * 360.0 / self.pulses_per_rev
            return self.sim_offset_deg + self.sim_direction * stage_deg + self.error_deg

    def sim_force(self, kind: str) -> None:
        """Make the next command suffer fault ``kind``."""
        if kind not in FAULTS:
            raise ValueError(f"expected a fault kind among {FAULTS}, got {kind!r}")
        self.forced.append(kind)

    def sim_revive(self) -> None:
        """Bring a vanished device back."""
        self.vanished = False

    # -- transport ---------------------------------------------------------------------------
    def _run(self) -> None:
        buffer = b""
        last_rx = time.monotonic()
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], self._poll_timeout())
            now = time.monotonic()
            if ready:
                try:
                    chunk = os.read(self.master, 1024)
                except OSError:
                    return
                buffer += chunk
                last_rx = now
            self._advance(now)
            buffer = self._consume(buffer, now)
            if buffer and now - last_rx > FRAME_TIMEOUT_S:
                self._expire(buffer, now)
                buffer = b""

    def _poll_timeout(self) -> float:
        operation = self._operation
        if operation is None or operation.duration_s is None:
            return 0.05
        return max(0.0, min(0.05, operation.start_s + operation.duration_s - time.monotonic()))

    def _send(self, entry: dict, reply: str, fault: str | None) -> None:
        entry.update(reply=reply, counts=self.counts, true_angle_deg=self.true_angle_deg())
        if fault == "drop" or self.vanished:
            return
        raw = f"{self.address}{reply}\r\n".encode()
        if fault == "garble":
            raw = bytes(b ^ 0x55 if i in (1, 4) else b for i, b in enumerate(raw))
        try:
            os.write(self.master, raw)
        except OSError:
            pass


# -- the runnable server ---------------------------------------------------------------------
def parse_faults(text: str) -> dict[str, float]:
    """'drop=0.05,garble=0.01' → {'drop': 0.05, 'garble': 0.01}; '' → {}.

    Kinds are among `FAULTS`, each at most once; probabilities are numbers in [0, 1].
    Raises ValueError naming the bad item.
    """
    if not isinstance(text, str):
        raise ValueError(f"expected a text like drop=0.05,garble=0.01, got {type(text).__name__}")
    faults: dict[str, float] = {}
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        kind, sep, prob_text = (part.strip() for part in item.partition("="))
        if not sep or kind not in FAULTS:
            raise ValueError(f"expected KIND=PROBABILITY items with KIND among {', '.join(FAULTS)}, got {item!r}")
        if kind in faults:
            raise ValueError(f"expected each fault kind once, got {kind!r} twice")
        try:
            prob = float(prob_text)
        except ValueError:
            raise ValueError(f"expected a probability in [0, 1] for {kind}, got {prob_text!r}") from None
        if not 0.0 <= prob <= 1.0:
            raise ValueError(f"expected a probability in [0, 1] for {kind}, got {prob_text!r}")
        faults[kind] = prob
    return faults


def serve(sim: SimulatedEll14, announce: Callable[[str], None], stop: threading.Event | None = None) -> None:
    """Serve ``sim`` (started here if it is not yet) until ``stop`` is set, Ctrl-C, or SIGTERM.

    ``announce`` gets one line with the pty path to open, e.g. ``simulated ELL14 on /dev/pts/5
    (address 0); Ctrl-C to stop``. Called from the main thread, SIGTERM sets ``stop`` and SIGINT
    stops it even where the parent shell ignored SIGINT (a background job), while serving (the
    previous handlers are restored on return). Returns normally on each of these;
    DeviceError if the simulator stops serving by itself. Does not close ``sim``.
    """
    stop = stop or threading.Event()
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: stop.set()) if in_main_thread else None
    # a shell starts background jobs with SIGINT ignored, and Python keeps it so: Ctrl-C / kill -INT must still stop us
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler) if in_main_thread else None
    try:
        sim.start()
        announce(f"simulated ELL14 on {sim.port_name} (address {sim.address}); Ctrl-C to stop")
        while not stop.wait(0.1):
            if not sim.serving:
                raise DeviceError(f"the simulated ELL14 on {sim.port_name} stopped serving")
    except KeyboardInterrupt:
        pass
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
            signal.signal(signal.SIGINT, previous_int if previous_int is not None else signal.default_int_handler)


def main(argv: list[str] | None = None) -> int:
    """``python -m acquire.sim_ell14``: serve a simulated ELL14 on a pty; exit status 0 after
    Ctrl-C or SIGTERM, 1 if it fails, 2 for bad arguments."""
    parser = argparse.ArgumentParser(
        prog="python -m acquire.sim_ell14",
        description="Serve a simulated Thorlabs ELL14 rotation mount on a pseudo-terminal until Ctrl-C, "
                    "to test any Elliptec client (9600 baud, 8N1).")
    parser.add_argument("--offset-deg", type=float, default=0.0,
                        help="polarizer mounting offset the encoder does not see (deg, default 0)")
    parser.add_argument("--jitter-deg", type=float, default=0.0,
                        help="per-move angle error the encoder does not see, std (deg, default 0)")
    parser.add_argument("--faults", default="",
                        help=f"fault probabilities per command, e.g. drop=0.05,garble=0.01; kinds: {', '.join(FAULTS)}")
    parser.add_argument("--address", default="0", help="device address 0-F (default 0)")
    parser.add_argument("--seed", type=int, default=0, help="seed of jitter and fault draws (default 0)")
    args = parser.parse_args(argv)
    try:
        faults = parse_faults(args.faults)
        sim = SimulatedEll14(args.address, sim_offset_deg=args.offset_deg, sim_jitter_deg=args.jitter_deg,
                             sim_faults=faults, seed=args.seed)
    except ValueError as exc:
        parser.error(str(exc))
    with sim:
        try:
            serve(sim, lambda line: print(line, flush=True))
        except UrdError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
