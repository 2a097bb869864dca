"""`urd train`'s answers to what a tester gave it: settings out of range, run folders that are
not resumable runs, files that are not weights, missing paths, --init on a resumed run, failed
starts, the time cap, and the config keys' table in docs/network.md."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from separate.infer import load_model
from separate.networks import build_model
from separate.train import MAX_SEED, TrainConfig, load_checkpoint, model_config, save_checkpoint, train
from urd.cli import app
from urd.core.errors import TrainingError, WeightsError

TINY = {"width": "4", "patch": "32", "batch": "2", "micro_batch": "2", "steps": "2", "val_samples": "4",
        "val_every": "100", "ckpt_every": "100", "precision": '"fp32"', "threads": "1"}
DOCS = Path(__file__).resolve().parent.parent / "docs" / "network.md"


class Thing:
    """An object of no urd type, as a file from elsewhere may hold."""


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def tiny_config(folder: Path, name: str = "tiny.toml", **changes: str) -> Path:
    """A tiny config file ``folder/name``, its settings replaced or added by ``changes`` (TOML values)."""
    config = folder / name
    config.write_text("".join(f"{key} = {value}\n" for key, value in {**TINY, **changes}.items()))
    return config


def error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("Error:")]


def fake_run(folder: Path, config: Path, step: int = 1, init: dict | None = None) -> Path:
    """A run folder as `train` leaves it at ``step`` (last.pt of an untrained network), without training."""
    cfg = TrainConfig.from_toml(config)
    model = build_model(model_config(cfg))
    optim = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    folder.mkdir()
    save_checkpoint(folder / "last.pt", model, optim, step, cfg, {"best_psnr_t": 10.0, "wall_s": 1.0, "init": init})
    (folder / "config.toml").write_text(cfg.to_toml())
    return folder


def tiny_weights(path: Path, config: Path) -> Path:
    """A weights file (``{"model", "model_config"}``) of the tiny config's untrained network."""
    model = build_model(model_config(TrainConfig.from_toml(config)))
    torch.save({"model": model.state_dict(), "model_config": model.config()}, path)
    return path


@pytest.mark.parametrize("key, value, expected", [
    ("threads", "100000", "expected threads at least 0 and at most 256"),
    ("seed", "99999999999999999999", f"expected seed at least 0 and at most {MAX_SEED}"),
    ("seed", "-1", f"expected seed at least 0 and at most {MAX_SEED}"),
])
def test_threads_and_seed_out_of_range_are_one_config_error(tmp_path, key, value, expected):
    config = tiny_config(tmp_path, **{key: value})
    out = invoke("train", config, tmp_path / "run")
    assert out.exit_code == 1, out.output
    assert out.output.startswith(f"Error: {config}: {expected}") and len(out.output.strip().splitlines()) == 1
    assert "Overflow" not in out.output and not (tmp_path / "run").exists()


def test_the_largest_seed_is_accepted_and_a_larger_seed_option_is_a_usage_error(tmp_path):
    assert TrainConfig.from_toml(tiny_config(tmp_path, seed=str(MAX_SEED))).seed == MAX_SEED
    out = invoke("train", tiny_config(tmp_path), tmp_path / "run", "--seed", "99999999999999999999")
    assert out.exit_code == 2, out.output
    assert "'--seed': expected at least 0 and at most 9223372036854775807" in out.output and "Overflow" not in out.output
    assert not (tmp_path / "run").exists()


def test_a_run_folder_without_last_pt_is_refused_and_left_as_it_was(tmp_path):
    run = tmp_path / "copied-run"
    run.mkdir()
    (run / "best.pt").write_bytes(b"the best weights of an earlier run")
    (run / "log.jsonl").write_text('{"step": 10}\n')
    out = invoke("train", tiny_config(tmp_path), run)
    assert out.exit_code == 1, out.output
    [line] = error_lines(out.output)
    assert str(run) in line and "no last.pt" in line and "use a new run folder" in line
    assert (run / "best.pt").read_bytes() == b"the best weights of an earlier run"
    assert (run / "log.jsonl").read_text() == '{"step": 10}\n' and not (run / "config.toml").exists()


def test_a_config_that_is_the_run_folders_own_config_toml_is_not_overwritten(tmp_path):
    run = tmp_path / "mycfg"
    run.mkdir()
    config = tiny_config(run, "config.toml")
    text = config.read_text()
    out = invoke("train", config, run)
    assert out.exit_code == 2, out.output
    assert "is the config.toml of the run folder" in out.output and "another run folder" in out.output
    assert config.read_text() == text and sorted(p.name for p in run.iterdir()) == ["config.toml"]


@pytest.mark.parametrize("name, content", [("cfg.toml", b"width = 4\n"), ("card.json", b'{"a": 1}\n'),
                                           ("empty.pt", b"")])
def test_a_file_that_is_not_weights_is_named_in_one_line_without_torch_advice(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    for load in (load_model, load_checkpoint):
        with pytest.raises(WeightsError) as caught:
            load(path)
        message = str(caught.value)
        assert message.startswith(f"{path} is not a urd weights or checkpoint file (")
        assert "\n" not in message and "weights_only" not in message and "arbitrary code" not in message


def test_files_of_torch_that_are_not_urd_weights_say_what_they_hold(tmp_path):
    torch.save(torch.zeros(3), tmp_path / "tensor.pt")
    with pytest.raises(WeightsError, match=r"tensor.pt is not a urd weights or checkpoint file \(it holds a Tensor"):
        load_model(tmp_path / "tensor.pt")
    torch.save({"model": {"w": torch.zeros(1)}, "extra": Thing()}, tmp_path / "obj.pt")
    with pytest.raises(WeightsError, match=r"obj.pt is not a urd weights or checkpoint file \(it holds a Python object"):
        load_checkpoint(tmp_path / "obj.pt")


@pytest.mark.slow
def test_a_toml_given_as_init_is_one_error_line_and_leaves_no_run_folder(tmp_path):
    config = tiny_config(tmp_path)
    out = invoke("train", config, tmp_path / "new" / "run", "--init", config)
    assert out.exit_code == 1, out.output
    assert error_lines(out.output) == [f"Error: {config} is not a urd weights or checkpoint file "
                                       "(a text file, not one written by torch.save)"]
    assert "Traceback" not in out.output and not (tmp_path / "new").exists()


def test_a_failed_start_in_an_existing_folder_removes_only_what_it_wrote(tmp_path, monkeypatch):
    import separate.train

    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("mine")
    out = invoke("train", tiny_config(tmp_path), run, "--init", tiny_config(tmp_path, "other.toml"))
    assert out.exit_code == 1, out.output
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt"]

    def no_validation(cfg):                         # fails after config.toml is written, before anything is logged
        assert (run / "config.toml").is_file()
        raise OSError("no validation photos")

    monkeypatch.setattr(separate.train, "validation_set", no_validation)
    out = invoke("train", tiny_config(tmp_path), run)
    assert out.exit_code != 0 and sorted(p.name for p in run.iterdir()) == ["notes.txt"], out.output


@pytest.mark.parametrize("args, expected", [
    (["missing.toml", "run"], "Invalid value for 'CONFIG': {t}/missing.toml: no such file"),
    (["folder", "run"], "Invalid value for 'CONFIG': {t}/folder is a folder, expected a TOML file"),
    (["tiny.toml", "afile"], "Invalid value for 'RUN_DIR': {t}/afile is a file, expected a run folder"),
    (["tiny.toml", "run", "--init", "missing.pt"], "Invalid value for '--init': {t}/missing.pt: no such file"),
    (["tiny.toml", "run", "--init", "folder"], "Invalid value for '--init': {t}/folder is a folder, expected a weights"),
])
def test_missing_paths_and_paths_of_the_wrong_kind_are_usage_errors_naming_them(tmp_path, args, expected):
    tiny_config(tmp_path)
    (tmp_path / "folder").mkdir()
    (tmp_path / "afile").write_text("")
    out = invoke("train", *[tmp_path / a if not a.startswith("--") else a for a in args])
    assert out.exit_code == 2, out.output
    assert expected.format(t=tmp_path) in out.output and "Errno" not in out.output
    assert not (tmp_path / "run").exists()


def test_the_library_names_a_run_folder_that_is_a_file_and_weights_that_are_a_folder(tmp_path):
    (tmp_path / "afile").write_text("")
    with pytest.raises(TrainingError, match="afile is a file, expected a run folder"):
        train(TrainConfig(), tmp_path / "afile")
    (tmp_path / "run1").mkdir()
    (tmp_path / "run1" / "best.pt").write_bytes(b"")
    with pytest.raises(WeightsError, match=r"run1 is a folder, expected a weights or checkpoint file \(a run folder"):
        load_model(tmp_path / "run1")


def test_init_on_a_run_that_resumes_is_refused_before_it_says_it_resumes(tmp_path):
    config = tiny_config(tmp_path, steps="5")
    run = fake_run(tmp_path / "run", config, step=3)
    weights = tiny_weights(tmp_path / "w.pt", config)
    out = invoke("train", config, run, "--init", weights)
    assert out.exit_code == 1, out.output
    assert error_lines(out.output) == [f"Error: {run} already holds a run at step 3 (started from scratch): --init "
                                       "applies to a new run; use a new run folder"]
    assert "resuming" not in out.output and load_checkpoint(run / "last.pt")["step"] == 3


def test_a_resume_with_another_width_says_use_a_new_run_folder(tmp_path):
    run = fake_run(tmp_path / "run", tiny_config(tmp_path, steps="5"), step=3)
    out = invoke("train", tiny_config(tmp_path, "wider.toml", steps="5", width="8"), run)
    assert out.exit_code == 1, out.output
    [line] = error_lines(out.output)
    assert "width 4 → 8" in line and line.endswith("use a new run folder")
    assert "resize_upsampling" not in out.output and "resuming" not in out.output


@pytest.mark.slow
def test_the_time_cap_says_so_and_the_same_command_with_init_resumes(tmp_path):
    config = tiny_config(tmp_path, steps="4", max_minutes="0.0001")
    weights = tiny_weights(tmp_path / "w.pt", config)
    run = tmp_path / "run"
    first = invoke("train", config, run, "--init", weights)
    assert first.exit_code == 0, first.output
    assert ("stopped at step 1 of 4: the max_minutes cap (0.0001 min, set-up included) was reached; "
            f"the same command resumes ('urd train {config} {run} --init {weights}')") in first.output
    again = invoke("train", config, run, "--init", weights)
    assert again.exit_code == 0, again.output
    assert f"resuming {run} from step 1 of 4" in again.output and "stopped at step 2 of 4: the max_minutes cap" in again.output
    assert load_checkpoint(run / "last.pt")["init"]["path"] == str(weights)


def test_the_docs_table_lists_every_config_key_with_its_default_and_help_points_to_it():
    rows = re.findall(r"^\| (`[a-z_0-9]+`(?:, `[a-z_0-9]+`)*) \| [^|]+ \| ([^|]+) \|", DOCS.read_text(), re.M)
    documented = {}
    for keys, default in rows:
        for key in re.findall(r"`([a-z_0-9]+)`", keys):
            documented[key] = json.loads(default.strip().strip("`").replace(" ", ""))
    fields = {f.name: f.default for f in dataclasses.fields(TrainConfig)}
    assert set(documented) == set(fields)
    for key, default in fields.items():
        assert documented[key] == (list(default) if isinstance(default, tuple) else default), key
    out = invoke("train", "--help")
    assert "docs/network.md" in " ".join(out.output.split())


def test_a_weights_file_in_place_of_last_pt_is_one_error_line(tmp_path):
    config = tiny_config(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    tiny_weights(run / "last.pt", config)
    out = invoke("train", config, run)
    assert out.exit_code == 1, out.output
    assert error_lines(out.output) == [f"Error: {run / 'last.pt'} holds weights but no training state to resume (a weights "
                                       "file, not a run's last.pt); use a new run folder, with --init to start from these weights"]
    assert "Traceback" not in out.output and sorted(p.name for p in run.iterdir()) == [".lock", "last.pt"]


@pytest.mark.slow
def test_the_model_card_says_what_the_run_trained_on_and_a_resume_elsewhere_adds_to_it(tmp_path):
    from separate.provenance import cpu_model
    from separate.train import export_weights

    config = tiny_config(tmp_path, steps="2")
    assert invoke("train", config, tmp_path / "run").exit_code == 0
    card = export_weights(tmp_path / "run" / "best.pt", tmp_path / "w.pt")
    assert card["training"]["device"] == f"{cpu_model()}, fp32, 1 process × 1 thread"
    last = tmp_path / "run" / "last.pt"
    state = load_checkpoint(last)
    torch.save({**state, "trained_on": "NVIDIA H200, bf16 autocast"}, last)     # its first session ran elsewhere
    assert invoke("train", tiny_config(tmp_path, steps="3"), tmp_path / "run").exit_code == 0
    assert load_checkpoint(last)["trained_on"] == f"NVIDIA H200, bf16 autocast; then {cpu_model()}, fp32, 1 process × 1 thread"
    assert export_weights(last, tmp_path / "v.pt", "given")["training"]["device"] == "given"
