"""Speed and memory: each method on a large scene in a fresh process, synthesis and training throughput.

`time_method` times one call of a method on `speed_stack` (seconds, and peak resident memory
of the call in MB) and `time_training` the steps/s of `separate.train` on a tiny config; both
are meant to run in a fresh (spawned) process, `run_isolated`, so that memory peaks and thread
settings are their own. `synthesis_throughput` gives the training-data synthesizer's patches/s.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import time
import traceback
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from separate import optics
from separate.robustness import NOISE_GAINS, Noise
from separate.scoring import make_method
from separate.synthesis import AngleMode, SynthesisConfig, Synthesizer, noise_std

#: Seconds one isolated measurement (a method at 1 or 24 MP, the training steps) may take.
ISOLATED_TIMEOUT_S = 3600.0


def speed_stack(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A (3, H, W, 3) float32 stack at 0/45/90° of two bundled photos behind glass (θ = 55°,
    φ⊥ along the first shot), exposure mean(S0) ≈ 0.2, medium noise; deterministic."""
    import skimage.data

    if height < 64 or width < 64:
        raise ValueError(f"expected at least 64 × 64 px, got {width} × {height}")
    refl, trans = (optics.photo_to_linear(cv2.resize(getattr(skimage.data, name)(), (width, height), interpolation=cv2.INTER_CUBIC))
                   for name in ("astronaut", "coffee"))
    theta = np.radians(55.0)
    rng = np.random.default_rng(seed)
    gain, read = NOISE_GAINS[Noise.MEDIUM]
    stack = np.empty((3, height, width, 3), np.float32)
    for k, angle in enumerate(np.radians(optics.PAPER_ANGLES_DEG)):
        stack[k] = optics.render(refl, trans, theta, 0.0, float(angle)) * 0.8
    exposure = 0.2 / float(stack.mean(dtype=np.float64) * 2)
    for k in range(3):
        shot = stack[k]
        shot *= exposure
        shot += rng.standard_normal(shot.shape, dtype=np.float32) * noise_std(shot, gain, read)
        np.clip(shot, 0.0, 1.0, out=shot)
    return stack


def _status_mb(field: str) -> float:
    """A memory field of /proc/self/status (VmRSS, VmHWM) in MB; NaN where not available."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak() -> bool:
    """Reset this process's peak resident memory (Linux ≥ 4.0); False where that is not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def time_method(name: str, height: int, width: int) -> dict:
    """Seconds and memory of one call of method ``name`` on `speed_stack` (run it in a fresh
    process, `run_isolated`): the peak resident memory counts from just before the call
    (input stack, loaded weights, interpreter included; 'rss_before_mb' is that baseline)."""
    stack = speed_stack(height, width)
    run, _ = make_method(name)
    exact = _reset_peak()
    before = _status_mb("VmRSS")
    started = time.perf_counter()
    run(stack, list(optics.PAPER_ANGLES_DEG))
    seconds = time.perf_counter() - started
    import resource

    peak = _status_mb("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"seconds": seconds, "peak_rss_mb": peak, "rss_before_mb": before}


def time_training(steps: int) -> dict:
    """Steps/s of `separate.train` on a tiny config (64² patches, batch 16, one thread, the
    CPU setting's shape; run it in a fresh process): steps 2 to N−1 are timed (the first warms
    up, the last validates and saves)."""
    import tempfile

    from separate.precision import resolve
    from separate.train import TrainConfig, train

    if steps < 3:
        raise ValueError(f"expected at least 3 training steps, got {steps}")
    cfg = TrainConfig(patch=64, batch=16, micro_batch=16, steps=steps, val_samples=4, val_every=10**9,
                      ckpt_every=10**9, threads=1)
    stamps: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        train(cfg, Path(tmp) / "run", progress=lambda record: stamps.append(time.perf_counter()))
    seconds = (stamps[-2] - stamps[0]) / (len(stamps) - 2)
    return {"steps_per_s": 1.0 / seconds, "patches_per_s": cfg.batch / seconds, "steps_timed": len(stamps) - 2,
            "patch": cfg.patch, "batch": cfg.batch, "threads": cfg.threads, "precision": resolve(cfg.precision).value}


def synthesis_throughput(count: int, size: int = 128) -> list[dict]:
    """Patches/s of the training-data synthesizer (full pipeline, training photos; loading the
    photos not timed), for each angle mode."""
    from separate.synthesis import default_pool

    pool = default_pool("train")
    rows = []
    for mode in AngleMode:
        synth = Synthesizer(pool, SynthesisConfig(patch=size, angles=mode), seed=0)
        started = time.perf_counter()
        synth.batch(count)
        seconds = time.perf_counter() - started
        rows.append({"mode": mode.value, "patches": count, "size": size, "patches_per_s": count / seconds,
                     "rejected": synth.rejected})
    return rows


def _isolated_entry(connection: multiprocessing.connection.Connection, function: Callable, args: tuple) -> None:
    """The child's side of `run_isolated`: sends ("ok", result) or ("error", traceback) back."""
    try:
        connection.send(("ok", function(*args)))
    except BaseException:  # noqa: BLE001 - the parent reports whatever failed
        connection.send(("error", traceback.format_exc()))
    finally:
        connection.close()


def run_isolated(function: Callable, args: tuple, timeout_s: float = ISOLATED_TIMEOUT_S) -> dict:
    """``function(*args)`` in a fresh (spawned) process, so that its memory peak and thread
    settings are its own; TimeoutError after ``timeout_s`` (the process is terminated),
    RuntimeError with the child's traceback if it fails."""
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(target=_isolated_entry, args=(sender, function, args), daemon=True)
    process.start()
    sender.close()
    try:
        if not receiver.poll(timeout_s):
            raise TimeoutError(f"{function.__name__}{args} did not finish within {timeout_s:.0f} s")
        status, value = receiver.recv()
    except EOFError:
        raise RuntimeError(f"{function.__name__}{args} ended without a result (exit code {process.exitcode})") from None
    finally:
        if process.is_alive():
            process.join(5)
        if process.is_alive():
            process.terminate()
            process.join(5)
        receiver.close()
    if status != "ok":
        raise RuntimeError(f"{function.__name__}{args} failed:\n{value}")
    return value
