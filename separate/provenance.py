"""What a result depends on: command, commit, date, CPU, library versions and precision.

`environment` is printed at the top of every report (the paper's evaluation, the ablation) and
`cpu_model` names the machine in the speed tools' output.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

#: The repository's root (its git work tree).
REPO = Path(__file__).resolve().parent.parent


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else what platform reports."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def git_commit() -> str:
    """HEAD's commit, with " (working tree modified)" when tracked files differ; "unknown" without git."""
    try:
        head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    if head.returncode:
        return "unknown"
    return head.stdout.strip() + (" (working tree modified)" if dirty.stdout.strip() else "")


def _command_line() -> str:
    """This process's command as typed: ``python tools/x.py ARGS`` or ``urd ARGS``."""
    program = sys.argv[0]
    if program.endswith(".py"):
        return shlex.join(["python", os.path.relpath(program) if os.path.isabs(program) else program, *sys.argv[1:]])
    return shlex.join([Path(program).name, *sys.argv[1:]])


def environment(command: str | None = None) -> dict:
    """What a result depends on: command, commit, date, CPU, torch and its capability flags, precision."""
    import torch

    from separate.precision import describe, resolve

    caps = torch.cpu.get_capabilities() if hasattr(torch.cpu, "get_capabilities") else {}
    flags = [k for k in ("avx2", "avx512_f", "avx512_bf16", "avx512_vnni", "amx_bf16", "amx_tile") if caps.get(k)]
    precision = resolve("auto")
    return {
        "command": command or _command_line(),
        "commit": git_commit(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "flags": flags,
        "precision": precision.value,
        "precision_note": describe(precision),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
    }
