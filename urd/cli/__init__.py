"""The ``urd`` command line: a thin layer. Each command parses its options, calls one workflow
function (acquire.plan, urd.ingest, urd.calibration, calib.store, urd.separation, urd.report, urd.demo,
separate.train, separate.bench) and prints.

One module per command group: `capture` (capture, sim-stage), `calibrate`, `ingest`, `separate`,
`reports` (report, verify), `demo`, `train`, `bench`; what they share (the error voice, option
checks and parsers) is in `common`. This module assembles them into one typer app.

Angles are degrees here and in manifests. Errors print one line in one voice, "Error: ...":
bad arguments name the option ("Invalid value for '--method': ...") and exit with status 2,
failures exit with status 1 (130 after Ctrl-C). Output paths are printed absolute. `main` is the
installed ``urd`` command: SIGTERM handling, the app, then a quick exit (`exit_now`).
"""

from __future__ import annotations

import atexit
import os
import sys
import threading
from typing import NoReturn

import typer

from urd import __version__
from urd.cli import bench, calibrate, capture, demo, ingest, reports, separate, train
from urd.cli.common import HELP_OPTIONS, WorkflowOrder
from urd.core.processes import handle_interrupts

app = typer.Typer(
    cls=WorkflowOrder,
    help="urd: photograph scenes through glass with a rotating polarizer and separate reflection from transmission.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings=HELP_OPTIONS,
)


def show_version(value: bool) -> None:
    if value:
        typer.echo(f"urd {__version__}")
        raise typer.Exit()


@app.callback()
def main_options(
    version: bool = typer.Option(False, "--version", callback=show_version, is_eager=True, help="Print urd's version and exit."),
) -> None:
    """urd: photograph scenes through glass with a rotating polarizer and separate reflection from transmission."""


app.command()(capture.capture)
app.command("sim-stage")(capture.sim_stage)
app.command()(ingest.ingest)
app.add_typer(calibrate.calibrate_app, name="calibrate")
app.command()(separate.separate)
app.command()(train.train)
app.command()(bench.bench)
app.command()(reports.report)
app.command()(reports.verify)
app.command()(demo.demo)


def main() -> None:
    """The ``urd`` command: the app, then a quick exit (`exit_now`)."""
    handle_interrupts()                     # SIGTERM stops worker pools and says what was kept, as Ctrl-C does
    try:
        app(prog_name="urd")                # standalone: always ends in SystemExit
    except SystemExit as done:
        exit_now(done.code)


def exit_now(code: int | str | None) -> NoReturn:
    """End the process as ``sys.exit(code)`` would, without the interpreter's teardown of every
    module: once torch is imported that takes 0.5-0.7 s of CPU after the work is done (its many
    Python objects cleared one by one). The exit handlers run and the standard streams are
    flushed first; where a thread other than daemons is still running, the normal exit waits
    for it instead."""
    if any(thread.is_alive() and not thread.daemon for thread in threading.enumerate()
           if thread is not threading.main_thread()):
        sys.exit(code)
    if isinstance(code, str):
        print(code, file=sys.stderr)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):       # a reader gone or a stream closed: nothing more to say there
            pass
    os._exit(code if isinstance(code, int) else 0 if code is None else 1)
