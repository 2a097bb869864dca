"""The fixed synthetic benchmark: seeded patches from bsds500/test through the full synthesis
pipeline (DR + NRD + LCG, ±4° angle noise, sensor noise; the paper's angles, φ⊥ within ±45°
of φ0, ``AngleMode.CLASSIC``), separated by each method with the nominal angles 0/45/90 (the
true φ0 and angle errors are unknown to the methods, as in the paper) and its reference policy
("auto": φ⊥ estimated from the shots; a number forces it, 0 = the first shot, urd's rule
before the reference was estimated). Figures: RMSE, PSNR and SSIM of R̂ and T̂ against the
observable layers, averaged over patches (linear values, peak 1, PSNR floored at 60 dB per
patch; see `separate.metrics`).

`reshoot` renders a benchmark patch's layers again at other polarizer angles (for
`tools/bench_reference.py`: any φ⊥, any angle set).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from separate import metrics, optics
from separate.synthesis import AngleMode, SynthesisConfig, Synthesizer, default_pool, draw_noise_levels, noise_std

SEED = 2018
DIRECT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "urd-direct.pt"


def largest_size() -> int:
    """The largest patch size (px) the benchmark can draw: the second-longest shorter side among
    the test photos (patches come from at least two of them); 0 with fewer than two photos."""
    sides = sorted((min(image.shape[:2]) for image in default_pool("test")), reverse=True)
    return sides[1] if len(sides) > 1 else 0


def benchmark_set(count: int, size: int) -> dict[str, np.ndarray]:
    """The benchmark patches (deterministic for ``count`` and ``size``); ValueError unless
    ``count`` ≥ 1 and 1 ≤ ``size`` ≤ `largest_size`."""
    if count < 1:
        raise ValueError(f"expected at least 1 benchmark patch, got {count}")
    if not 1 <= size <= largest_size():
        raise ValueError(f"expected a patch size between 1 and {largest_size()} px (the shorter side of the "
                         f"benchmark's test photos), got {size}")
    return Synthesizer(default_pool("test"), SynthesisConfig(patch=size, angles=AngleMode.CLASSIC), seed=SEED).batch(count)


def reshoot(sample: dict[str, np.ndarray], angles: np.ndarray, rng: np.random.Generator,
            angle_noise_deg: float = 4.0, n: float = optics.N_GLASS) -> np.ndarray:
    """A benchmark patch's scene shot again through a polarizer at ``angles`` (rad, in the
    frame of its ``phi_perp``), each off by U[±``angle_noise_deg``], with the synthesis
    pipeline's sensor noise (gains drawn from ``rng``) and clipping; no new non-rigid
    deformation. Returns (N, P, P, 3) float32 in [0, 1]."""
    theta = sample["theta"]
    i_r, i_t = optics.radiances_from_layers(sample["r"], sample["t"], theta, n)
    true = np.asarray(angles, np.float64) + np.radians(rng.uniform(-angle_noise_deg, angle_noise_deg, len(angles)))
    shots = np.stack([optics.render(i_r, i_t, theta, sample["phi_perp"], float(a), n) for a in true])
    shot_gain, read_var = draw_noise_levels(rng)
    shots = shots + rng.normal(0.0, 1.0, shots.shape) * noise_std(shots, shot_gain, read_var)
    return np.clip(shots, 0.0, 1.0).astype(np.float32)


def run_benchmark(methods: list[str], count: int = 64, size: int = 256, direct_weights: Path | None = None,
                  reference: str | float = "auto") -> list[dict]:
    """Score each method on the benchmark set; one row of figures per method.

    A method is a name of `separate.methods.METHODS`, "direct" (the network with the direct
    variant's weights), or "LABEL=PATH": the network with the weights or checkpoint at PATH;
    each with the reference policy ``reference`` ("auto" or degrees in the nominal frame).
    """
    from separate.methods import get_method

    data = benchmark_set(count, size)
    aoi_deg = np.degrees(data["theta"].mean(axis=(1, 2)))
    rows = []
    for name in methods:
        label, _, weights = name.partition("=")
        if weights:
            run, _ = get_method("network", reference, weights=Path(weights))
            name = label
        elif name == "direct":
            run, _ = get_method("network", reference, weights=direct_weights or DIRECT_WEIGHTS)
        else:
            run, _ = get_method(name, reference)
        scores = {k: [] for k in ("rmse_r", "psnr_r", "ssim_r", "rmse_t", "psnr_t", "ssim_t")}
        timed = Timed(run)
        for obs, r, t in zip(data["obs"], data["r"], data["t"]):
            r_hat, t_hat = timed(obs, list(optics.PAPER_ANGLES_DEG))
            for layer, est, ref in (("r", r_hat, r), ("t", t_hat, t)):
                scores[f"rmse_{layer}"].append(float(metrics.rmse(est, ref)))
                scores[f"psnr_{layer}"].append(float(metrics.psnr(est, ref)))
                scores[f"ssim_{layer}"].append(metrics.ssim(np.clip(est, 0, 1), np.clip(ref, 0, 1)))
        rows.append({"method": name, **{k: float(np.mean(v)) for k, v in scores.items()},
                     "seconds_per_patch": timed.per_call(), "psnr_t_per_patch": scores["psnr_t"], "aoi_deg_per_patch": aoi_deg})
    return rows


AOI_BANDS = ((10, 30), (30, 45), (45, 65), (65, 85))


def format_aoi_table(rows: list[dict]) -> str:
    """A Markdown table of mean T̂ PSNR (dB) per band of the patches' mean angle of incidence."""
    theta = rows[0]["aoi_deg_per_patch"]
    bands = [(lo, hi, (theta >= lo) & (theta < hi)) for lo, hi in AOI_BANDS]
    lines = ["| method | " + " | ".join(f"θ {lo}–{hi}° ({m.sum()})" for lo, hi, m in bands) + " |",
             "|---|" + "---|" * len(bands)]
    for r in rows:
        values = np.asarray(r["psnr_t_per_patch"])
        cells = [f"{values[m].mean():.2f}" if m.any() else "–" for _, _, m in bands]
        lines.append(f"| {r['method']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


class Timed:
    """A method's ``run`` that keeps the wall time of each call (s); `per_call` is their mean
    without the first call (warm-up: threads, caches, lazy imports) where there are more."""

    def __init__(self, run: Callable):
        self.run, self.seconds = run, []

    def __call__(self, *args, **kwargs):
        started = time.perf_counter()
        try:
            return self.run(*args, **kwargs)
        finally:
            self.seconds.append(time.perf_counter() - started)

    def per_call(self) -> float:
        timed = self.seconds[1:] or self.seconds
        return float(np.mean(timed)) if timed else float("nan")


def paired_gain(rows: list[dict], a: str, b: str, resamples: int = 10000, groups: list | None = None) -> dict:
    """Per-patch T̂ PSNR of method ``a`` minus method ``b`` (dB): mean, a 95% percentile bootstrap
    interval of the mean (seeded), and the patches where ``a`` scores higher. With ``groups`` (one
    label per patch: patches cut from one capture are not independent) whole groups are resampled."""
    by_name = {r["method"]: np.asarray(r["psnr_t_per_patch"]) for r in rows}
    for name in (a, b):
        if name not in by_name:
            raise ValueError(f"expected a row for method {name!r}, got {sorted(by_name)}")
    diff = by_name[a] - by_name[b]
    labels = np.arange(diff.size) if groups is None else np.unique(np.asarray(groups), return_inverse=True)[1]
    if labels.size != diff.size:
        raise ValueError(f"expected one group label per patch ({diff.size}), got {labels.size}")
    sums, counts = np.bincount(labels, diff), np.bincount(labels)
    picked = np.random.default_rng(SEED).integers(0, counts.size, (resamples, counts.size))
    means = sums[picked].sum(axis=1) / counts[picked].sum(axis=1)
    lo, hi = np.quantile(means, [0.025, 0.975])
    return {"mean": float(diff.mean()), "ci95": (float(lo), float(hi)), "wins": int((diff > 0).sum()), "count": int(diff.size)}


def format_paired(rows: list[dict], a: str, b: str) -> str:
    """One line: the paired T̂ PSNR gain of ``a`` over ``b``."""
    g = paired_gain(rows, a, b)
    return (f"T PSNR {a} - {b}: {g['mean']:+.2f} dB (95% bootstrap interval {g['ci95'][0]:+.2f} to "
            f"{g['ci95'][1]:+.2f}), higher on {g['wins']} of {g['count']} patches")


def format_table(rows: list[dict]) -> str:
    """A Markdown table of benchmark rows."""
    lines = ["| method | T RMSE | T PSNR (dB) | T SSIM | R RMSE | R PSNR (dB) | R SSIM | s/patch |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['rmse_t']:.4f} | {r['psnr_t']:.2f} | {r['ssim_t']:.3f} | "
                     f"{r['rmse_r']:.4f} | {r['psnr_r']:.2f} | {r['ssim_r']:.3f} | {r['seconds_per_patch']:.2f} |")
    return "\n".join(lines)
