"""Worker processes that do not outlive the command that started them, and SIGTERM as an interrupt.

A scheduler's ``timeout``, ``kill`` or a closed SSH session signals the main process alone (Ctrl-C
in a terminal signals the whole group). So that no worker goes on writing into a dataset whose
lock its parent no longer holds:

* the main process turns SIGTERM into `Terminated` (a KeyboardInterrupt: every ``finally`` runs),
  and `process_pool` kills its workers on any exception instead of waiting for their tasks;
* each worker asks Linux to SIGKILL it when its parent dies (``PR_SET_PDEATHSIG``, which also
  covers a SIGKILL of the parent), and a watchdog thread ends it within `WATCH_S` once it is
  re-parented (other systems, or a parent gone before the request took effect).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from typing import Callable, Iterator

from urd.core.errors import CaptureInterrupted
from urd.core.progress import plural

PR_SET_PDEATHSIG = 1                    # linux/prctl.h
WATCH_S = 1.0                           # how often a worker checks that its parent lives (s)


class Terminated(KeyboardInterrupt):
    """The process was sent SIGTERM (raised in the main thread by `handle_interrupts`' handler)."""


def capture_stopped(exc: KeyboardInterrupt, what: str, kept: str) -> CaptureInterrupted:
    """The error for ``what`` (a capture, a calibration sweep) stopped by ``exc``: Ctrl-C, or
    SIGTERM (`Terminated`, exit 143), saying what it ``kept``."""
    terminated = isinstance(exc, Terminated)
    return CaptureInterrupted(f"{what} {'stopped by SIGTERM' if terminated else 'interrupted'}; {kept}", terminated)


#: The signals `handle_interrupts`' handler raised an exception for, in this process.
_RAISED: list[int] = []


def _interrupt(signum: int, frame) -> None:
    _RAISED.append(signum)
    if signum == signal.SIGTERM:
        raise Terminated(f"stopped by signal {signal.Signals(signum).name}")
    raise KeyboardInterrupt


def handle_interrupts() -> None:
    """Ctrl-C raises KeyboardInterrupt and SIGTERM `Terminated` in the main thread, each noted so
    that `check_interrupted` raises it again where Python swallowed it (an exception raised while
    a finalizer or weak-reference callback runs is only printed). A signal the process was started
    ignoring (a shell's background job ignores Ctrl-C) stays ignored. Call once, from the main thread."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _interrupt)


def check_interrupted() -> None:
    """In the main thread, raise the interrupt `handle_interrupts` noted if its exception was
    lost (a command that reports progress goes on otherwise); nothing elsewhere or without one."""
    if _RAISED and threading.current_thread() is threading.main_thread():
        signum = _RAISED.pop()
        _RAISED.clear()
        if signum == signal.SIGTERM:
            raise Terminated(f"stopped by signal {signal.Signals(signum).name}")
        raise KeyboardInterrupt


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Ctrl-C and SIGTERM that arrive within the block take effect as it ends, through the handlers
    that were in place (a step whose state must change all at once: an optimizer's update). Only
    the main thread handles signals; elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if pending:
            signal.raise_signal(pending[0])


def die_with_parent(parent: int) -> None:
    """Worker initializer: end this process when its parent ``parent`` (pid) ends (module
    docstring); at once if it has already."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:
        os._exit(1)
    threading.Thread(target=_watch, args=(parent,), name="urd-parent-watchdog", daemon=True).start()


def killed_with_this_process() -> Callable[[], None] | None:
    """A ``preexec_fn`` for a child program (`subprocess.run`) asking Linux to SIGKILL it when this
    process dies, even by SIGKILL (the camera's gphoto2, which would go on holding the camera's
    USB claim); None on other systems. libc is loaded here, before the fork."""
    if not sys.platform.startswith("linux"):
        return None
    prctl, parent = ctypes.CDLL(None, use_errno=True).prctl, os.getpid()

    def request() -> None:
        prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent:                   # this process died before the request took effect
            os._exit(1)

    return request


def _watch(parent: int) -> None:
    """End this process once it is no longer ``parent``'s child (checked every `WATCH_S` s)."""
    while os.getppid() == parent:
        time.sleep(WATCH_S)
    os._exit(1)


@contextlib.contextmanager
def process_pool(jobs: int) -> Iterator[concurrent.futures.ProcessPoolExecutor]:
    """A pool of ``jobs`` fresh worker interpreters (spawned: no forked torch state) that die with
    this process. On leaving, queued tasks are cancelled; on an exception (an interrupt, SIGTERM)
    the workers are killed at once rather than left to finish their tasks."""
    context = multiprocessing.get_context("spawn")
    pool = concurrent.futures.ProcessPoolExecutor(jobs, mp_context=context, initializer=die_with_parent,
                                                  initargs=(os.getpid(),))
    try:
        yield pool
    except BaseException:
        for process in list(pool._processes.values()):     # no public way before Python 3.14's kill_workers
            process.kill()
        raise
    finally:
        pool.shutdown(cancel_futures=True)


def kept_note(names: list[str], what: str, forced: bool = False) -> str:
    """What an interrupted command with workers kept: the scenes it recorded (``what``:
    separated, ingested) before it was stopped; the others are unchanged. ``forced``: the
    command redoes every scene (--force, --redo), so running it again redoes the kept ones too."""
    if not names:
        return f"no scene {what} before it and none changed: run the same command again"
    again = ("run the same command again to do them (it does the kept ones again too; name the others "
             "one by one to spare them)" if forced else "run the same command again to do them")
    return f"{plural(len(names), 'scene')} {what} before it ({', '.join(names)}) kept, the others unchanged: {again}"
