"""QA findings on `urd bench` and the scripts in tools/: refusals, help texts, one-line errors."""

import argparse
import contextlib
import dataclasses
import io
import itertools
import json
import runpy
import sys
from pathlib import Path
from unittest import mock

import pytest
import torch
from typer.testing import CliRunner

from separate import ablation
from separate.bench import benchmark_set, largest_size
from separate.networks import build_model
from separate.provenance import cpu_model
from separate.train import TrainConfig, model_config
from urd.cli import app
from urd.core.errors import TrainingError

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def tool(name: str, *args) -> tuple[int, str, str]:
    """Run tools/NAME in this process with ``args``: (exit status, stdout, stderr). An exception
    other than SystemExit (a traceback for the user) fails the test."""
    out, err = io.StringIO(), io.StringIO()
    code = 0
    with mock.patch.object(sys, "argv", [name, *map(str, args)]), mock.patch.object(sys, "path", [str(TOOLS), *sys.path]), \
            contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            runpy.run_path(str(TOOLS / name), run_name="__main__")
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
            if isinstance(exc.code, str):
                err.write(exc.code)
    return code, out.getvalue(), err.getvalue()


def bench(*args) -> tuple[int, str]:
    """``urd bench ARGS`` in this process: (exit status, output)."""
    out = CliRunner().invoke(app, ["bench", *map(str, args)], env={"COLUMNS": "200"})
    return out.exit_code, out.output


def checkpoint(path: Path, seed: int, precision: str = "fp32", steps: int = 3) -> Path:
    """A tiny training checkpoint (width 4) at ``path``, its weights drawn with ``seed``."""
    torch.manual_seed(seed)
    cfg = TrainConfig(width=4, steps=steps, precision=precision, threads=1)
    model = build_model(model_config(cfg))
    torch.save({"model": model.state_dict(), "model_config": model.config(), "optim": None, "step": steps,
                "train_config": dataclasses.asdict(cfg), "wall_s": 5.0, "init": None, "val": {"psnr_t": 20.0}}, path)
    return path


# 1. export_weights.py: an existing output is replaced only with --force


def test_export_refuses_to_replace_other_weights_but_exports_the_same_again(tmp_path):
    first, second = checkpoint(tmp_path / "run3.pt", 3), checkpoint(tmp_path / "run1.pt", 1)
    out = tmp_path / "exp" / "mine.pt"
    assert tool("export_weights.py", first, out)[0] == 0
    kept = out.read_bytes(), out.with_suffix(".json").read_bytes()
    code, _, err = tool("export_weights.py", second, out)
    assert code == 1 and "mine.pt and" in err and "exist;" in err and "--force" in err
    assert (out.read_bytes(), out.with_suffix(".json").read_bytes()) == kept
    assert tool("export_weights.py", first, out, "--note", "another note")[0] == 1            # the card would change
    assert tool("export_weights.py", first, out)[0] == 0 and out.read_bytes() == kept[0]        # nothing changes: allowed
    out.unlink()
    assert tool("export_weights.py", first, out)[0] == 1                                       # the card alone is there
    assert tool("export_weights.py", second, out, "--force")[0] == 0
    assert out.read_bytes() != kept[0]
    out.write_text("not weights")                                                              # --force replaces any file
    assert tool("export_weights.py", second, out, "--force")[0] == 0 and out.read_bytes()[:2] == b"PK"


def test_a_scratch_folder_is_made_anew_only_when_the_tool_made_it(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(TOOLS))
    from toolargs import SCRATCH_MARK, scratch

    folder = scratch(tmp_path / "bench")
    (folder / "dataset.json").write_text("{}")                       # what the tool then writes there
    assert sorted(p.name for p in scratch(folder).iterdir()) == [SCRATCH_MARK]     # made anew
    (tmp_path / "link").symlink_to(folder)
    with pytest.raises(SystemExit, match="not a scratch folder this tool made"):
        scratch(tmp_path / "link")
    (folder / SCRATCH_MARK).unlink()
    (folder / "dataset.json").write_text("{}")                       # a dataset of the user's
    with pytest.raises(SystemExit, match="not a scratch folder this tool made"):
        scratch(folder)
    assert (folder / "dataset.json").is_file()


# 2. export_weights.py: the card's device is this machine and the run's precision; --help explains


def test_export_card_names_this_machine_and_the_runs_precision(tmp_path):
    out = tmp_path / "w.pt"
    code, printed, _ = tool("export_weights.py", checkpoint(tmp_path / "run.pt", 0, "fp32"), out)
    device = json.loads(printed)["training"]["device"]
    assert code == 0 and cpu_model() in device and "fp32" in device and "1 thread" in device and "bf16" not in device
    assert tool("export_weights.py", checkpoint(tmp_path / "b.pt", 0, "bf16"), tmp_path / "b-w.pt")[0] == 0
    assert "bf16 autocast" in json.loads((tmp_path / "b-w.json").read_text())["training"]["device"]
    code, printed, _ = tool("export_weights.py", "--help")
    assert code == 0
    for text in ("checkpoint", "output", "--device", "--note", "--parent", "--force", cpu_model(), "default: none"):
        assert text in printed, text


# 3. export_weights.py: bad paths are one line, not a traceback


@pytest.mark.parametrize("case", ["folder", "missing parent", "toml parent", "list parent"])
def test_export_refuses_bad_paths_in_one_line(tmp_path, case):
    run = checkpoint(tmp_path / "run.pt", 0)
    (tmp_path / "tiny.toml").write_text("steps = 4\n")
    (tmp_path / "list.json").write_text("[1, 2]\n")
    (tmp_path / "exp").mkdir()
    args, reason = {"folder": ((run, tmp_path / "exp"), "is a folder"),
                    "missing parent": ((run, tmp_path / "w.pt", "--parent", tmp_path / "nonexist.json"), "does not exist"),
                    "toml parent": ((run, tmp_path / "w.pt", "--parent", tmp_path / "tiny.toml"), "not a model card"),
                    "list parent": ((run, tmp_path / "w.pt", "--parent", tmp_path / "list.json"), "not a model card")}[case]
    code, _, err = tool("export_weights.py", *args)
    assert code == 2 and reason in err
    assert not (tmp_path / "w.pt").exists()


# 4. urd bench --ablation: runs started with another budget are refused


def test_ablation_refuses_runs_started_with_another_budget(tmp_path, monkeypatch):
    runs = tmp_path / "runs"
    for name, step in (("dr-s0", 4), ("dr-nrd-s1", 2)):
        (runs / name).mkdir(parents=True)
        checkpoint(runs / name / "last.pt", 0, steps=4)
        if step != 4:
            state = torch.load(runs / name / "last.pt", weights_only=True)
            torch.save({**state, "step": step}, runs / name / "last.pt")
    ablation.check_budgets(ablation.ablation_runs([0, 1], runs, steps=4))
    with pytest.raises(TrainingError, match=r"dr-s0, dr-nrd-s1: 4 steps\), not the 6 steps") as info:
        ablation.check_budgets(ablation.ablation_runs([0, 1], runs, steps=6))
    assert str(runs) in str(info.value) and "--runs" in str(info.value)

    def never(*args, **kwargs):
        raise AssertionError("the ablation trained or scored")

    monkeypatch.setattr(ablation, "train_missing", never)
    monkeypatch.setattr(ablation, "run_ablation", never)
    code, output = bench("--ablation", "--steps", "6", "--runs", runs, "--out", tmp_path / "out")
    assert code == 1 and "4 steps" in output and "6 steps" in output and str(runs) in output
    assert not (tmp_path / "out").exists()


# 5. urd bench: one mode per run


@pytest.mark.parametrize("pair", list(itertools.combinations(["--quick", "--full", "--ablation", "--semireal", "--virtual"], 2)))
def test_bench_refuses_two_modes(pair, monkeypatch):
    monkeypatch.setattr(ablation, "ablation_runs", mock.Mock(side_effect=AssertionError("the ablation started")))
    code, output = bench(*pair)
    assert code == 2 and f"{pair[0]} or {pair[1]}, not both" in output


# 6. bench_baselines.py: --help prints help and does nothing else


def test_bench_baselines_help_runs_nothing_and_its_folder_is_checked(tmp_path):
    code, printed, _ = tool("bench_baselines.py", "--help")
    assert code == 0 and printed.startswith("usage:") and "1-megapixel" in printed and "--folder" in printed
    (tmp_path / "mine.txt").write_text("keep")
    code, _, err = tool("bench_baselines.py", "--folder", tmp_path)
    assert code == 1 and "not a scratch folder this tool made" in err and (tmp_path / "mine.txt").read_text() == "keep"
    (tmp_path / "dataset.json").write_text("{}")                   # a dataset of the user's is not the tool's either
    code, _, err = tool("bench_baselines.py", "--folder", tmp_path)
    assert code == 1 and (tmp_path / "dataset.json").is_file() and (tmp_path / "mine.txt").is_file()


# 7. tools: bad arguments are usage errors (2), the project's errors one line (1)


@pytest.mark.parametrize("name, args, status, reason", [
    ("bench_synthetic.py", ("--count", "0"), 2, "--count: expected at least 1"),
    ("bench_synthetic.py", ("--methods", "bogus"), 2, "--methods: expected some of"),
    ("bench_synthetic.py", ("--size", "100000"), 2, "--size: expected at most"),
    ("bench_synthetic.py", ("--reference", "east"), 2, "--reference"),
    ("bench_synthetic.py", ("--count", "1", "--size", "64", "--methods", "x=/nonexist.pt"), 1, "/nonexist.pt"),
    ("bench_reference.py", ("--weights", "/nonexist.pt"), 1, "/nonexist.pt"),
    ("bench_texture.py", ("--weights", "/nonexist.pt"), 1, "/nonexist.pt"),
    ("bench_speed.py", ("--weights", "/nonexist.pt"), 1, "/nonexist.pt"),
    ("resize_upsampling.py", ("--weights", "/nonexist.pt", "--out", "{tmp}/r.pt"), 1, "/nonexist.pt"),
    ("bench_virtual.py", ("--size", "abc"), 2, "--size: expected WIDTHxHEIGHT"),
    ("bench_virtual.py", ("--methods", "bogus"), 2, "--methods"),
    ("bench_calibration.py", ("--seeds", "0"), 2, "--seeds"),
    ("bench_calibration.py", ("--size", "768"), 2, "--size"),
    ("bench_24mp.py", ("--size", "10x10"), 2, "--size"),
    ("bench_24mp.py", ("--runs", "0"), 2, "--runs"),
    ("bench_demosaic.py", ("--size", "30"), 2, "--size"),
    ("profile_separate.py", ("--size", "abc"), 2, "--size"),
    ("contact_sheets.py", ("--methods", "bogus"), 2, "--methods"),
    ("bench_paper.py", ("--images", "/nonexist"), 2, "--images"),
])
def test_tools_refuse_bad_arguments_in_one_line(tmp_path, name, args, status, reason):
    code, _, err = tool(name, *(a.format(tmp=tmp_path) for a in args))
    assert code == status and reason in err
    assert not (tmp_path / "r.pt").exists()


# 8. tools: every option has a help text, shown with its default


class Parsed(Exception):
    """Raised in place of parsing: the tool's parser is built and nothing else runs."""


def parser_of(name: str) -> argparse.ArgumentParser:
    """The argument parser tools/NAME builds (its work never starts)."""
    parsers = []

    def capture(self, *args, **kwargs):
        parsers.append(self)
        raise Parsed

    with mock.patch.object(argparse.ArgumentParser, "parse_args", capture), mock.patch.object(sys, "argv", [name]), \
            mock.patch.object(sys, "path", [str(TOOLS), *sys.path]):
        with pytest.raises(Parsed):
            runpy.run_path(str(TOOLS / name), run_name="__main__")
    return parsers[0]


@pytest.mark.parametrize("name", sorted(path.name for path in TOOLS.glob("*.py") if path.name != "toolargs.py"))     # its helpers, no script
def test_every_tool_option_has_help_and_its_default_is_shown(name):
    parser = parser_of(name)
    assert issubclass(parser.formatter_class, argparse.ArgumentDefaultsHelpFormatter), name
    bare = [action.dest for action in parser._actions if not action.help]
    assert bare == [], f"{name}: options without help: {bare}"


@pytest.mark.parametrize("name, option, unit", [
    ("bench_synthetic.py", "--size", "px"), ("bench_24mp.py", "--size", "px"), ("bench_calibration.py", "--size", "px"),
    ("bench_calibration.py", "--shake", "px"), ("bench_calibration.py", "--jitter", "deg"), ("bench_demosaic.py", "--size", "px"),
    ("bench_virtual.py", "--size", "px"), ("bench_reference.py", "--size", "px"), ("bench_texture.py", "--size", "px"),
    ("profile_separate.py", "--size", "px"), ("contact_sheets.py", "--size", "px"), ("report_screenshot.py", "--height", "px"),
    ("bench_24mp.py", "--tile", "px"),
])
def test_tool_sizes_state_their_unit(name, option, unit):
    action = next(a for a in parser_of(name)._actions if option in a.option_strings)
    assert unit in action.help


def test_tool_help_shows_the_defaults():
    code, printed, _ = tool("bench_synthetic.py", "--help")
    assert code == 0 and "benchmark patches (default: 64)" in " ".join(printed.split())
    assert "patch side (px) (default: 256)" in " ".join(printed.split())


# 9, 10. urd bench: an unused --direct-weights, a --size larger than the photos


def test_bench_refuses_direct_weights_without_direct():
    code, output = bench("--count", "1", "--size", "64", "--methods", "none", "--direct-weights", "/nonexist.pt")
    assert code == 2 and "--direct-weights: not used by this run" in output


def test_bench_names_size_and_the_largest_usable_one():
    largest = largest_size()
    assert largest >= 64
    code, output = bench("--size", "100000", "--count", "1", "--methods", "none")
    assert code == 2 and "'--size'" in output and f"at most {largest} px" in output
    with pytest.raises(ValueError, match=f"between 1 and {largest} px"):
        benchmark_set(1, largest + 1)
    with pytest.raises(ValueError, match="at least 1 benchmark patch"):
        benchmark_set(0, 64)


# 11. the ablation's validation table: "–" before a run's first validation


def test_validation_table_shows_a_dash_before_the_first_validation():
    table = ablation.format_curves({"DR/s0": {500: 20.0, 1000: 21.5}}, 1000)
    assert "| DR/s0 | – | 20.00 | 20.00 | 21.50 |" in table and "nan" not in table
