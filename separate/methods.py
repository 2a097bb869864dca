"""Separation methods by name: the network and the classical baselines share one interface.

``get_method(name, **options)`` returns ``(run, info)``: ``run(images, angles_deg)`` maps an
aligned stack (N, H, W, C) float32 linear and its polarizer angles (deg) to (R̂, T̂), each
H×W×C float32 linear; ``info`` describes the method and parameters for the manifest.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

Run = Callable[[np.ndarray, list[float]], tuple[np.ndarray, np.ndarray]]


def network(weights: Path | None = None, tile: int = 768, precision: str = "auto",
            colour_match: bool = False, progress=None) -> tuple[Run, dict]:
    """The paper's network (`separate.model`) with shipped or given weights."""
    from separate.infer import OVERLAP, load_model, match_histograms, separate_stack

    from separate.precision import resolve

    model, weights_info = load_model(weights)
    chosen = resolve(precision).value

    def run(images: np.ndarray, angles_deg: list[float]) -> tuple[np.ndarray, np.ndarray]:
        r_hat, t_hat = separate_stack(model, images, angles_deg, tile, OVERLAP, chosen, progress)
        if colour_match:
            darkest = int(np.argmin([shot.mean(dtype=np.float64) for shot in images]))
            t_hat = match_histograms(t_hat, images[darkest])
        return r_hat, t_hat

    info = {"weights": {"file": Path(weights_info["file"]).name, "sha256": weights_info["sha256"],
                        "config": weights_info["config"]},
            "parameters": {"tile": tile, "overlap": OVERLAP, "precision": chosen, "colour_match": colour_match}}
    return run, info


def ceilnet(weights: Path | None = None, **options) -> tuple[Run, dict]:
    """The CEILNet baseline (`separate.baselines.ceilnet`), run like the network: tiled, with
    the same options, its weights hash in the manifest."""
    from separate.baselines import ceilnet as module

    run, info = network(weights or module.WEIGHTS, **options)
    if info["weights"]["config"].get("variant") != "ceilnet":
        raise ValueError(f"weights {weights} hold a {info['weights']['config'].get('variant')} network, not CEILNet")
    return run, {**info, "reference": module.__doc__.strip().splitlines()[0]}


def no_separation() -> tuple[Run, dict]:
    """The reference point: T̂ = S0 (the unpolarized image), R̂ = 0."""
    from separate import optics

    def run(images: np.ndarray, angles_deg: list[float]) -> tuple[np.ndarray, np.ndarray]:
        s0 = optics.stokes_from_images(images, np.radians(angles_deg))[0]
        return np.zeros_like(s0), s0

    return run, {"parameters": {}}


def baseline(module_name: str) -> Callable[..., tuple[Run, dict]]:
    """A factory for the baseline in ``separate.baselines.<module_name>``; options are its
    keyword parameters (paper defaults when omitted)."""

    def make(**params) -> tuple[Run, dict]:
        import importlib
        import inspect

        module = importlib.import_module(f"separate.baselines.{module_name}")
        accepted = list(inspect.signature(module.separate).parameters)[2:]
        unknown = sorted(set(params) - set(accepted))
        if unknown:
            raise ValueError(f"unknown parameters {unknown} for {module_name}; expected some of {accepted}")

        def run(images: np.ndarray, angles_deg: list[float]) -> tuple[np.ndarray, np.ndarray]:
            return module.separate(images, angles_deg, **params)

        return run, {"parameters": params, "reference": module.__doc__.strip().splitlines()[0]}

    return make


METHODS: dict[str, Callable[..., tuple[Run, dict]]] = {
    "network": network,
    "none": no_separation,
    "schechner": baseline("schechner"),
    "kong": baseline("kong"),
    "farid": baseline("farid"),
    "li-brown": baseline("li_brown"),
    "arvanitopoulos": baseline("arvanitopoulos"),
    "ceilnet": ceilnet,
}


def get_method(name: str, **options) -> tuple[Run, dict]:
    """The method called ``name`` with its options; ValueError naming the known methods."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; expected one of {sorted(METHODS)}")
    return METHODS[name](**options)
