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


def test_tables_are_shown_before_they_are_written_and_a_failed_write_is_one_error_line(tmp_path, monkeypatch):
    """A benchmark's tables reach the terminal even when its --out folder is gone by the time they
    are written (removed, unmounted, disk full): exit 1 with one line naming the folder, no traceback."""
    import shutil

    from typer.testing import CliRunner

    import urd.virtual_bench
    from urd.cli import app

    def finished_after_the_folder_went(methods, progress=None):
        shutil.rmtree(tmp_path / "out")
        return "| method | T PSNR |\n| network | 36.5 |"

    monkeypatch.setattr(urd.virtual_bench, "run_virtual_bench", finished_after_the_folder_went)
    result = CliRunner().invoke(app, ["bench", "--virtual", "--out", str(tmp_path / "out")])
    assert result.exit_code == 1, result.output
    lines = result.output.splitlines()
    assert lines[:2] == ["| method | T PSNR |", "| network | 36.5 |"]
    assert lines[2:] == [f"Error: cannot write in {tmp_path / 'out' / 'virtual'}: No such file or directory"]
