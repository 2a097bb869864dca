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
