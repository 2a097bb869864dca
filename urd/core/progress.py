"""Progress reporting: one callback shape for every long step, one terminal renderer.

A workflow takes ``progress: Progress | None`` and calls ``progress(done, total, label)``
with counts of its own units (tiles, shots, steps, patches). The CLI renders it with
`TerminalProgress`: a bar with percentage, counts, elapsed time and ETA on stderr, redrawn in
place on a terminal and written as occasional plain lines anywhere else (a log file, a pipe).
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
    """Render progress callbacks as one updating line on a terminal (a new line when a new step
    starts: the label changes and the count starts again or has another total; a label that
    changes while the count goes on, naming the item at hand, stays on its line), and as plain
    lines on anything else (a log file of a long run): no carriage returns there, one line at
    most every `LOG_INTERVAL_S`, besides each step's first and last.

    The ETA extrapolates the rate of the current label's units since its first call, counted
    from the ``done`` of that call (a resumed run starts part-way: its earlier units took no time
    here). On a terminal the line is redrawn at most every 0.2 s, besides each label's first and
    last call.
    """

    #: Bars with a line drawn and not yet ended (`end_open_lines`).
    _open: "weakref.WeakSet[TerminalProgress]" = weakref.WeakSet()

    def __init__(self, stream: TextIO = sys.stderr, width: int = 24):
        self.stream, self.width = stream, width
        self.label: str | None = None
        self.started = time.monotonic()
        self.first_done = 0
        self.last_draw = 0.0
        self.lines = not stream.isatty()             # plain lines, each ended, instead of one line redrawn
        self.interval = LOG_INTERVAL_S if self.lines else 0.2
        self.finished = False                        # the label's last line is written (plain lines: once)
        self.done, self.total = 0, 0                 # the last call's counts

    def __call__(self, done: int, total: int, label: str) -> None:
        from urd.core.processes import check_interrupted

        check_interrupted()                 # a Ctrl-C whose exception a finalizer swallowed stops the work here
        now = time.monotonic()
        goes_on = self.label is not None and total == self.total and done >= self.done
        self.done, self.total = done, total
        if label != self.label and not goes_on:
            if self.label is not None and not self.lines:
                self.stream.write("\n")
            self.label, self.started, self.first_done, self.finished = label, now, done, False
            if not self.lines:
                TerminalProgress._open.add(self)
        elif done < total and now - self.last_draw < self.interval:
            self.label = label
            return
        elif self.lines and done >= total and self.finished:
            return
        self.label = label
        self.last_draw = now
        total = max(total, 1)
        frac = min(1.0, done / total)
        self.finished = frac >= 1
        elapsed = now - self.started
        rate = (done - self.first_done) / elapsed if elapsed > 0 else 0.0
        eta = "done" if frac >= 1 else (f"ETA {_clock((total - done) / rate)}" if rate > 0 else "ETA --:--")
        bar = "#" * round(self.width * frac) + "-" * (self.width - round(self.width * frac))
        text = f"{label[:40]:<40} [{bar}] {100 * frac:3.0f}% {done}/{total} {_clock(elapsed)} {eta}  "
        self.stream.write(f"{text}\n" if self.lines else f"\r{text}")
        self.stream.flush()

    def break_line(self) -> None:
        """End the current line so that other output can follow; the progress goes on in a new
        line with its timing (elapsed time and rate still counted from the label's first call).
        Plain lines are ended already."""
        if self.label is not None and not self.lines:
            self.stream.write("\n")
            self.stream.flush()
        self.last_draw = 0.0

    def close(self) -> None:
        """End the current line."""
        if self.label is not None and not self.lines:
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
