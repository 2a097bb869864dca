"""Multi-seed ablation of the synthesis pipeline (paper §4, the table of Fig. 7).

The canonical network is trained on DR, DR+NRD and DR+NRD+LCG at an equal budget (the TOML
configs `PIPELINES` names, in ``configs/``), once per seed, and scored on the synthetic
benchmark (`separate.bench`, whose test data has every effect). Reported per pipeline: T̂ PSNR
per seed, their mean and spread, and the paired T̂ gains between pipelines trained with the
same seed, so that the order of the pipelines can be judged against the noise of one training run.

Runs live in ``runs_dir/<pipeline>-s<seed>`` (e.g. ``dr-nrd-s1``) (`urd train` folders: an unfinished one
resumes); each run's best checkpoint is exported as float16 weights with a model card. The budget
is the configs' step count unless ``steps`` overrides it for every run; another budget needs its own
runs folder (a run resumed with more steps would stretch its learning-rate schedule), and runs
started with another budget are refused (`check_budgets`).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from separate.bench import SEED, paired_gain, run_benchmark
from separate.bench_report import write_csv, write_text
from separate.plots import plot_bars, plot_lines
from separate.provenance import cpu_model, environment
from separate.train import TrainConfig, export_weights, load_checkpoint, train
from urd.core.errors import TrainingError
from urd.core.processes import process_pool

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
PIPELINES = {"DR": "ablation-dr", "DR+NRD": "ablation-dr-nrd", "DR+NRD+LCG": "ablation-dr-nrd-lcg"}


@dataclasses.dataclass(frozen=True)
class AblationRun:
    """One training run of the ablation: a pipeline's config trained with one seed."""

    pipeline: str
    seed: int
    config: Path
    folder: Path
    steps: int | None = None

    @property
    def label(self) -> str:
        """'PIPELINE/sSEED', its method name in the benchmark rows."""
        return f"{self.pipeline}/s{self.seed}"

    def train_config(self) -> TrainConfig:
        """The config file's settings with this run's seed and budget, one thread (runs go side by side)."""
        cfg = TrainConfig.from_toml(self.config)
        return dataclasses.replace(cfg, seed=self.seed, threads=1, steps=cfg.steps if self.steps is None else self.steps)

    def finished(self) -> bool:
        """Whether the folder holds a checkpoint at the config's last step."""
        last = self.folder / "last.pt"
        return last.exists() and load_checkpoint(last)["step"] >= self.train_config().steps


def ablation_runs(seeds: Sequence[int], runs_dir: Path, configs: Path = CONFIGS, steps: int | None = None) -> list[AblationRun]:
    """Every (pipeline, seed) run, of ``steps`` steps each (default: the configs'); ValueError
    unless there are at least two different seeds and ``steps`` is positive."""
    if len(set(seeds)) < 2 or any(s < 0 for s in seeds):
        raise ValueError(f"expected at least two different non-negative seeds (the spread between them is the point), got {list(seeds)}")
    if steps is not None and steps < 1:
        raise ValueError(f"expected at least 1 training step per run, got {steps}")
    missing = [f"{stem}.toml" for stem in PIPELINES.values() if not (Path(configs) / f"{stem}.toml").is_file()]
    if missing:
        raise ValueError(f"the ablation's training configs {', '.join(missing)} are not in {configs}: "
                         "run it from a source checkout of urd, which has them in configs/")
    return [AblationRun(pipeline, seed, Path(configs) / f"{stem}.toml", Path(runs_dir) / f"{stem.removeprefix('ablation-')}-s{seed}", steps)
            for pipeline, stem in PIPELINES.items() for seed in dict.fromkeys(seeds)]


def check_budgets(runs: Sequence[AblationRun]) -> None:
    """TrainingError naming the runs' folder and the step counts where a run there (finished or
    not) was started with another budget than its own: resuming it would stretch (or cut) its
    learning-rate schedule, and a finished one would be scored as if trained for this budget."""
    started: dict[int, list[str]] = {}
    for run in runs:
        last = run.folder / "last.pt"
        if last.is_file():
            steps = load_checkpoint(last)["train_config"]["steps"]
            if steps != run.train_config().steps:
                started.setdefault(steps, []).append(run.folder.name)
    if started:
        budget = runs[0].train_config().steps
        found = "; ".join(f"{', '.join(names)}: {steps} steps" for steps, names in sorted(started.items()))
        theirs = (f", or --runs {runs[0].folder.parent} --steps {next(iter(started))} to go on with these"
                  if len(started) == 1 else "")
        raise TrainingError(f"the runs in {runs[0].folder.parent} were started with another budget ({found}), not the {budget} steps "
                            f"asked for: resuming them would change their learning-rate schedule; choose a new runs "
                            f"folder (--runs) for {budget} steps{theirs}")


def _train_run(run: AblationRun) -> None:
    """Train or resume one run (in a worker process), its log lines in ``<run folder>.log``."""
    cfg = run.train_config()
    with open(run.folder.with_suffix(".log"), "a") as log:
        def show(record: dict) -> None:
            if "psnr_t" in record:
                log.write(f"step {record['step']}/{cfg.steps}: val PSNR T {record['psnr_t']:.2f} dB, R {record['psnr_r']:.2f} dB\n")
                log.flush()

        train(cfg, run.folder, progress=show)


def train_missing(runs: Sequence[AblationRun], jobs: int, progress: Callable[[int, int], None] | None = None) -> list[AblationRun]:
    """Train the runs that are missing or unfinished, ``jobs`` processes at a time (one thread
    each); returns them. ``progress`` is called with (runs done, runs to train)."""
    if jobs < 1:
        raise ValueError(f"expected at least 1 job, got {jobs}")
    todo = [run for run in runs if not run.finished()]
    for run in todo:
        run.folder.parent.mkdir(parents=True, exist_ok=True)
    if todo:
        try:
            with process_pool(jobs) as pool:             # spawned workers; an interrupt kills them at once
                futures = {pool.submit(_train_run, run): run for run in todo}
                for done, future in enumerate(concurrent.futures.as_completed(futures), 1):
                    try:
                        future.result()
                    except Exception as exc:              # noqa: BLE001 - name the run, stop the others
                        raise TrainingError(f"ablation run {futures[future].label} ({futures[future].folder}) failed: {exc}") from exc
                    if progress:
                        progress(done, len(todo))
        except KeyboardInterrupt as exc:
            exc.add_note(f"every ablation run resumes from its last checkpoint (in {todo[0].folder.parent}) when the "
                         "same command runs again")
            raise
    return todo


def score(runs: Sequence[AblationRun], weights_dir: Path, count: int, size: int) -> list[dict]:
    """Export each run's best checkpoint into ``weights_dir`` (float16 + card) and score it on
    the benchmark (``count`` patches of ``size``²); one `run_benchmark` row per run."""
    device = (f"{torch.cuda.get_device_name()}, runs side by side" if torch.cuda.is_available() else
              f"{cpu_model()} (the machine that exported it), one thread per run, runs side by side")
    methods = []
    for run in runs:
        target = Path(weights_dir) / f"{run.folder.name}.pt"
        export_weights(run.folder / "best.pt", target, device, note=f"ablation {run.label} (separate.ablation); not shipped")
        methods.append(f"{run.label}={target}")
    return run_benchmark(methods, count, size)


def validation_curve(run: AblationRun) -> dict[int, float]:
    """A run's validation T̂ PSNR (dB) by training step, from its ``log.jsonl`` (a step logged
    twice, after a resume, keeps its last value)."""
    records = [json.loads(line) for line in (run.folder / "log.jsonl").read_text().splitlines() if line.strip()]
    return {r["step"]: r["psnr_t"] for r in records if "psnr_t" in r}


def curve_at(curve: dict[int, float], step: int) -> float:
    """The last validation figure logged at or before ``step`` (NaN if none)."""
    logged = [s for s in curve if s <= step]
    return curve[max(logged)] if logged else float("nan")


def format_curves(curves: dict[str, dict[int, float]], budget: int) -> str:
    """Markdown: each run's validation T̂ PSNR (``curves``: run label → `validation_curve`) at a
    quarter, half, three quarters and all of the budget, to judge how far from convergence the runs are
    ("–" before a run's first validation)."""
    marks = [budget * k // 4 for k in (1, 2, 3, 4)]
    lines = ["Validation T̂ PSNR (dB) during training (the runs' own validation set: bsds500/val, full pipeline), "
             "by step:", "", "| run | " + " | ".join(str(m) for m in marks) + " |", "|---|" + "---|" * len(marks)]
    for label, curve in curves.items():
        figures = [curve_at(curve, m) for m in marks]
        lines.append(f"| {label} | " + " | ".join("–" if np.isnan(x) else f"{x:.2f}" for x in figures) + " |")
    return "\n".join(lines) + "\n"


def format_ablation(runs: Sequence[AblationRun], rows: list[dict], header: str) -> str:
    """The Markdown report: per-pipeline T̂ PSNR per seed, mean, spread; paired gains between
    the pipelines of one seed."""
    by_label = {r["method"]: r for r in rows}
    seeds = list(dict.fromkeys(run.seed for run in runs))
    val = {run.label: load_checkpoint(run.folder / "best.pt")["val"]["psnr_t"] for run in runs}

    def figures(pipeline: str, key: str) -> list[float]:
        return [by_label[f"{pipeline}/s{s}"][key] for s in seeds]

    lines = [header, "", "| pipeline | " + " | ".join(f"T PSNR s{s}" for s in seeds)
             + " | T PSNR mean | seed spread | R PSNR mean | T SSIM mean | val T PSNR mean |",
             "|---|" + "---|" * (len(seeds) + 5)]
    for pipeline in PIPELINES:
        t = figures(pipeline, "psnr_t")
        lines.append(f"| {pipeline} | " + " | ".join(f"{x:.2f}" for x in t) + f" | {np.mean(t):.2f} | {max(t) - min(t):.2f} | "
                     f"{np.mean(figures(pipeline, 'psnr_r')):.2f} | {np.mean(figures(pipeline, 'ssim_t')):.3f} | "
                     f"{np.mean([val[f'{pipeline}/s{s}'] for s in seeds]):.2f} |")
    lines += ["", "Paired T̂ PSNR gains between pipelines trained with the same seed (dB; mean over patches, "
              "95% bootstrap interval):", "",
              "| comparison | " + " | ".join(f"seed {s}" for s in seeds) + " |", "|---|" + "---|" * len(seeds)]
    names = list(PIPELINES)
    for a, b in ((names[1], names[0]), (names[2], names[1]), (names[2], names[0])):
        cells = []
        for s in seeds:
            g = paired_gain(rows, f"{a}/s{s}", f"{b}/s{s}")
            cells.append(f"{g['mean']:+.2f} ({g['ci95'][0]:+.2f} to {g['ci95'][1]:+.2f})")
        lines.append(f"| {a} − {b} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run_ablation(out_dir: Path, runs_dir: Path, seeds: Sequence[int] = (0, 1), jobs: int = 2, count: int = 64,
                 size: int = 256, configs: Path = CONFIGS, progress: Callable[[int, int], None] | None = None,
                 command: str | None = None, steps: int | None = None) -> dict:
    """Train what is missing (``steps`` per run, default the configs'; TrainingError where a run
    in ``runs_dir`` was started with another budget, `check_budgets`), score every run, and
    write ``out_dir``/ablation.md, .csv, .png and ``out_dir``/weights; returns
    {"files": [...], "trained": [run folder names], "rows": [...]}."""
    runs = ablation_runs(seeds, runs_dir, configs, steps)
    check_budgets(runs)
    trained = train_missing(runs, jobs, progress)
    out_dir = Path(out_dir)
    started = time.perf_counter()
    rows = score(runs, out_dir / "weights", count, size)
    env = environment(command)
    budget = runs[0].train_config().steps
    header = (f"# Ablation of the synthesis pipeline, {len(set(seeds))} seeds\n\n"
              f"Command: `{env['command']}` (commit {env['commit']}, {env['date']}, {env['cpu']}). Each run: "
              f"`{runs[0].config.parent.name}/ablation-*.toml` with its seed ({budget} steps), scored at its best-validation "
              f"checkpoint; benchmark: {count} patches of {size}² (seed {SEED}, full pipeline, reference auto), scored in "
              f"{time.perf_counter() - started:.0f} s. Weights and cards: `weights/` (not shipped).")
    curves = {run.label: validation_curve(run) for run in runs}
    write_text(out_dir / "ablation.md", format_ablation(runs, rows, header) + "\n" + format_curves(curves, budget))
    by_label = {r["method"]: r for r in rows}
    write_csv(out_dir / "ablation.csv", ["pipeline", "seed", "rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r", "ssim_r"],
              [[run.pipeline, run.seed] + [by_label[run.label][k] for k in ("rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r", "ssim_r")]
               for run in runs])
    seeds = list(dict.fromkeys(seeds))
    plot_bars(out_dir / "ablation.png", list(PIPELINES),
              {f"seed {s}": [by_label[f"{p}/s{s}"]["psnr_t"] for p in PIPELINES] for s in seeds},
              "Ablation: T PSNR on the synthetic benchmark", "T PSNR (dB)", "training pipeline")
    steps = sorted({step for curve in curves.values() for step in curve})
    every = -(-len(steps) // 12)                                        # at most 12 step labels
    plot_lines(out_dir / "ablation-curves.png", [str(step) if i % every == 0 else "" for i, step in enumerate(steps)],
               {label.replace("/", " "): [curve.get(step, float("nan")) for step in steps] for label, curve in curves.items()},
               "Ablation: validation T PSNR during training", "training step", "val T PSNR (dB)")
    files = [out_dir / name for name in ("ablation.md", "ablation.csv", "ablation.png", "ablation-curves.png")]
    return {"files": files, "trained": [run.folder.name for run in trained], "rows": rows}
