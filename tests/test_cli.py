"""The CLI lists its commands and never fakes results."""

import os
import re
import subprocess
import sys

import pytest

COMMANDS = ("capture", "sim-stage", "ingest", "calibrate", "separate", "train", "bench", "report", "verify", "demo")


def urd(*args, cwd=None):
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1"}
    return subprocess.run([sys.executable, "-m", "urd.cli", *args], capture_output=True, text=True, timeout=300,
                          env=env, cwd=cwd)


def test_help_lists_every_command_with_a_line_of_help():
    out = urd("--help")
    assert out.returncode == 0
    for name in COMMANDS:
        match = re.search(rf"^\W*{name}\s{{2,}}(\w.{{10,}})$", out.stdout, re.M)
        assert match, f"no help line for {name}"


@pytest.mark.slow
def test_bench_prints_the_table_and_the_paired_gain_of_the_network_over_direct():
    out = urd("bench", "--count", "3", "--size", "64", "--methods", "none,direct,network")
    assert out.returncode == 0, out.stderr
    names = [line.split(" | ")[0].strip("| ") for line in out.stdout.splitlines() if line.startswith("| ")][1:]
    assert names == ["none", "direct", "network"]
    assert re.search(r"T PSNR network - direct: [+-]\d+\.\d\d dB \(95% bootstrap interval .*\), higher on \d of 3 patches", out.stdout)
    bad = urd("bench", "--count", "2", "--size", "64", "--methods", "none,nonsense")
    assert bad.returncode != 0 and "nonsense" in bad.stderr + bad.stdout


@pytest.mark.slow
def test_commands_without_a_dataset_use_the_current_dataset_or_dataset_folder(tmp_path):
    """The design card's `urd capture --stage ...`, `urd ingest raw/`, `urd separate scene_12`
    name no dataset: ./dataset from outside a dataset, the current folder inside one."""
    out = urd("capture", "--stage", "sim", "--camera", "virtual", "--sim-size", "256x192", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "dataset" / "scene_01" / "scene.json").is_file()
    assert urd("ingest", "dataset", cwd=tmp_path).returncode == 0
    out = urd("separate", "scene_01", "--method", "none", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "dataset" / "scene_01" / "results" / "none" / "T.tiff").is_file()
    inside = urd("report", cwd=tmp_path / "dataset")
    assert inside.returncode == 0 and re.search(r"scene_01: 3 shots .* aligned, .* none", inside.stdout)
    lost = urd("separate", "scene_01", cwd=tmp_path / "dataset" / "scene_01")
    assert lost.returncode == 1 and "lies inside the dataset" in lost.stderr and "(in scene_01)" in lost.stderr


def test_version_and_help_show_the_sim_and_virtual_prefixes():
    out = urd("--version")
    assert out.returncode == 0 and re.fullmatch(r"urd \d+\.\d+\.\d+\n", out.stdout)
    out = urd("capture", "--help")
    assert "[sim] polarizer mounting offset" in out.stdout and "[virtual] sensor size" in out.stdout


def test_bad_parameters_exit_2_with_the_reason(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from urd.cli import app

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("COLUMNS", "200")
    for args, reason in ((("separate", "--images", "a.tif", "--angles", "0,45,nan"), "finite"),
                         (("separate", "--images", "a.tif", "--angles", "0,45,180"), "same mod 180"),
                         (("capture", "--stage", "sim", "--sim-size", "0x10"), "between 32 and 20000"),
                         (("capture", "--stage", "sim", "--address", "G"), "one hex digit 0-F"),
                         (("separate", "scene_01", "--reference", "east"), "'auto', 'global' or an angle"),
                         (("separate", "scene_01", "--method", "kong", "--precision", "bf16"), "--precision: for the networks"),
                         (("separate", "scene_01", "--method", "farid", "--colour-match"), "--colour-match: for the networks"),
                         (("separate", "scene_01", "--out", "x"), "--out: for --images"),
                         (("bench", "--ablation", "--seeds", "1,1"), "at least two different"),
                         (("bench", "--jobs", "3"), "go with --ablation"),
                         (("bench", "--steps", "16000"), "go with --ablation"),
                         (("bench", "--ablation", "--steps", "0"), "--steps")):
        out = CliRunner().invoke(app, list(args))
        assert out.exit_code == 2 and reason in out.stderr, (args, out.output)


def test_the_installed_urd_command_is_main_with_its_sigterm_handling_and_quick_exit(monkeypatch):
    import signal
    import tomllib
    from pathlib import Path

    import urd.cli

    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["urd"] == "urd.cli:main"
    server = subprocess.Popen([sys.executable, "-c", "import sys; sys.argv = ['urd', 'sim-stage']; from urd.cli import main; main()"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert "simulated ELL14 on" in server.stdout.readline()
    server.send_signal(signal.SIGTERM)
    assert server.wait(timeout=60) == 0                      # stopped as by Ctrl-C, not killed by the signal (-15)
    server.stdout.close()
    server.stderr.close()
    ended = []
    monkeypatch.setattr(sys, "argv", ["urd", "--version"])
    monkeypatch.setattr(urd.cli, "exit_now", ended.append)
    installed = []
    monkeypatch.setattr(urd.cli, "handle_interrupts", lambda: installed.append(1))   # this process's stay pytest's
    urd.cli.main()
    assert ended == [0] and installed == [1]


@pytest.mark.parametrize("code,status,stderr", [(3, 3, ""), (None, 0, ""), ("Error: gone", 1, "Error: gone\n")])
def test_the_quick_exit_runs_the_exit_handlers_flushes_and_keeps_the_status(code, status, stderr):
    program = ("import atexit, sys; from urd.cli import exit_now; atexit.register(print, 'handler ran'); "
               f"print('work done', end=' '); exit_now({code!r})")
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout, done.stderr) == (status, "work done handler ran\n", stderr)


def test_the_quick_exit_waits_for_a_running_thread_as_a_normal_exit_does(tmp_path):
    program = ("import threading, time, pathlib; from urd.cli import exit_now; "
               f"threading.Thread(target=lambda: (time.sleep(0.5), pathlib.Path({str(tmp_path / 'late')!r}).write_text('x'))).start(); "
               "exit_now(0)")
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and (tmp_path / "late").read_text() == "x"
