"""Speed of the separation network on this CPU against what the CPU can do, printed.

Measures the machine's large-matmul rate (fp32, and bf16 where it is native), counts the
network's FLOPs per megapixel (torch.utils.flop_counter), then times the network alone on a
1 MP tile (1024 × 1024, no tiling, no file I/O) for each precision and each way of running it:

    eager          the module's forward pass (NCHW), as training runs it
    channels-last  the module with channels-last weights (its activations follow)
    jit-frozen     torch.jit.trace + freeze + optimize_for_inference (fp32 only)
    fused          separate.infer.FusedNet: oneDNN fused conv+ReLU / conv+sum+ReLU (the default)
    fused-1thread  the same on one thread
    compiled       the module with torch.compile of its backbone (inductor with freezing; --compile:
                   compiling costs ~40 s cold, ~9 s with inductor's cache, per tile shape)

and, with --full, `separate.infer.separate_stack` on a 24 MP stack (6000 × 4000, default tiles:
network, tiling and blending, no file I/O) once per precision. Beside each time: GFLOP/s (network
FLOPs of the pixels processed / seconds) and its fraction of the matmul rate of the same
precision. Figures are the best of ``--repeat`` runs; other load on the machine slows them.

    python tools/bench_speed.py [--full] [--compile] [--repeat 3] [--threads N] [--weights FILE]

On a busy machine wall-clock figures fall with the load; the one-thread figures per CPU second
(``--threads 1``, and the matmul's rate measured the same way) do not, or much less.

An AVX2-only CPU can be imitated on a newer one by capping the instruction sets of oneDNN,
ATen and MKL (urd's precision ``auto`` then takes fp32, as on such a CPU):

    ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 python tools/bench_speed.py
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from separate.infer import FusedNet, load_model, separate_stack
from separate.tiling import OVERLAP, TILE, tile_spans
from separate.precision import Precision, describe, native_bf16, resolve
from separate.provenance import cpu_model
from urd.core.errors import UrdError

from toolargs import Formatter, positive

ANGLES = [float(a) for a in np.radians([0.0, 45.0, 90.0])]
SCALE = torch.tensor([0.5])
THETA = torch.tensor([np.radians(50.0)], dtype=torch.float32)


def call_args(model: torch.nn.Module) -> tuple:
    """What the network takes beside the shots: the angles and exposure scale, and for a
    physics-anchored network (``base="fresnel"``, the shipped one) an angle of incidence of 50°."""
    return (ANGLES, SCALE, THETA) if getattr(model, "base", "canonical") == "fresnel" else (ANGLES, SCALE)


def best_seconds(fn, repeat: int) -> tuple[float, float]:
    """Best wall-clock and best CPU seconds (this process, all threads) of ``repeat`` calls of
    ``fn`` after one warm-up call."""
    fn()
    wall, cpu = [], []
    for _ in range(repeat):
        started, started_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - started)
        cpu.append(time.process_time() - started_cpu)
    return min(wall), min(cpu)


def matmul_gflops(dtype: torch.dtype, repeat: int, n: int = 2048) -> tuple[float, float]:
    """Rate of an n × n by n × n matrix product in ``dtype``: GFLOP per wall second, and per
    CPU second of one thread (what one core does however busy the machine is)."""
    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    wall, _ = best_seconds(lambda: a @ b, max(repeat, 5))
    _, cpu = one_thread(lambda _: best_seconds(lambda: a @ b, max(repeat, 5)))(None)
    return 2 * n**3 / wall / 1e9, 2 * n**3 / cpu / 1e9


def flops_per_mp(model: torch.nn.Module) -> float:
    """The network's forward FLOPs per megapixel (convolutions and matmuls, counted at 256²)."""
    side = 256
    with FlopCounterMode(display=False) as counter, torch.inference_mode():
        model(torch.rand(1, 3, model.channels, side, side), *call_args(model))
    return counter.get_total_flops() / (side * side) * 1e6


def levers(model: torch.nn.Module, bf16: bool, compile_too: bool, threads: int) -> dict[str, object]:
    """Ways of running ``model(obs, angles, scale)`` at one precision, by name."""
    dtype = torch.bfloat16 if bf16 else torch.float32
    args = call_args(model)

    def autocast(fn):
        def run(obs):
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                return fn(obs, *args)
        return run

    fused = FusedNet(model, dtype)
    ways = {"eager": autocast(model)}
    channels_last = load_model_like(model).to(memory_format=torch.channels_last)
    ways["channels-last"] = autocast(channels_last)
    if not bf16:
        ways["jit-frozen"] = jit_frozen(model)
    ways["fused"] = lambda obs: fused(obs, *args)
    if threads > 1:
        ways["fused-1thread"] = one_thread(ways["fused"])
    if compile_too:
        ways["compiled"] = compiled(model, bf16)
    return ways


def load_model_like(model: torch.nn.Module) -> torch.nn.Module:
    """A copy of ``model`` (same class, config and weights) in eval mode."""
    from separate.networks import build_model

    copy = build_model(model.config())
    copy.load_state_dict(model.state_dict())
    return copy.eval()


def one_thread(fn):
    """``fn`` run on one torch thread."""
    def run(obs):
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return fn(obs)
        finally:
            torch.set_num_threads(threads)
    return run


def jit_frozen(model: torch.nn.Module):
    """torch.jit.trace → freeze → optimize_for_inference (oneDNN layouts, conv+ReLU fusion)."""
    class Wrapped(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, obs):
            return self.net(obs, *call_args(self.net))

    traced = {}

    def run(obs):
        if obs.shape not in traced:
            with torch.no_grad():
                module = torch.jit.trace(Wrapped(model).eval(), obs, check_trace=False)
                traced[obs.shape] = torch.jit.optimize_for_inference(torch.jit.freeze(module))
        return traced[obs.shape](obs)
    return run


def compiled(model: torch.nn.Module, bf16: bool):
    """The module with its backbone through torch.compile (inductor with freezing: oneDNN
    fusion and packed weights); the optics around it stay eager (compiling the whole forward
    trips a dynamo guard error in torch 2.13). Prints the first call's seconds (compilation,
    per input shape) when it happens."""
    import torch._inductor.config as inductor_config

    inductor_config.freezing = True
    net = load_model_like(model).to(memory_format=torch.channels_last)
    net.backbone = torch.compile(net.backbone)
    first = []

    def run(obs):
        started = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = net(obs, *call_args(net))
        if not first:
            first.append(time.perf_counter() - started)
            print(f"    (torch.compile: first call {first[0]:.1f} s, compilation included)")
        return out
    return run


def report(name: str, seconds: tuple[float, float], megapixels: float, flops_mp: float, rate: tuple[float, float],
           fp32_rate: tuple[float, float], threads: int) -> None:
    """One line: wall seconds, GFLOP/s and its fraction of the matmul rate (of this precision,
    and of fp32 for bf16); for one thread also GFLOP per CPU second against the matmul's."""
    wall, cpu = seconds
    gflops = flops_mp * megapixels / wall / 1e9
    extra = f" ({gflops / fp32_rate[0]:4.0%} of fp32's)" if rate != fp32_rate else ""
    line = (f"  {name:22s} {wall:7.3f} s  {megapixels / wall:5.2f} MP/s  {gflops:6.1f} GFLOP/s = "
            f"{gflops / rate[0]:4.0%} of matmul{' (on every thread)' if threads == 1 else ''}{extra}")
    if threads == 1:
        per_cpu = flops_mp * megapixels / cpu / 1e9
        line += f"; per CPU-s {per_cpu:6.1f} GFLOP = {per_cpu / rate[1]:4.0%} of matmul's"
    print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--full", action="store_true", help="also time separate_stack on a 24 MP stack per precision")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile (a minute or more to compile)")
    parser.add_argument("--repeat", type=positive, default=3, help="timed runs per figure (the best is printed)")
    parser.add_argument("--precision", choices=["both", "fp32", "bf16"], default="both", help="the precisions timed")
    parser.add_argument("--weights", type=Path, default=None,
                        help="the network's weights file (.pt) (default: the shipped network's)")
    parser.add_argument("--threads", type=positive, default=None,
                        help="torch threads (default: torch's, the physical cores); with 1, figures per CPU second too")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()

    try:
        model, _ = load_model(args.weights)
    except UrdError as exc:
        raise SystemExit(f"error: {exc}") from None
    caps = torch.cpu.get_capabilities() if hasattr(torch.cpu, "get_capabilities") else {}
    flags = [k for k in ("avx2", "avx512_f", "avx512_bf16", "avx512_vnni", "amx_bf16") if caps.get(k)]
    print(f"CPU: {cpu_model()}, {threads} threads; torch {torch.__version__}, "
          f"oneDNN {'yes' if torch.backends.mkldnn.is_available() else 'no'}; flags: {' '.join(flags) or 'unknown'}")
    capped = {k: os.environ[k] for k in ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS") if k in os.environ}
    if capped:
        print("instruction sets capped (emulating an older CPU): " + ", ".join(f"{k}={v}" for k, v in capped.items()))
    print(f"precision auto → {describe(resolve('auto'))}")
    rates = {Precision.FP32: matmul_gflops(torch.float32, args.repeat)}
    if native_bf16():
        rates[Precision.BF16] = matmul_gflops(torch.bfloat16, args.repeat)
    print("matmul 2048², GFLOP/s (per CPU-s of one thread): "
          + ", ".join(f"{p.value} {wall:.0f} ({cpu:.0f})" for p, (wall, cpu) in rates.items()))
    flops_mp = flops_per_mp(model)
    print(f"network: {sum(p.numel() for p in model.parameters()) / 1e6:.2f} M parameters, "
          f"{flops_mp / 1e9:.1f} GFLOP per megapixel (forward)")

    chosen = [p for p in (Precision.FP32, Precision.BF16) if args.precision in ("both", p.value)]
    obs = torch.rand(1, 3, model.channels, 1024, 1024) * 0.5
    for precision in chosen:
        rate = rates.get(precision, rates[Precision.FP32])
        print(f"network alone, 1024 × 1024 tile, {describe(precision)}:")
        for name, fn in levers(model, precision is Precision.BF16, args.compile, threads).items():
            with torch.inference_mode():
                seconds = best_seconds(lambda fn=fn: fn(obs), args.repeat)
            report(name, seconds, obs.shape[-1] * obs.shape[-2] / 1e6, flops_mp, rate, rates[Precision.FP32],
                   1 if name.endswith("1thread") else threads)

    if args.full:
        h, w = 4000, 6000
        stack = np.random.default_rng(0).random((3, h, w, model.channels), dtype=np.float32)
        stack *= 0.5
        rows, cols = tile_spans(h, TILE, OVERLAP), tile_spans(w, TILE, OVERLAP)
        processed = sum(b - a for a, b in rows) * sum(b - a for a, b in cols)
        print(f"separate_stack, {w} × {h} ({h * w / 1e6:.0f} MP), tile {TILE}: {len(rows)} × {len(cols)} tiles, "
              f"{processed / (h * w):.2f}× the pixels")
        for precision in chosen:
            rate = rates.get(precision, rates[Precision.FP32])
            incidence = 50.0 if getattr(model, "base", "") == "fresnel" else None        # the gate on, as its FLOPs count it
            separate_stack(model, stack[:, :512, :512], [0, 45, 90], precision=precision.value, theta_deg=incidence)  # warm-up
            started, started_cpu = time.perf_counter(), time.process_time()
            separate_stack(model, stack, [0, 45, 90], precision=precision.value, theta_deg=incidence)
            seconds = time.perf_counter() - started, time.process_time() - started_cpu
            report(f"{precision.value} (image pixels)", seconds, h * w / 1e6, flops_mp, rate, rates[Precision.FP32], threads)
            report(f"{precision.value} (tile pixels)", seconds, processed / 1e6, flops_mp, rate, rates[Precision.FP32],
                   threads)

if __name__ == "__main__":
    main()
