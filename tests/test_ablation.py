"""The multi-seed pipeline ablation (`urd bench --ablation`) on tiny configs, end to end."""

import csv
import json
import math
import re

import pytest

from separate.ablation import PIPELINES, ablation_runs, curve_at, run_ablation, validation_curve

TINY = 'width = 4\npatch = 32\nbatch = 2\nmicro_batch = 2\nsteps = 2\nval_samples = 4\nval_every = 2\nprecision = "fp32"\nthreads = 1\npipeline = "{}"\n'


def tiny_configs(folder):
    folder.mkdir()
    for pipeline, stem in PIPELINES.items():
        (folder / f"{stem}.toml").write_text(TINY.format(pipeline))
    return folder


def test_ablation_needs_two_seeds(tmp_path):
    with pytest.raises(ValueError, match="at least two different"):
        ablation_runs([3, 3], tmp_path)
    names = [run.folder.name for run in ablation_runs([0, 1], tmp_path)]
    assert names == ["dr-s0", "dr-s1", "dr-nrd-s0", "dr-nrd-s1", "dr-nrd-lcg-s0", "dr-nrd-lcg-s1"]


def test_ablation_budget_is_the_configs_unless_steps_overrides_it(tmp_path):
    configs = tiny_configs(tmp_path / "configs")
    assert {run.train_config().steps for run in ablation_runs([0, 1], tmp_path, configs)} == {2}
    longer = ablation_runs([0, 1], tmp_path, configs, steps=7)
    assert {(run.train_config().steps, run.train_config().threads) for run in longer} == {(7, 1)}
    assert [run.train_config().seed for run in longer] == [0, 1] * 3
    with pytest.raises(ValueError, match="at least 1 training step"):
        ablation_runs([0, 1], tmp_path, configs, steps=0)


@pytest.mark.slow
def test_ablation_trains_scores_and_resumes_without_retraining(tmp_path):
    configs = tiny_configs(tmp_path / "configs")
    calls = []
    result = run_ablation(tmp_path / "out", tmp_path / "runs", (0, 1), jobs=2, count=3, size=64, configs=configs,
                          progress=lambda done, total: calls.append((done, total)))
    assert sorted(result["trained"]) == sorted(run.folder.name for run in ablation_runs([0, 1], tmp_path / "runs"))
    assert calls[-1] == (6, 6)
    table = (tmp_path / "out" / "ablation.md").read_text()
    for pipeline in PIPELINES:
        assert re.search(rf"^\| {re.escape(pipeline)} \| \d+\.\d\d \| \d+\.\d\d \| \d+\.\d\d \| \d+\.\d\d \|", table, re.M), table
    for comparison in ("DR+NRD − DR", "DR+NRD+LCG − DR+NRD", "DR+NRD+LCG − DR"):
        cell = r"[+-]\d+\.\d\d \([+-]\d+\.\d\d to [+-]\d+\.\d\d\)"
        assert re.search(rf"^\| {re.escape(comparison)} \| {cell} \| {cell} \|$", table, re.M), table
    curves = table.split("by step:")[1]
    for run in ablation_runs([0, 1], tmp_path / "runs"):
        assert re.search(rf"^\| {re.escape(run.label)} \|.* \| \d+\.\d\d \|$", curves, re.M), curves
    assert (tmp_path / "out" / "ablation-curves.png").stat().st_size > 0
    rows = list(csv.DictReader(open(tmp_path / "out" / "ablation.csv")))
    assert [(r["pipeline"], r["seed"]) for r in rows] == [(p, s) for p in PIPELINES for s in ("0", "1")]
    cards = sorted((tmp_path / "out" / "weights").glob("*.json"))
    assert len(cards) == 6 and json.loads(cards[0].read_text())["training"]["steps"] == 2
    seeds = {json.loads(c.read_text())["training"]["config"]["seed"] for c in cards}
    assert seeds == {0, 1}
    again = run_ablation(tmp_path / "out", tmp_path / "runs", (0, 1), jobs=2, count=3, size=64, configs=configs)
    assert again["trained"] == []
    assert [r["psnr_t"] for r in again["rows"]] == [r["psnr_t"] for r in result["rows"]]


def test_validation_curve_keeps_a_resumed_steps_last_figure(tmp_path):
    run = ablation_runs([0, 1], tmp_path)[0]
    run.folder.mkdir(parents=True)
    records = [{"step": 10, "loss": 1.0}, {"step": 500, "psnr_t": 20.0}, {"step": 1000, "psnr_t": 21.0},
               {"step": 1000, "psnr_t": 22.0}]
    (run.folder / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    curve = validation_curve(run)
    assert curve == {500: 20.0, 1000: 22.0}
    assert curve_at(curve, 999) == 20.0 and curve_at(curve, 1000) == 22.0 and math.isnan(curve_at(curve, 499))
