"""The terminal progress line: counts, elapsed time and an ETA from the rate seen here."""

import io

import pytest

from urd.core import progress


def test_eta_counts_the_units_done_here_not_before_a_resume(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    out = io.StringIO()
    bar = progress.TerminalProgress(out)
    bar(1000, 2000, "train")                  # a run resumed at step 1000
    now[0] += 10.0
    bar(1010, 2000, "train")                  # 10 steps in 10 s: 990 s left
    line = out.getvalue().split("\r")[-1]
    assert "1010/2000" in line and "0:10" in line and "ETA 16:30" in line
    now[0] += 1.0
    bar(2000, 2000, "train")
    assert out.getvalue().split("\r")[-1].rstrip().endswith("done")
    bar(0, 3, "separate")                     # a new label starts a new line and a new clock
    assert "\n" in out.getvalue() and "ETA --:--" in out.getvalue().split("\r")[-1]


def test_a_line_break_keeps_the_clock_running(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    out = io.StringIO()
    bar = progress.TerminalProgress(out)
    bar(0, 100, "train")
    now[0] += 30.0
    bar(50, 100, "train")
    bar.break_line()
    out.write("step 50: val PSNR T 30.00 dB\n")
    now[0] += 30.0
    bar(100, 100, "train")
    assert "\nstep 50: val PSNR T 30.00 dB\n" in out.getvalue()
    assert "1:00" in out.getvalue().split("\r")[-1]          # elapsed since the start, not since the break


def test_a_log_file_gets_a_line_every_ten_seconds_not_every_step(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    out = io.StringIO()
    bar = progress.TerminalProgress(out)
    for step in range(101):                   # one step a second
        bar(step, 100, "train")
        now[0] += 1.0
    assert "\r" not in out.getvalue()                 # a log gets whole lines, not a terminal's redrawn one
    lines = out.getvalue().splitlines()
    assert [line.split()[3] for line in lines] == [f"{k}/100" for k in range(0, 101, 10)]


def test_training_bar_ends_where_the_time_cap_stops_the_run():
    from urd.cli.train import projected_steps

    first = {"step": 0, "wall_s": 0.0}
    assert projected_steps(100000, 330.0, first, {"step": 300, "wall_s": 165.0}) == 600      # the cap comes first
    assert projected_steps(500, 330.0, first, {"step": 300, "wall_s": 165.0}) == 500         # the steps do
    assert projected_steps(100000, 0.0, first, {"step": 300, "wall_s": 165.0}) == 100000     # no cap
    resumed = {"step": 400, "wall_s": 1000.0}                                                 # the cap counts this session
    assert projected_steps(100000, 60.0, resumed, {"step": 430, "wall_s": 1030.0}) == 460
    assert projected_steps(100000, 60.0, resumed, resumed) == 100000                          # no pace yet
    assert projected_steps(100000, 60.0, first, {"step": 50, "wall_s": 70.0}) == 50           # past the cap: where it is


def test_a_label_naming_the_item_at_hand_does_not_start_a_line_per_item(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    out = io.StringIO()
    bar = progress.TerminalProgress(out)
    for done in range(6):                     # a benchmark naming each scene it scores, a tenth of a second apart
        bar(done, 6, f"semi-real: scene {done}")
        now[0] += 0.1
    bar(6, 6, "semi-real")
    bar(0, 2, "tables")                       # a new step: another total
    assert [line.split()[0:2] for line in out.getvalue().splitlines()] == [["semi-real:", "scene"], ["semi-real", "[########################]"], ["tables", "[------------------------]"]]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")      # the swallowed exception, as printed
def test_a_ctrl_c_a_finalizer_swallowed_stops_the_work_at_the_next_progress_report():
    import signal
    import weakref

    from urd.core import processes

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    bar = progress.TerminalProgress(io.StringIO())
    try:
        processes.handle_interrupts()

        class Held:
            pass

        held = Held()
        watch = weakref.ref(held, lambda ref: signal.raise_signal(signal.SIGINT))   # Ctrl-C during a weakref callback
        del held                                            # its KeyboardInterrupt is printed by Python, not raised
        assert watch() is None
        with pytest.raises(KeyboardInterrupt):
            bar(1, 2, "work")
        bar(2, 2, "work")                                   # raised once: a later report goes on
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        processes._RAISED.clear()
