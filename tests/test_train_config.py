"""`urd train`'s config checks and its stops: bad settings refused on load naming the file and the
key, Ctrl-C keeping the step reached, a diverging loss stopped, finished and locked runs."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

import urd.cli.train
from separate.model import SeparationNet
from separate.train import TrainConfig, load_checkpoint, rank_batches, run_lock
from urd.cli import app

ROOT = Path(__file__).resolve().parents[1]


TINY = ('width = 4\npatch = 32\nbatch = 2\nmicro_batch = 2\nsteps = 2\nval_samples = 2\nval_every = 100\n'
        'ckpt_every = 100\nprecision = "fp32"\nthreads = 1\n')


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def tiny_config(folder: Path, **changes: str) -> Path:
    """A tiny config file in ``folder``, its settings replaced or added by ``changes`` (TOML values)."""
    lines = dict(line.split(" = ", 1) for line in TINY.splitlines())
    config = folder / "tiny.toml"
    config.write_text("".join(f"{key} = {value}\n" for key, value in {**lines, **changes}.items()))
    return config


@pytest.mark.parametrize("key, value, expected", [
    ("precision", '"fp16"', "expected precision in"),
    ("val_every", "0", "expected val_every at least 1"),
    ("ckpt_every", "0", "expected ckpt_every at least 1"),
    ("patch", "0", "expected patch a positive multiple of 8"),
    ("patch", "33", "expected patch a positive multiple of 8"),
    ("patch", "[64]", "expected patch a whole number"),
    ("width", "0", "expected width at least 1 and at most 128"),
    ("width", "700", "expected width at least 1 and at most 128"),
    ("blocks", "25", "expected blocks at least 1 and at most 24"),
    ("val_samples", "0", "expected val_samples at least 1"),
    ("threads", "-2", "expected threads at least 0"),
    ("lr", '"abc"', "expected lr a number"),
    ("lr", "-1e-3", "expected lr above 0"),
    ("lr_min", "1.0", "expected lr_min at most lr"),
    ("batch", "0", "expected batch at least 1"),
    ("batch", "3", "expected batch a multiple of micro_batch"),
    ("steps", "0", "expected steps at least 1"),
    ("steps", "-5", "expected steps at least 1"),
    ("steps", "1.5", "expected steps a whole number"),
    ("no_glass_prob", "1.5", "expected no_glass_prob between 0 and 1"),
    ("strength", "[2.0, 0.5]", "expected strength"),
    ("pipeline", '"DR+FOO"', "pipeline: expected one of"),
])
def test_a_bad_setting_is_one_error_line_naming_the_file_and_key_and_makes_no_run_folder(tmp_path, monkeypatch, key,
                                                                                         value, expected):
    import separate.train as train_module

    monkeypatch.setattr(train_module, "_train", lambda *args: pytest.fail("trained with a bad setting"))
    config = tiny_config(tmp_path, **{key: value})
    out = invoke("train", config, tmp_path / "run")
    assert out.exit_code == 1, out.output
    assert f"Error: {config}: {expected}" in out.output
    assert "Traceback" not in out.output and len(out.output.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_a_toml_syntax_error_names_the_file(tmp_path):
    config = tmp_path / "broken.toml"
    config.write_text(TINY + "seed = = 3\n")
    out = invoke("train", config, tmp_path / "run")
    assert out.exit_code == 1 and f"Error: {config}: not a valid TOML file" in out.output
    assert not (tmp_path / "run").exists()


def test_the_shipped_configs_pass_the_checks_and_floats_read_as_floats(tmp_path):
    configs = sorted((ROOT / "configs").glob("*.toml"))
    assert len(configs) >= 3
    for config in configs:
        TrainConfig.from_toml(config)
    cfg = TrainConfig.from_toml(tiny_config(tmp_path, lr="1", strength="[1, 2]"))
    assert cfg.lr == 1.0 and isinstance(cfg.lr, float) and cfg.strength == (1.0, 2.0)


def test_ctrl_c_keeps_the_step_reached_and_says_how_to_resume(tmp_path, monkeypatch):
    class Interrupting(urd.cli.train.TerminalProgress):
        def __call__(self, step, total, label):
            if step == 3:
                raise KeyboardInterrupt

    monkeypatch.setattr(urd.cli.train, "TerminalProgress", Interrupting)
    config, run = tiny_config(tmp_path, steps="10"), tmp_path / "run"
    out = invoke("train", config, run)
    assert out.exit_code == 130, out.output
    assert f"{run / 'last.pt'} keeps step 3" in out.output and f"resume with: urd train {config} {run}" in out.output
    assert load_checkpoint(run / "last.pt")["step"] == 3
    assert not list(run.glob("*.tmp*"))


def test_a_diverging_loss_stops_at_its_step_and_keeps_the_last_finite_checkpoint(tmp_path, monkeypatch):
    calls = []
    loss = SeparationNet.loss

    def diverging(outputs, r, t, kind="l2"):
        calls.append(kind)
        return loss(outputs, r, t, kind) * (math.nan if len(calls) >= 4 else 1.0)

    monkeypatch.setattr(SeparationNet, "loss", staticmethod(diverging))
    run = tmp_path / "run"
    out = invoke("train", tiny_config(tmp_path, steps="10", ckpt_every="2"), run)
    assert out.exit_code == 1, out.output
    assert "not finite at step 4" in out.output and "keeps step 2" in out.output and "lower lr" in out.output
    state = load_checkpoint(run / "last.pt")
    assert state["step"] == 2 and all(torch.isfinite(v).all() for v in state["model"].values())


def test_a_finished_run_says_it_is_complete_and_how_to_train_further(tmp_path):
    config, run = tiny_config(tmp_path), tmp_path / "run"
    assert invoke("train", config, run).exit_code == 0
    again = invoke("train", config, run)
    assert again.exit_code == 0, again.output
    assert f"run {run} is already complete at step 2" in again.output and "raise steps" in again.output
    assert "None" not in again.output and "resuming" not in again.output


def test_a_locked_run_is_refused_before_it_says_it_resumes(tmp_path):
    config, run = tiny_config(tmp_path, steps="1"), tmp_path / "run"
    assert invoke("train", config, run).exit_code == 0
    config.write_text(config.read_text().replace("steps = 1", "steps = 3"))
    with run_lock(run):
        out = invoke("train", config, run)
    assert out.exit_code == 1 and "being trained by another process" in out.output
    assert "resuming" not in out.output


def test_the_help_example_names_the_weights_of_the_paper_config():
    out = invoke("train", "--help")
    paper = TrainConfig.from_toml(ROOT / "configs/paper.toml")
    weights = Path("separate/weights/urd-canonical-transposed.pt")
    assert f"--init {weights}" in out.output
    assert load_checkpoint(ROOT / weights)["model_config"].get("upsample", "transposed") == paper.upsample


def test_training_without_the_shared_photos_warns_and_its_model_card_says_what_it_used(tmp_path, monkeypatch, request):
    import separate.synthesis as synthesis
    from separate.train import export_weights

    monkeypatch.setattr(synthesis, "SHARED_NATURAL", tmp_path / "absent")
    monkeypatch.setattr(synthesis.samples, "no_glass_captures", lambda split=None: [])
    for pool in (synthesis.default_pool, synthesis.real_pool):      # the pools are read once per process:
        pool.cache_clear()                                          # not the ones without the data, for later tests
        request.addfinalizer(pool.cache_clear)
    out = invoke("train", tiny_config(tmp_path, real_prob="0.5"), tmp_path / "run")
    assert out.exit_code == 0, out.output
    assert "not found: " in out.output and "../shared/data/natural" in out.output and "../shared/data/polarization" in out.output
    card = export_weights(tmp_path / "run" / "best.pt", tmp_path / "w.pt", "cpu")
    assert card["training"]["data"].startswith("synthesized from scikit-image's bundled photos, pipeline")


@pytest.mark.slow
def test_ctrl_c_during_the_optimizer_update_takes_effect_after_it(tmp_path, monkeypatch):
    """A checkpoint holds whole updates: Ctrl-C arriving inside ``optim.step`` stops the run after
    it, and last.pt's weights are the update of the step it records."""
    import signal

    calls = []
    real_step = torch.optim.Adam.step

    def interrupted_step(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            signal.raise_signal(signal.SIGINT)          # to this thread (os.kill may reach another, later); between updates
        return real_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", interrupted_step)
    config, run = tiny_config(tmp_path, steps="10"), tmp_path / "run"
    out = invoke("train", config, run)
    assert out.exit_code == 130, out.output
    state = load_checkpoint(run / "last.pt")
    assert state["step"] == 2 and len(calls) == 2
    adam_steps = {float(s["step"]) for s in state["optim"]["state"].values()}
    assert adam_steps == {2.0}                            # every parameter updated as often as the step says


@pytest.mark.parametrize("batch, micro, world, expected", [
    (32, 8, 1, (32, 8)), (32, 8, 2, (16, 8)), (16, 8, 4, (4, 4)), (12, 8, 2, (6, 6))])
def test_a_step_splits_into_whole_micro_batches_per_rank(batch, micro, world, expected):
    assert rank_batches(batch, micro, world) == expected


@pytest.mark.parametrize("batch, micro, world", [(32, 8, 3), (24, 8, 2), (2, 8, 4)])
def test_a_batch_that_does_not_split_over_the_ranks_is_refused(batch, micro, world):
    with pytest.raises(ValueError, match=f"batch {batch} does not split into {world} rank"):
        rank_batches(batch, micro, world)


def test_a_run_from_init_weights_stopped_before_its_first_step_resumes_with_the_command_it_printed(tmp_path, monkeypatch):
    import separate.train as train_module

    config = tiny_config(tmp_path)
    assert invoke("train", config, tmp_path / "start").exit_code == 0
    weights, run = tmp_path / "start" / "best.pt", tmp_path / "run"
    real_batches = train_module.synthesis_batches

    def stopped(*args, **kwargs):                       # Ctrl-C once the step-0 validation wrote best.pt
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "synthesis_batches", stopped)
    out = invoke("train", config, run, "--init", weights)
    assert out.exit_code == 130 and (run / "best.pt").exists(), out.output
    assert load_checkpoint(run / "last.pt")["step"] == 0
    (run / ".last.k2x9.tmp.pt").write_bytes(b"")            # what a kill during a checkpoint's writing leaves
    monkeypatch.setattr(train_module, "synthesis_batches", real_batches)
    again = invoke("train", config, run, "--init", weights)
    assert again.exit_code == 0, again.output
    assert load_checkpoint(run / "last.pt")["step"] == 2 and not list(run.glob(".last.*"))


def test_an_empty_config_file_is_refused_rather_than_training_on_every_default(tmp_path, monkeypatch):
    import separate.train as train_module

    monkeypatch.setattr(train_module, "_train", lambda *args: pytest.fail("trained on every default"))
    (tmp_path / "empty.toml").write_text("# nothing set\n")
    out = invoke("train", tmp_path / "empty.toml", tmp_path / "run")
    assert out.exit_code == 1 and "empty.toml: no settings" in out.output, out.output      # as every bad config
    assert not (tmp_path / "run").exists()
