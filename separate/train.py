"""Training of the separation network on synthesized data.

Configured by a TOML file (see `TrainConfig`; `configs/` holds the paper's and a CPU
setting). A run folder holds ``config.toml`` as used, ``last.pt`` (resumed automatically),
``best.pt`` (best validation PSNR of T̂; a run started from ``--init`` weights validates them
first, as step 0, so fine-tuning never leaves a best.pt worse than where it started), and
``log.jsonl``. Works on CPU and CUDA; with
``torchrun --nproc_per_node K`` it runs DistributedDataParallel (gloo on CPU, nccl on CUDA),
each rank drawing its own synthetic stream, synthesized in the rank's process or, with
``workers`` > 0, in that many data-loader processes (a GPU's many-core host).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import time
import tomllib
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import torch
import torch.distributed as dist

from separate import metrics
from separate.infer import read_weights
from separate.model import BASES, LOSSES, UPSAMPLING, VARIANTS, with_fresnel_base
from separate.networks import build_model
from separate.precision import Precision, resolve
from separate.provenance import cpu_model
from separate.synthesis import READ_VAR_LOG10, SHOT_GAIN_LOG10, AngleMode, SynthesisConfig, Synthesizer, default_pool, training_data
from urd.core.files import atomic_path, pid_lock
from urd.core.processes import interrupts_deferred
from urd.core.errors import TrainingError, WeightsError


#: What a run trains: every weight, or only the fresnel network's gate.
TRAINABLE = ("all", "gate", "backbone")


@dataclasses.dataclass
class TrainConfig:
    """A training run. Defaults are the paper's (Adam, lr 5e-3, batch 32, 128² patches).

    ``variant`` is "canonical" (the paper's network), "direct", or "ceilnet" (the CEILNet
    baseline, with ``blocks`` residual blocks per stage). ``angles`` is the synthesis angle mode
    of the training and validation data (`separate.synthesis.AngleMode`): "classic" (the
    paper's φ0 + 0/45/90° near φ⊥, the shipped weights' first three stages), "any" (random
    angle sets, shots presented at the estimated reference, as `urd separate` does) or
    "any-true-side" (as "any", the reference on φ⊥'s side). ``base`` is "canonical" or
    "fresnel" (`separate.model.BASES`: the physics-anchored network, whose samples then carry an
    estimate of their angle of incidence); ``trainable`` is "all", "gate" (the fresnel
    network's gate alone, the rest frozen) or "backbone" (all but the gate). ``phi_field_prob``, ``no_glass_prob``,
    ``reference_field``, the sensor-noise ranges ``shot_gain_log10`` and ``read_var_log10`` and
    the gate's θ-estimate errors ``incidence_error_deg`` and ``incidence_failure``, and the
    scene's own polarization ``t_polarized_prob``, ``real_prob``, ``mono_prob``, ``mosaic_prob`` and
    ``defocus_prob`` and the reflection's ``strength`` are the synthesis settings of the same names (`separate.synthesis.SynthesisConfig`). ``workers``
    synthesis processes per rank feed the network (0: the rank synthesizes between steps; 0 and
    1 draw the same samples, K > 1 interleaves K seeded streams); ``schedule_minutes`` > 0 lets the
    learning rate's cosine end after that much training time where that comes before ``steps``
    (`lr_at`): the run's wall time, earlier sessions of a resumed run, set-up and validation
    included, so the weights then depend on the machine's speed. ``loss`` is the network's
    training loss (`separate.model.LOSSES`: "l2", the paper's, or "log-mse"; CEILNet: "l2").
    """

    variant: str = "canonical"
    width: int = 16
    blocks: int = 6
    patch: int = 128
    batch: int = 32
    micro_batch: int = 8
    lr: float = 5e-3
    lr_min: float = 1e-5
    steps: int = 100_000
    max_minutes: float = 0.0
    seed: int = 0
    pipeline: str = "DR+NRD+LCG"
    val_samples: int = 256
    val_every: int = 500
    ckpt_every: int = 100
    precision: str = "auto"
    threads: int = 0
    angles: str = "classic"
    upsample: str = "transposed"
    base: str = "canonical"
    phi_field_prob: float = 0.0
    no_glass_prob: float = 0.0
    reference_field: bool = False
    trainable: str = "all"
    shot_gain_log10: tuple[float, float] = SHOT_GAIN_LOG10
    read_var_log10: tuple[float, float] = READ_VAR_LOG10
    incidence_error_deg: tuple[float, float] = (3.0, 1.5)
    incidence_failure: tuple[float, float] = (0.05, 0.3)
    workers: int = 0
    schedule_minutes: float = 0.0
    loss: str = "l2"
    t_polarized_prob: float = 0.0
    real_prob: float = 0.0
    mono_prob: float = 0.0
    mosaic_prob: float = 0.0
    defocus_prob: float = 0.0
    strength: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        for name in ("shot_gain_log10", "read_var_log10", "incidence_error_deg", "incidence_failure", "strength"):
            setattr(self, name, tuple(getattr(self, name)))

    @classmethod
    def from_toml(cls, path: Path) -> "TrainConfig":
        """Read a config file, every setting checked for type and range (`LIMITS`); ValueError
        naming the file and the setting otherwise."""
        try:
            data = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ValueError(f"{path}: no such file") from None
        except IsADirectoryError:
            raise ValueError(f"{path} is a folder, expected a TOML file") from None
        except OSError as exc:
            raise ValueError(f"{path}: cannot be read: {exc.strerror or exc}") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: not a valid TOML file: {exc}") from None
        names = {f.name for f in dataclasses.fields(cls)}
        if not data:
            raise ValueError(f"{path}: no settings (an empty file, or comments only); a config names at least the "
                             "steps to train, e.g. configs/cpu.toml")
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"{path}: unknown config keys {unknown}; expected some of {sorted(names)}")
        for field in dataclasses.fields(cls):
            if field.name in data:
                data[field.name] = _checked(path, field.name, field.type, data[field.name])
        cfg = cls(**data)
        if cfg.lr_min > cfg.lr:
            raise ValueError(f"{path}: expected lr_min at most lr ({cfg.lr:g}), got {cfg.lr_min:g}")
        if cfg.batch % cfg.micro_batch:
            raise ValueError(f"{path}: expected batch a multiple of micro_batch ({cfg.micro_batch}), got {cfg.batch}")
        if cfg.loss != "l2" and cfg.variant == "ceilnet":
            raise ValueError(f"{path}: expected loss in {list(LOSSES)} ('l2' for ceilnet), got {cfg.loss!r}")
        if cfg.trainable != "all" and cfg.base != "fresnel":
            raise ValueError(f"{path}: expected trainable in {list(TRAINABLE)} ('gate' and 'backbone' with base 'fresnel'), "
                             f"got {cfg.trainable!r}")
        if cfg.base == "fresnel" and cfg.variant != "canonical":
            raise ValueError(f"{path}: expected base 'canonical' for variant {cfg.variant!r}, got {cfg.base!r}")
        try:
            SynthesisConfig.ablation(cfg.pipeline)
        except ValueError as exc:
            raise ValueError(f"{path}: pipeline: {exc}") from None
        try:
            synthesis_config(cfg)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
        return cfg

    def to_toml(self) -> str:
        lines = []
        for key, value in dataclasses.asdict(self).items():
            lines.append(f"{key} = {json.dumps(value)}")
        return "\n".join(lines) + "\n"


#: A limit on a setting's value: a test and its words in an error.
Limit = tuple[Callable[[Any], bool], str]
COUNT: Limit = (lambda v: v >= 1, "at least 1")
#: The most threads a run may ask for: torch crashes (a segmentation fault) on a request of
#: 100 000; 256 covers the largest hosts a run is sent to (0: torch's default, one per core).
MAX_THREADS = 256
#: The largest seed: torch's and numpy's generators take a seed of 64 bits; 2**63 - 1 keeps it a signed one.
MAX_SEED = 2**63 - 1
#: The widest network (channels at full resolution; 8× that at the coarsest level) and the most
#: CEILNet blocks per stage a config may name (the shipped network has 16; CEILNet 32 and 6).
MAX_WIDTH, MAX_BLOCKS = 128, 24
NONNEGATIVE: Limit = (lambda v: v >= 0, "at least 0")
PROBABILITY: Limit = (lambda v: 0 <= v <= 1, "between 0 and 1")


def _one_of(choices: tuple[str, ...]) -> Limit:
    return (lambda v: v in choices, f"in {list(choices)}")


#: What each setting's value must be besides its type (the `TrainConfig` field's), checked on
#: loading a config file. Sizes in px, times in minutes, probabilities in [0, 1].
LIMITS: dict[str, Limit] = {
    "variant": _one_of(VARIANTS + ("ceilnet",)),
    "width": (lambda v: 1 <= v <= MAX_WIDTH, f"at least 1 and at most {MAX_WIDTH}"),
    "blocks": (lambda v: 1 <= v <= MAX_BLOCKS, f"at least 1 and at most {MAX_BLOCKS}"),
    "patch": (lambda v: v > 0 and v % 8 == 0, "a positive multiple of 8 (the network's 3 down-samplings)"),
    "batch": COUNT,
    "micro_batch": COUNT,
    "lr": (lambda v: v > 0, "above 0"),
    "lr_min": NONNEGATIVE,
    "steps": COUNT,
    "max_minutes": NONNEGATIVE,
    "seed": (lambda v: 0 <= v <= MAX_SEED, f"at least 0 and at most {MAX_SEED} (2**63 - 1)"),
    "val_samples": COUNT,
    "val_every": COUNT,
    "ckpt_every": COUNT,
    "precision": _one_of(tuple(p.value for p in Precision)),
    "threads": (lambda v: 0 <= v <= MAX_THREADS, f"at least 0 and at most {MAX_THREADS} (0: torch's default, one per core)"),
    "angles": _one_of(tuple(m.value for m in AngleMode)),
    "upsample": _one_of(UPSAMPLING),
    "base": _one_of(BASES),
    "phi_field_prob": PROBABILITY,
    "no_glass_prob": PROBABILITY,
    "trainable": _one_of(TRAINABLE),
    "shot_gain_log10": (lambda v: v[0] <= v[1], "a range [lo, hi] with lo <= hi"),
    "read_var_log10": (lambda v: v[0] <= v[1], "a range [lo, hi] with lo <= hi"),
    "incidence_error_deg": (lambda v: min(v) >= 0, "two numbers at least 0"),
    "incidence_failure": (lambda v: all(0 <= p <= 1 for p in v), "two probabilities between 0 and 1"),
    "workers": NONNEGATIVE,
    "schedule_minutes": NONNEGATIVE,
    "loss": _one_of(LOSSES),
    "t_polarized_prob": PROBABILITY,
    "real_prob": PROBABILITY,
    "mono_prob": PROBABILITY,
    "mosaic_prob": PROBABILITY,
    "defocus_prob": PROBABILITY,
    "strength": (lambda v: v == (0.0, 0.0) or 0 < v[0] <= v[1], "[0, 0] (as drawn) or [lo, hi] with 0 < lo <= hi"),
}


#: The words for each `TrainConfig` field type in an error.
TYPE_WORDS = {"int": "a whole number", "float": "a number", "str": "a string", "bool": "true or false",
              "tuple[float, float]": "a pair of numbers [a, b]"}


def _finite_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _checked(path: Path, key: str, kind: str, value: Any) -> Any:
    """A config file's ``value`` of setting ``key``, whose `TrainConfig` field type is ``kind``
    (a `TYPE_WORDS` key), floats as float and pairs as tuples; ValueError naming ``path`` and
    ``key`` when it has another type or is out of its `LIMITS`."""
    if kind == "tuple[float, float]":
        typed = isinstance(value, list) and len(value) == 2 and all(map(_finite_number, value))
    elif kind == "float":
        typed = _finite_number(value)
    elif kind == "int":
        typed = isinstance(value, int) and not isinstance(value, bool)
    else:
        typed = isinstance(value, {"str": str, "bool": bool}[kind])
    if not typed:
        raise ValueError(f"{path}: expected {key} {TYPE_WORDS[kind]}, got {value!r}")
    read = tuple(map(float, value)) if kind == "tuple[float, float]" else float(value) if kind == "float" else value
    if key in LIMITS and not LIMITS[key][0](read):
        raise ValueError(f"{path}: expected {key} {LIMITS[key][1]}, got {value!r}")
    return read


def to_tensors(batch: dict[str, np.ndarray], device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Synthesizer batch → (obs (B,3,C,H,W), R (B,C,H,W), T (B,C,H,W)) tensors on ``device``."""
    obs = torch.from_numpy(batch["obs"]).permute(0, 1, 4, 2, 3).contiguous().to(device)
    r = torch.from_numpy(batch["r"]).permute(0, 3, 1, 2).contiguous().to(device)
    t = torch.from_numpy(batch["t"]).permute(0, 3, 1, 2).contiguous().to(device)
    return obs, r, t


def network_inputs(batch: dict[str, np.ndarray], device: torch.device) -> dict:
    """The keyword arguments besides the shots that a batch gives the network: ``theta``
    (B, 1, P, P) rad where the samples carry an estimate of their angle of incidence."""
    return {"theta": torch.from_numpy(batch["theta_est"])[:, None].to(device)} if "theta_est" in batch else {}


def synthesis_config(cfg: TrainConfig, pipeline: str | None = None) -> SynthesisConfig:
    """The synthesis settings of a run: its pipeline (or ``pipeline``), patch, angle mode and switches."""
    base = SynthesisConfig.ablation(pipeline or cfg.pipeline, cfg.patch, cfg.angles)
    return dataclasses.replace(base, phi_field_prob=cfg.phi_field_prob, no_glass_prob=cfg.no_glass_prob,
                               reference_field=cfg.reference_field, incidence_estimate=cfg.base == "fresnel",
                               shot_gain_log10=cfg.shot_gain_log10, read_var_log10=cfg.read_var_log10,
                               incidence_error_deg=cfg.incidence_error_deg, incidence_failure=cfg.incidence_failure,
                               t_polarized_prob=cfg.t_polarized_prob, real_prob=cfg.real_prob, mono_prob=cfg.mono_prob,
                               mosaic_prob=cfg.mosaic_prob, defocus_prob=cfg.defocus_prob, strength=cfg.strength)


def validation_set(cfg: TrainConfig) -> dict[str, np.ndarray]:
    """The fixed validation patches: bsds500/val (bundled photos when absent), seed 1234, full
    pipeline with the run's angle mode and synthesis switches, from photos only: the real
    no-glass captures of the training side are training data and those of the test side the
    benchmark's (`urd.core.samples.NO_GLASS_TEST`), so none picks the best checkpoint."""
    synth = Synthesizer(default_pool("val"), synthesis_config(cfg, "DR+NRD+LCG"), seed=1234, real=())
    return synth.batch(cfg.val_samples)


@torch.no_grad()
def evaluate(model: torch.nn.Module, data: dict[str, np.ndarray], device: torch.device, chunk: int = 32) -> dict:
    """Mean PSNR of R̂ and T̂ (linear, see `separate.metrics.psnr`) over a validation set."""
    model.eval()
    psnr_r, psnr_t = [], []
    for i in range(0, len(data["obs"]), chunk):
        part = {k: v[i : i + chunk] for k, v in data.items()}
        obs, r, t = to_tensors(part, device)
        r_hat, t_hat = model(obs, **network_inputs(part, device))
        psnr_r += metrics.psnr(r_hat.cpu().numpy(), r.cpu().numpy(), axis=(1, 2, 3)).tolist()
        psnr_t += metrics.psnr(t_hat.cpu().numpy(), t.cpu().numpy(), axis=(1, 2, 3)).tolist()
    model.train()
    return {"psnr_r": float(np.mean(psnr_r)), "psnr_t": float(np.mean(psnr_t))}


def save_checkpoint(path: Path, model: torch.nn.Module, optim, step: int, cfg: TrainConfig, extra: dict) -> None:
    """Atomically write a checkpoint (model, optimizer, step, config, bookkeeping)."""
    state = {
        "model": model.state_dict(),
        "model_config": model.config(),
        "optim": optim.state_dict() if optim is not None else None,
        "step": step,
        "train_config": dataclasses.asdict(cfg),
        **extra,
    }
    with atomic_path(path, overwrite=True) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict:
    """Read a checkpoint or weights file with tensors and plain data only (no code runs on
    loading; `separate.infer.read_weights`); WeightsError in one line naming the file and why
    it is not one otherwise."""
    return read_weights(path, device)


def model_config(cfg: TrainConfig) -> dict:
    """The network's config for a training config."""
    if cfg.variant == "ceilnet":
        return {"variant": "ceilnet", "width": cfg.width, "blocks": cfg.blocks}
    config = {"variant": cfg.variant, "width": cfg.width}
    if cfg.upsample != "transposed":
        config["upsample"] = cfg.upsample
    return config if cfg.base == "canonical" else {**config, "base": cfg.base}


def lr_at(cfg: TrainConfig, step: int, wall_s: float = 0.0) -> float:
    """Cosine decay from lr to lr_min after a 200-step warm-up, over ``steps`` or, where it
    comes first, ``schedule_minutes`` of training time ``wall_s`` (s)."""
    warm = min(1.0, (step + 1) / 200)
    progress = step / cfg.steps
    if cfg.schedule_minutes > 0:
        progress = max(progress, wall_s / (cfg.schedule_minutes * 60))
    return cfg.lr_min + (cfg.lr - cfg.lr_min) * warm * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


class SynthesisStream(torch.utils.data.IterableDataset):
    """Endless micro-batches of ``size`` samples from a `Synthesizer` over the ``split`` image
    pool, seeded ``seed`` (data-loader worker k: ``seed`` + 1_000_003·k, single-threaded)."""

    def __init__(self, split: str, cfg: SynthesisConfig, seed: int, size: int):
        self.split, self.cfg, self.seed, self.size = split, cfg, seed, size

    def __iter__(self):
        worker = torch.utils.data.get_worker_info()
        if worker is not None:
            cv2.setNumThreads(1)
            torch.set_num_threads(1)
        synth = Synthesizer(default_pool(self.split), self.cfg, seed=self.seed + 1_000_003 * (worker.id if worker else 0))
        while True:
            yield synth.batch(self.size)


def _unchanged(batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A data loader's collate step that keeps a synthesizer batch as it is."""
    return batch


@contextlib.contextmanager
def synthesis_batches(cfg: TrainConfig, seed: int, size: int):
    """The iterator of a rank's training micro-batches (`SynthesisStream`), as a context: in
    ``cfg.workers`` spawned processes (a fork of a process whose thread pools have run can hang),
    ended on leaving it. Spawning needs a script's ``if __name__ == "__main__":`` guard."""
    stream = SynthesisStream("train", synthesis_config(cfg), seed, size)
    if cfg.workers == 0:
        yield iter(stream)
        return
    batches = iter(torch.utils.data.DataLoader(stream, batch_size=None, num_workers=cfg.workers, collate_fn=_unchanged,
                                               prefetch_factor=4, persistent_workers=True, timeout=300,
                                               multiprocessing_context="spawn"))
    try:
        yield batches
    finally:
        batches._shutdown_workers()         # now, also while a traceback still holds the iterator


# Settings a resumed run may change: how long, how often, how fast; not what it learns from
# (`workers` changes the order of the synthetic samples, not their distribution).
RESUMABLE_CHANGES = {"steps", "max_minutes", "threads", "precision", "val_every", "ckpt_every", "workers"}


def run_lock(run_dir: Path) -> contextlib.AbstractContextManager:
    """``run_dir``'s training lock (`urd.core.files.pid_lock`); TrainingError naming the holder's
    pid when another process is training in that folder."""
    return pid_lock(Path(run_dir) / ".lock",
                    busy=lambda pid: TrainingError(f"run {run_dir} is being trained by another process (pid {pid})"),
                    unopenable=lambda exc: TrainingError(f"cannot lock run {run_dir}: {exc.strerror or exc}"))


#: The files a run writes in its folder besides ``last.pt`` and ``.lock``.
RUN_FILES = ("config.toml", "best.pt", "log.jsonl")


def check_run_folder(run_dir: Path) -> None:
    """TrainingError when ``run_dir`` holds an earlier run's ``best.pt`` but no ``last.pt`` to resume
    from: a new run there would overwrite it. (A start killed before its first checkpoint leaves
    config.toml and log.jsonl only; a new run takes the folder over; a run from ``--init`` writes
    ``last.pt`` beside its step-0 ``best.pt``.) Removes the temporary files of checkpoints whose
    writing was killed (the folder is locked: no other run writes them)."""
    for stale in Path(run_dir).glob(".*.tmp.*"):
        if stale.name.startswith((".last.", ".best.", ".config.")):
            stale.unlink(missing_ok=True)
    if (Path(run_dir) / "best.pt").exists() and not (Path(run_dir) / "last.pt").exists():
        raise TrainingError(f"{run_dir} holds best.pt of an earlier run but no last.pt to resume from, and a new "
                            "run would overwrite it; use a new run folder (or restore last.pt there to resume)")


def check_resume(state: dict, cfg: TrainConfig, source: Path, init: Path | None = None) -> None:
    """TrainingError when the run checkpoint ``state``, read from ``source`` (a run's last.pt),
    cannot go on with ``cfg`` (`check_resumable`) or with ``init`` weights: those apply to a new
    run, and are accepted on resuming only when they are the very weights (SHA-256) it started from."""
    if not all(isinstance(state.get(key), kind) for key, kind in (("train_config", dict), ("step", int), ("optim", dict))):
        raise TrainingError(f"{source} holds weights but no training state to resume (a weights file, not a run's "
                            "last.pt); use a new run folder, with --init to start from these weights")
    check_resumable(state["train_config"], cfg, source)
    origin = state.get("init") or {}
    if init is not None and not (Path(init).is_file() and origin.get("sha256") == _sha256(Path(init))):
        started = f"from {origin['path']}" if origin else "from scratch"
        raise TrainingError(f"{Path(source).parent} already holds a run at step {state['step']} (started {started}): "
                            "--init applies to a new run; use a new run folder")


def _sha256(path: Path) -> str:
    """A file's SHA-256 (hex)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def check_resumable(stored: dict, cfg: TrainConfig, source: Path) -> None:
    """TrainingError naming the settings in which ``cfg`` differs from the config a checkpoint
    was trained with (``stored``), other than `RESUMABLE_CHANGES`."""
    current = dataclasses.asdict(cfg)
    changed = sorted(k for k in set(stored) & set(current) - RESUMABLE_CHANGES if stored[k] != current[k])
    if changed:
        detail = ", ".join(f"{k} {stored[k]!r} → {current[k]!r}" for k in changed)
        raise TrainingError(f"{source} was trained with other settings ({detail}); use a new run folder")


def train(cfg: TrainConfig, run_dir: Path, init: Path | None = None, progress=None) -> dict:
    """Train (or resume) a run in ``run_dir``; returns the final log record (at least its ``step``).

    ``init`` optionally starts from a weights or checkpoint file (fine-tuning); a run folder
    with ``last.pt`` always resumes from it instead, provided its config differs from ``cfg``
    only in `RESUMABLE_CHANGES` and ``init`` is none or the weights it started from (else
    TrainingError, `check_resume`). A folder holding an earlier run's ``best.pt`` without ``last.pt``
    is refused (`check_run_folder`). One process (DDP: rank 0) holds the folder's lock while
    training (`run_lock`). On Ctrl-C or SIGTERM rank 0 saves ``last.pt`` at the step reached and
    notes it on the exception; a non-finite loss or gradient stops the run with TrainingError,
    ``last.pt`` left at its last (finite) checkpoint. A new run that fails before it logs anything
    (and so before its first ``last.pt``) leaves no trace: the files it wrote, and the folders it
    made, are removed; one that fails later keeps its log.jsonl and best.pt to look at. Under
    torchrun (``WORLD_SIZE`` > 1) every rank joins the process group first (and leaves it at the
    end) unless the caller has one, and a start that rank 0 refuses is refused on every rank.
    """
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise TrainingError(f"{run_dir} is a file, expected a run folder")
    joined = int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized()
    if joined:
        _join_process_group()                      # every rank, before rank 0 may refuse the start
    record = _started(cfg, run_dir, init, progress)
    if joined:
        dist.barrier()                             # no rank leaves while another still talks to it
        dist.destroy_process_group()
    return record


def _started(cfg: TrainConfig, run_dir: Path, init: Path | None, progress) -> dict:
    """`train` on this rank: rank 0 locks and checks the folder and tells the other ranks whether
    it starts (`_share_start`); the others wait for its word."""
    if dist.is_initialized() and dist.get_rank() != 0:
        refusal = _share_start(None)
        if refusal is not None:
            raise TrainingError(f"rank 0 did not start the run: {refusal}")
        return _train(cfg, run_dir, init, progress)
    made = [folder for folder in (run_dir, *run_dir.parents) if not folder.exists()]     # the deepest first
    told = False                                             # whether the other ranks know this rank starts
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        before = {path.name for path in run_dir.iterdir()}
        with run_lock(run_dir):
            try:
                check_run_folder(run_dir)
                told = True
                _share_start(None)
                return _train(cfg, run_dir, init, progress)
            except BaseException:
                log = run_dir / "log.jsonl"
                if not (run_dir / "last.pt").exists() and not (log.exists() and log.stat().st_size):   # a failed start
                    for name in (*RUN_FILES, ".lock"):
                        if name not in before:
                            (run_dir / name).unlink(missing_ok=True)
                raise
    except BaseException as exc:
        if not told:
            with contextlib.suppress(Exception):             # a refused start: the other ranks, if still there, are told why
                _share_start(exc)
        for folder in made:                                  # only if empty: never what another process put there
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def _join_process_group() -> None:
    """Join torchrun's process group: nccl on CUDA (this rank's GPU made current), gloo on the CPU."""
    if torch.cuda.is_available():
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
    dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")


def _share_start(refusal: BaseException | None) -> str | None:
    """Under DDP, rank 0's word on starting, told to every rank: rank 0 sends ``refusal`` (the error
    that stops it before training, or None for a start); another rank gets it back, as a message
    or None. Without a process group: None, nothing sent."""
    if not dist.is_initialized():
        return None
    word = [None if refusal is None else str(refusal) or type(refusal).__name__]
    dist.broadcast_object_list(word, src=0)
    return word[0]


def _config_in(run_dir: Path) -> TrainConfig | None:
    """The settings of ``run_dir``'s config.toml; None when it is missing or not a valid config."""
    try:
        return TrainConfig.from_toml(Path(run_dir) / "config.toml")
    except ValueError:
        return None


def rank_batches(batch: int, micro_batch: int, world: int) -> tuple[int, int]:
    """(samples per rank, micro-batch) of a step of ``batch`` samples over ``world`` ranks, each
    rank's share in whole micro-batches of at most ``micro_batch``; ValueError naming a batch that
    does not split so (every sample counted once, each weighed alike)."""
    per_rank = batch // world
    micro = min(micro_batch, per_rank)
    if per_rank < 1 or batch % world or per_rank % micro:
        raise ValueError(f"batch {batch} does not split into {world} rank(s) of whole micro-batches of at most "
                         f"{micro_batch}: choose a batch that is a multiple of {world * micro_batch}"
                         + (f" (or of {world}, at most {world * micro_batch})" if world > 1 else ""))
    return per_rank, micro


def training_setup(device: torch.device, bf16: bool, world: int) -> str:
    """What a training session runs on, as a model card states it: the GPU or this machine's CPU,
    the precision, and the processes (DDP ranks) and threads."""
    compute = "bf16 autocast" if bf16 else "fp32"
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)}{f' ×{world} (DDP)' if world > 1 else ''}, {compute}"
    threads = torch.get_num_threads()
    return (f"{cpu_model()}, {compute}, {world} process{'es' if world > 1 else ''} × "
            f"{threads} thread{'s' if threads > 1 else ''}")


def _train(cfg: TrainConfig, run_dir: Path, init: Path | None, progress) -> dict:
    """`train`'s loop, in a folder already locked."""
    distributed = dist.is_initialized()
    rank = dist.get_rank() if distributed else 0
    world = dist.get_world_size() if distributed else 1
    device = torch.device(f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if torch.cuda.is_available() else "cpu")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    model = build_model(model_config(cfg)).to(device, memory_format=torch.channels_last)   # ~17% faster steps on CPU
    if cfg.trainable != "all":
        for name, param in model.named_parameters():
            param.requires_grad_(name.startswith("gate.") == (cfg.trainable == "gate"))
    optim = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr)
    step, best, started = 0, -math.inf, time.time()
    elapsed_before = 0.0
    origin = None
    trained_on = ""                                         # what earlier sessions of a resumed run ran on
    data = training_data(cfg.real_prob)[0]                 # for the model card (`export_weights`)
    last = run_dir / "last.pt"
    resumed = last.exists()
    if resumed or init is not None:
        source = last if resumed else init
        state = load_checkpoint(source, device)
        if resumed:
            check_resume(state, cfg, last, init)
        stored = {"channels": 3, **state.get("model_config", {})}
        if not resumed and model.config().get("base") == "fresnel" and "base" not in stored \
                and stored.get("variant", "canonical") == "canonical":
            start = build_model(stored)                     # a canonical-base start: its weights and a new, closed gate
            start.load_state_dict({k: v.float() for k, v in state["model"].items()})
            converted = with_fresnel_base(start)
            state = {**state, "model": converted.state_dict()}
            stored = {"channels": 3, **converted.config()}
        mismatch = stored != {"channels": 3, **model.config()}
        if mismatch and resumed:
            raise TrainingError(f"{last} holds a network {stored}, not the {model.config()} of this config; "
                                "use a new run folder")
        if mismatch:
            raise WeightsError(f"{source} holds a network {stored}, not the {model.config()} of this config "
                               "(for resize up-sampling from transposed weights: tools/resize_upsampling.py)")
        model.load_state_dict(state["model"])
        if resumed:
            optim.load_state_dict(state["optim"])
            step, best = state["step"], state.get("best_psnr_t", -math.inf)
            elapsed_before = state.get("wall_s", 0.0)
            origin = state.get("init")
            trained_on = state.get("trained_on", "")
        else:
            origin = {"path": str(init), "sha256": _sha256(Path(init))}
    if rank == 0 and _config_in(run_dir) != cfg:            # never rewritten when it holds these settings already
        with atomic_path(run_dir / "config.toml", overwrite=True) as tmp:
            tmp.write_text(cfg.to_toml())
    ddp = torch.nn.parallel.DistributedDataParallel(model) if distributed else model
    per_rank, micro = rank_batches(cfg.batch, cfg.micro_batch, world)
    val = validation_set(cfg) if rank == 0 else None
    use_bf16 = resolve(cfg.precision, device) is Precision.BF16
    setup = training_setup(device, use_bf16, world)
    trained_on = trained_on if trained_on.endswith(setup) else f"{trained_on}; then {setup}" if trained_on else setup
    record: dict = {"step": step}
    saved = step if resumed else None                  # the step last.pt holds
    wall = elapsed_before                                   # training time (s), the same on every rank

    def keep(path: Path, with_optim: bool, **extra) -> None:
        """A checkpoint of the run as it is now: ``last.pt`` with the optimizer, ``best.pt`` without."""
        save_checkpoint(path, model, optim if with_optim else None, step, cfg,
                        {"best_psnr_t": best, "wall_s": wall, "init": origin, "data": data, "trained_on": trained_on, **extra})

    log = open(run_dir / "log.jsonl", "a") if rank == 0 else None
    if rank == 0 and init is not None and not resumed:          # the starting weights compete for best.pt
        record = {"step": 0, "lr": lr_at(cfg, 0), "wall_s": 0.0, "patches_seen": 0, **evaluate(model, val, device)}
        best = record["psnr_t"]
        keep(run_dir / "best.pt", False, val=record)
        keep(last, True, val=record)                            # resumable from here: best.pt is never left alone
        saved = 0
        log.write(json.dumps(record) + "\n")
        log.flush()
        if progress is not None:
            progress(record)
    try:
        with synthesis_batches(cfg, cfg.seed * 1000 + rank + 7919 * step, micro) as batches:
            while step < cfg.steps:
                for group in optim.param_groups:
                    group["lr"] = lr_at(cfg, step, wall)
                optim.zero_grad(set_to_none=True)
                loss_sum = 0.0
                for start in range(0, per_rank, micro):
                    batch = next(batches)
                    obs, r, t = to_tensors(batch, device)
                    last_micro = start + micro >= per_rank         # DDP averages the gradients once, after it
                    with ddp.no_sync() if distributed and not last_micro else contextlib.nullcontext():
                        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16):
                            outputs = ddp(obs, **network_inputs(batch, device))
                        loss = model.loss(outputs, r, t, cfg.loss) * micro / per_rank
                        loss.backward()
                    loss_sum += loss.item()
                norm = torch.nn.utils.clip_grad_norm_([p for p in model.parameters() if p.requires_grad], 1.0)
                if not math.isfinite(norm.item()):           # a non-finite loss makes it so; one value on every DDP rank
                    kept = f"{last} keeps step {saved}" if saved is not None else "no checkpoint was written"
                    raise TrainingError(f"training diverged: the loss or its gradient is not finite at step {step + 1} "
                                        f"({kept}); lower lr (now {cfg.lr:g}) and train in a new run folder")
                with interrupts_deferred():                     # a checkpoint never holds half an update
                    optim.step()
                    step += 1
                session = time.time() - started
                wall = elapsed_before + session
                out_of_time = cfg.max_minutes > 0 and session > cfg.max_minutes * 60
                if distributed:                                 # every rank stops, and schedules its learning rate, alike
                    shared = torch.tensor([float(out_of_time), wall], dtype=torch.float64, device=device)
                    dist.all_reduce(shared, op=dist.ReduceOp.MAX)
                    out_of_time, wall = bool(shared[0].item()), shared[1].item()
                if rank == 0:
                    record = {"step": step, "loss": loss_sum, "lr": lr_at(cfg, step, wall), "wall_s": round(wall, 1),
                              "patches_seen": step * cfg.batch}
                    if step % cfg.val_every == 0 or step == cfg.steps or out_of_time:
                        record.update(evaluate(model, val, device))
                        if record["psnr_t"] > best:
                            best = record["psnr_t"]
                            keep(run_dir / "best.pt", False, val=record)
                    if step % cfg.ckpt_every == 0 or step == cfg.steps or out_of_time or "psnr_t" in record:
                        keep(last, True)
                        saved = step
                    if step % 10 == 0 or "psnr_t" in record:
                        log.write(json.dumps(record) + "\n")
                        log.flush()
                    if progress is not None:
                        progress(record)
                if out_of_time:
                    break
    except KeyboardInterrupt as exc:                 # Ctrl-C, or SIGTERM (urd.core.processes.Terminated)
        if rank == 0 and step > (saved or 0):
            keep(last, True)
            saved = step
        if rank == 0 and saved is not None:
            exc.add_note(f"{last} keeps step {saved}")
        raise
    return record


def holds_weights(path: Path, weights: dict) -> bool:
    """Whether the file at ``path`` is a weights file holding exactly ``weights`` (config, tensor
    names, dtypes and values); False when it is missing or not a weights file at all."""
    try:
        held = load_checkpoint(path) if path.is_file() else None
    except WeightsError:
        return False
    return held is not None and held.get("model_config") == weights["model_config"] \
        and held["model"].keys() == weights["model"].keys() \
        and all(held["model"][k].dtype == v.dtype and torch.equal(held["model"][k], v) for k, v in weights["model"].items())


def export_weights(checkpoint: Path, output: Path, device: str | None = None, note: str = "", parent: dict | None = None) -> dict:
    """Write a checkpoint's network as shipped weights (float16: half the size, loaded as
    float32) plus a model card (``output`` with .json) and return the card. A weights file
    already holding exactly these weights is kept as it is (same bytes, same SHA-256).

    The card records the training config, steps, patches seen, wall time, ``device`` (default:
    what the run recorded it trained on, `training_setup`), and the validation figures logged at that checkpoint. ``parent`` is the card of the weights the run
    was initialized from (`train` with ``init``): the card then lists every stage and the totals.
    WeightsError if ``parent`` does not describe the weights the run started from.
    """
    state = load_checkpoint(checkpoint)
    if parent is not None and state.get("init") and state["init"]["sha256"] != parent["sha256"]:
        raise WeightsError(f"the parent card ({parent['weights']}) does not describe the weights the run started from "
                           f"({state['init']['path']})")
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    weights = {"model": {k: v.half().contiguous() for k, v in state["model"].items()}, "model_config": state["model_config"]}
    if not holds_weights(output, weights):              # torch.save's bytes differ each time
        with atomic_path(output, overwrite=True) as tmp:
            torch.save(weights, tmp)
    cfg = state["train_config"]
    card = {
        "weights": output.name,
        "sha256": hashlib.sha256(output.read_bytes()).hexdigest(),
        "model": state["model_config"],
        "parameters": sum(v.numel() for v in state["model"].values()),
        "training": {"config": cfg, "steps": state["step"], "patches_seen": state["step"] * cfg["batch"],
                     "wall_time_s": round(state.get("wall_s", 0.0)),
                     "device": device or state.get("trained_on") or "not recorded in the checkpoint",
                     "data": state.get("data", "synthesized from bsds500/train + sunhays80 (../shared/data/natural)")
                             + ", pipeline " + cfg["pipeline"]},
        "validation": state.get("val"),
        "initialized_from": state.get("init") or (parent and {"path": parent["weights"], "sha256": parent["sha256"]}),
        "note": note,
    }
    if parent is not None:
        stages = parent.get("stages", [parent["training"]]) + [card["training"]]
        card["stages"] = stages
        card["total"] = {key: sum(s[key] for s in stages) for key in ("steps", "patches_seen", "wall_time_s")}
    with atomic_path(output.with_suffix(".json"), overwrite=True) as tmp:
        tmp.write_text(json.dumps(card, indent=2) + "\n")
    return card
