"""``urd train``: the separation network (or the CEILNet baseline) from a TOML config."""

from __future__ import annotations

import dataclasses
import os
import shlex
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

from urd.cli.common import bad, refuse_weights_folder, run_guarded, usage, warn
from urd.core.progress import TerminalProgress

if TYPE_CHECKING:
    from separate.train import TrainConfig


def check_seed(value: Optional[int]) -> Optional[int]:
    """``--seed``: a usage error unless within the config's seed range (`separate.train.LIMITS`)."""
    if value is None:
        return value
    from separate.train import LIMITS

    allowed, expected = LIMITS["seed"]
    if not allowed(value):
        raise typer.BadParameter(f"expected {expected}, got {value}")
    return value


def train(
    config: Path = typer.Argument(..., help="TOML config (see configs/cpu.toml and configs/paper.toml)."),
    run_dir: Path = typer.Argument(..., help="Run folder: checkpoints, log.jsonl; an existing run resumes."),
    init: Optional[Path] = typer.Option(None, help="Start from these weights (e.g. the shipped ones) instead of scratch."),
    seed: Optional[int] = typer.Option(None, callback=check_seed, help="Override the config's seed (weight initialisation and training data), e.g. for a multi-seed ablation."),
) -> None:
    """Train the separation network (or the CEILNet baseline: configs/ceilnet.toml) on synthesized data (config file, checkpoints, resume; torchrun for DDP).

    The config's keys, with their units and defaults: docs/network.md, "Training your own".
    An existing run folder resumes from its last.pt (--init then only as the weights it started from).

    \b
    Example:
      urd train configs/cpu.toml runs/cpu
      urd train configs/paper.toml runs/paper --init separate/weights/urd-canonical-transposed.pt
    """
    from separate.precision import describe, resolve
    from separate.synthesis import training_data
    from separate.train import TrainConfig, train as train_run

    check_paths(config, run_dir, init)
    cfg = run_guarded(TrainConfig.from_toml, config)
    if seed is not None:
        cfg = dataclasses.replace(cfg, seed=seed)
    last = Path(run_dir) / "last.pt"
    own = Path(run_dir) / "config.toml"
    if not last.exists() and own.is_file() and own.samefile(config):
        raise usage(f"{config} is the config.toml of the run folder {run_dir}, which a new run there overwrites with "
                    "the config as used; copy it out of the folder, or name another run folder")
    typer.echo(f"precision: {describe(resolve(cfg.precision))}", err=True)
    data, missing = training_data(cfg.real_prob)
    if missing:
        warn(f"not found: {'; '.join(missing)}; the samples are {data} (the model card will say so)")
    bar = TerminalProgress()
    first: list[dict] = []                                   # this session's first record

    def show(record: dict) -> None:
        if not first:
            first.append(record)
        bar(record["step"], projected_steps(cfg.steps, cfg.max_minutes * 60, first[0], record), "train")
        if "psnr_t" in record:
            loss = f"loss {record['loss']:.5f}" if "loss" in record else "the --init weights"
            bar.break_line()
            typer.echo(f"step {record['step']}: {loss}, val PSNR T {record['psnr_t']:.2f} dB, R {record['psnr_r']:.2f} dB "
                       f"({record['wall_s'] / 60:.1f} min of training)")

    again = shlex.join(["urd", "train", str(config), str(run_dir)] + (["--seed", str(seed)] if seed is not None else [])
                       + (["--init", str(init)] if init is not None else []))
    if last.is_file():
        state = run_guarded(resume_point, Path(run_dir), cfg, init)
        if state["step"] >= cfg.steps:
            if os.environ.get("RANK", "0") == "0":
                typer.echo(f"run {run_dir} is already complete at step {state['step']} (steps = {cfg.steps} in {config}); "
                           f"for more steps, raise steps in {config} and run '{again}' again")
            return
        if os.environ.get("RANK", "0") == "0":
            typer.echo(f"resuming {run_dir} from step {state['step']} of {cfg.steps} ({Path(run_dir) / 'last.pt'}; "
                       f"{state.get('wall_s', 0.0) / 60:.1f} min trained so far)")

    def run() -> dict:
        try:
            return train_run(cfg, run_dir, init, progress=show)
        except KeyboardInterrupt as exc:
            exc.add_note(f"resume with: {again}")
            raise

    record = run_guarded(run)
    bar.close()
    if os.environ.get("RANK", "0") != "0":                   # under torchrun, rank 0 reports
        return
    if record["step"] < cfg.steps:                             # the loop ends early only at the time cap
        typer.echo(f"stopped at step {record['step']} of {cfg.steps}: the max_minutes cap ({cfg.max_minutes:g} min, "
                   f"set-up included) was reached; the same command resumes ('{again}'); "
                   f"checkpoints in {Path(run_dir).resolve()}")
    else:
        typer.echo(f"stopped at step {record['step']}; checkpoints in {Path(run_dir).resolve()}")


def check_paths(config: Path, run_dir: Path, init: Optional[Path]) -> None:
    """Usage errors (exit 2) naming CONFIG, RUN_DIR or --init when it is missing or of the wrong kind."""
    if config.is_dir():
        raise bad("CONFIG", f"{config} is a folder, expected a TOML file")
    if not config.exists():
        raise bad("CONFIG", f"{config}: no such file")
    if run_dir.exists() and not run_dir.is_dir():
        raise bad("RUN_DIR", f"{run_dir} is a file, expected a run folder")
    refuse_weights_folder(init, "--init", by_name=False)


def resume_point(run_dir: Path, cfg: "TrainConfig", init: Optional[Path]) -> dict:
    """The checkpoint ``run_dir/last.pt`` a run resumes from, read under the run's lock
    (`separate.train.run_lock`: TrainingError while another process trains it; under torchrun
    without it, as `separate.train.train` refuses a busy run on every rank), and checked to go on
    with the config ``cfg`` and ``init`` (`separate.train.check_resume`: TrainingError)."""
    from separate.train import check_resume, load_checkpoint, run_lock

    last = run_dir / "last.pt"
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        state = load_checkpoint(last)
    else:
        with run_lock(run_dir):
            state = load_checkpoint(last)
    check_resume(state, cfg, last, init)
    return state


def projected_steps(steps: int, cap_s: float, first: dict, record: dict) -> int:
    """The step a run will stop at: ``steps``, or fewer where its time cap (``cap_s`` seconds of
    this session; 0: none) comes first at the pace since this session's ``first`` record (both
    records hold ``step`` and ``wall_s``)."""
    session = record["wall_s"] - first["wall_s"]
    if cap_s <= 0 or session <= 0 or record["step"] <= first["step"]:
        return steps
    pace = (record["step"] - first["step"]) / session
    return min(steps, max(record["step"], round(record["step"] + pace * (cap_s - session))))
