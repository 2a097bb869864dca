"""The CLI lists its commands and never fakes results."""

import os
import re
import subprocess
import sys

COMMANDS = ("capture", "ingest", "calibrate", "separate", "train", "bench", "report", "demo")


def urd(*args):
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1"}
    return subprocess.run([sys.executable, "-m", "urd.cli", *args], capture_output=True, text=True, timeout=300, env=env)


def test_help_lists_every_command_with_a_line_of_help():
    out = urd("--help")
    assert out.returncode == 0
    for name in COMMANDS:
        match = re.search(rf"^\W*{name}\s{{2,}}(\w.{{10,}})$", out.stdout, re.M)
        assert match, f"no help line for {name}"


def test_bench_prints_the_table_and_the_paired_gain_of_the_network_over_direct():
    out = urd("bench", "--count", "3", "--size", "64", "--methods", "none,direct,network")
    assert out.returncode == 0, out.stderr
    names = [line.split(" | ")[0].strip("| ") for line in out.stdout.splitlines() if line.startswith("| ")][1:]
    assert names == ["none", "direct", "network"]
    assert re.search(r"T PSNR network - direct: [+-]\d+\.\d\d dB \(95% bootstrap interval .*\), higher on \d of 3 patches", out.stdout)
    bad = urd("bench", "--count", "2", "--size", "64", "--methods", "none,nonsense")
    assert bad.returncode != 0 and "nonsense" in bad.stderr + bad.stdout
