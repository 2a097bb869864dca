"""Progress reporting: one callback shape for every long step, one terminal renderer.

A workflow takes ``progress: Progress | None`` and calls ``progress(done, total, label)``
with counts of its own units (tiles, shots, steps, patches). The CLI renders it with
`TerminalProgress`: a bar with percentage, counts, elapsed time and ETA on stderr.
"""

from __future__ import annotations

import sys
import time
import weakref
from typing import Callable, TextIO

Progress = Callable[[int, int, str], None]


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}" if seconds >= 3600 else f"{seconds // 60}:{seconds % 60:02d}"


def plural(count: int, noun: str) -> str:
    """'1 scene', '3 scenes'."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


#: Seconds between two progress lines written to a stream that is not a terminal.
LOG_INTERVAL_S = 10.0


class TerminalProgress:
    """Render progress callbacks as one updating line (a new line when the label changes).

    The ETA extrapolates the rate of the current label's units since its first call, counted
    from the ``done`` of that call (a resumed run starts part-way: its earlier units took no time
    here). The line is redrawn at most every 0.2 s on a terminal and every `LOG_INTERVAL_S` on
    anything else (a log file of a long run), besides each label's first and last call.
    """

    #: Bars with a line drawn and not yet ended (`end_open_lines`).
    _open: "weakref.WeakSet[TerminalProgress]" = weakref.WeakSet()

    def __init__(self, stream: TextIO = sys.stderr, width: int = 24):
        self.stream, self.width = stream, width
        self.label: str | None = None
        self.started = time.monotonic()
        self.first_done = 0
        self.last_draw = 0.0
        self.interval = 0.2 if stream.isatty() else LOG_INTERVAL_S

    def __call__(self, done: int, total: int, label: str) -> None:
        now = time.monotonic()
        if label != self.label:
            if self.label is not None:
                self.stream.write("\n")
            self.label, self.started, self.first_done = label, now, done
            TerminalProgress._open.add(self)
        elif done < total and now - self.last_draw < self.interval:
            return
        self.last_draw = now
        total = max(total, 1)
        frac = min(1.0, done / total)
        elapsed = now - self.started
        rate = (done - self.first_done) / elapsed if elapsed > 0 else 0.0
        eta = "done" if frac >= 1 else (f"ETA {_clock((total - done) / rate)}" if rate > 0 else "ETA --:--")
        bar = "#" * round(self.width * frac) + "-" * (self.width - round(self.width * frac))
        self.stream.write(f"\r{label[:40]:<40} [{bar}] {100 * frac:3.0f}% {done}/{total} {_clock(elapsed)} {eta}  ")
        self.stream.flush()

    def break_line(self) -> None:
        """End the current line so that other output can follow; the progress goes on in a new
        line with its timing (elapsed time and rate still counted from the label's first call)."""
        if self.label is not None:
            self.stream.write("\n")
            self.stream.flush()
        self.last_draw = 0.0

    def close(self) -> None:
        """End the current line."""
        if self.label is not None:
            self.stream.write("\n")
            self.stream.flush()
            self.label = None
        TerminalProgress._open.discard(self)

    @classmethod
    def end_open_lines(cls, stream: TextIO) -> None:
        """End the lines every bar left open on ``stream``, so that a message starts a line of its
        own (a command may hand its bar to the work inside a callback, out of the error handler's sight)."""
        for bar in list(cls._open):
            if bar.stream is stream:
                bar.close()
