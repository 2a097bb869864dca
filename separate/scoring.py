"""Scoring a separation method's R̂ and T̂ against the truth, as `separate.bench` scores its benchmark.

`make_method` loads a method of `separate.methods` (or "direct": the network with the direct
variant's weights); `score` gives RMSE, PSNR and SSIM of both layers (linear values, peak 1,
PSNR floored at 60 dB per patch, `separate.metrics`); `attempt` turns a method refusing an input
(ValueError) into NaN figures and the message; `finite_mean` averages what was scored;
`gap` is the paired T̂ PSNR gain of one method over another (`separate.bench.paired_gain`).
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from separate import metrics
from separate.bench import DIRECT_WEIGHTS, paired_gain


def make_method(name: str) -> tuple[Callable, dict]:
    """``(run, info)`` of a method of `separate.methods` or "direct" (the network with the direct
    variant's weights); every method with its default ("auto") reference."""
    from separate.methods import get_method

    if name == "direct":
        return get_method("network", weights=DIRECT_WEIGHTS)
    return get_method(name)


SCORES = ("rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r", "ssim_r")


def score(r_hat: np.ndarray, t_hat: np.ndarray, r: np.ndarray, t: np.ndarray, with_ssim: bool = True) -> dict[str, float]:
    """RMSE, PSNR (and SSIM, on values clipped to [0, 1]) of R̂ and T̂ against the truth, as
    `separate.bench` scores them."""
    out = {}
    for layer, est, ref in (("r", r_hat, r), ("t", t_hat, t)):
        out[f"rmse_{layer}"] = float(metrics.rmse(est, ref))
        out[f"psnr_{layer}"] = float(metrics.psnr(est, ref))
        if with_ssim:
            out[f"ssim_{layer}"] = metrics.ssim(np.clip(est, 0, 1), np.clip(ref, 0, 1))
    return out


def attempt(run: Callable, shots: np.ndarray, angles_deg: Sequence[float], truth: tuple[np.ndarray, np.ndarray],
            with_ssim: bool = True) -> tuple[dict[str, float], str | None]:
    """``score`` of one call of a method, or NaN figures and the message when the method
    refuses the input (ValueError: e.g. calibrated angles spanning less than it accepts)."""
    try:
        r_hat, t_hat = run(shots, list(angles_deg))
    except ValueError as exc:
        keys = SCORES if with_ssim else ("rmse_t", "psnr_t", "rmse_r", "psnr_r")
        return dict.fromkeys(keys, float("nan")), str(exc)
    return score(r_hat, t_hat, *truth, with_ssim=with_ssim), None


def finite_mean(values: Sequence[float]) -> float:
    """The mean of the finite values (NaN marks a refused patch); NaN when there are none."""
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def gap(rows: list[dict], a: str = "network", b: str = "direct") -> dict | None:
    """`separate.bench.paired_gain` of T̂ PSNR, ``a`` − ``b``, over the patches of one set or
    condition that both methods accepted; None unless both methods are there and share one."""
    by_name = {r["method"]: np.asarray(r["psnr_t_per_patch"], np.float64) for r in rows}
    if a not in by_name or b not in by_name:
        return None
    both = np.isfinite(by_name[a]) & np.isfinite(by_name[b])
    if not both.any():
        return None
    return {"a": a, "b": b, **paired_gain([{"method": m, "psnr_t_per_patch": by_name[m][both]} for m in (a, b)], a, b)}
