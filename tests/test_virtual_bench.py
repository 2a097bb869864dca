"""The virtual-camera benchmark (``urd bench --virtual``) on a tiny setting."""

import re

import pytest

from urd.virtual_bench import THETAS_DEG, run_virtual_bench


@pytest.mark.slow
def test_the_virtual_set_scores_every_angle_and_the_wide_view():
    tables = run_virtual_bench(("none", "schechner"), size=(128, 96), pairs=1)
    rows = {}
    for line in tables.splitlines():
        if line.startswith("| "):
            rows.setdefault(line.split("|")[1].strip(), line)             # the PSNR table comes first
    assert all(f"{theta:.0f}°" in rows for theta in THETAS_DEG)
    t_none, t_schechner = (float(v) for v in re.findall(r"([\d.]+) / [\d.]+", rows["50°"]))
    assert t_schechner > t_none + 3.0                      # the closed form holds on a flat pane
    assert "schechner (auto)" in rows and "schechner (global)" in rows and "none (auto)" not in rows
    estimates = [line for line in tables.splitlines() if re.match(r"\| \d+° \| \d+–\d+° \|", line)]
    assert len(estimates) == len(THETAS_DEG)
    field, one = (float(v) for v in estimates[2].split("|")[3:5])    # 50°: θ turns across the pane
    assert field < one
