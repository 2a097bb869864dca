"""Separation methods by name: the network and the classical baselines share one interface.

``get_method(name, reference="auto", **options)`` returns ``(run, info)``:
``run(images, angles_deg, reference_deg=None, trial=False)`` maps an aligned stack (N, H, W, C) float32
linear, or its uint16 codes (`separate.optics.code_scale`; the network converts them a tile at a
time, the baselines all at once), and its N ≥ 3 polarizer angles (deg) to (R̂, T̂), each H×W×C
float32 linear; ``trial=True`` makes it the side decision's trial separation
(`separate.reference.decide_side`): silent, and for a fresnel network without its gate; ``info``
describes the method, its parameters and its reference policy for the manifest.

Reference policy of the polarization methods (network, schechner, kong, farid): the shots are
re-rendered at reference + 0/45/90° (`separate.presentation.present`, from the least-squares
Stokes fit of all N shots; the network's tiles are presented one by one inside
`separate.infer.separate_stack`) and the method reads φ⊥ within ±45° of the reference. The reference
is ``reference_deg`` when ``run`` is given one (a number, or an H×W map in degrees, which
presents each pixel at its own reference: `separate.presentation.present_field`); otherwise the
method's ``reference`` option: "auto" estimates the glass's s-direction per pixel, a smooth
field (`separate.reference.estimate_reference_field`), "global" one angle for the whole view
(`separate.reference.estimate_reference_deg`), a number (deg) forces it. The methods that see only the unpolarized
image S0 (none, li-brown, arvanitopoulos, ceilnet) take and ignore the reference: S0 is the
same for every presentation, so they skip it (and its full-resolution copy).
"""

from __future__ import annotations

import inspect
import math
import numbers
from functools import partial
from pathlib import Path
from types import ModuleType
from typing import Callable

import numpy as np

from separate import optics
from separate.incidence import estimate_incidence
from separate.reference import Inspection, resolve_reference
from separate.presentation import present, present_field

Run = Callable[..., tuple[np.ndarray, np.ndarray]]
Reference = str | float
#: The estimated references: a per-pixel field, or one angle for the view.
ESTIMATED = ("auto", "global")


def check_reference(reference: Reference) -> Reference:
    """``reference`` as "auto", "global" or a float (deg) from any finite real number (NumPy's
    included, bool not); ValueError otherwise."""
    if isinstance(reference, np.ndarray) and reference.ndim == 0:
        reference = reference.item()
    if isinstance(reference, str):
        if reference in ESTIMATED:
            return reference
        raise ValueError(f"expected reference 'auto', 'global' or an angle in degrees, got {reference!r}")
    if isinstance(reference, bool) or not isinstance(reference, numbers.Real) or not math.isfinite(reference):
        raise ValueError(f"expected reference 'auto', 'global' or a finite angle in degrees, got {reference!r}")
    return float(reference)


def reference_policy(reference: Reference) -> str:
    """The reference policy of a polarization method, as recorded in its ``info``."""
    if reference == "auto":
        return ("auto: the glass's s-direction estimated per pixel from the shots, a smooth field (separate.reference), "
                "or one angle where the polarization is weak and of one orientation; each pixel presented at it + 0/45/90 deg")
    if reference == "global":
        return "global: one s-direction estimated from the shots (separate.reference); shots presented at it + 0/45/90 deg"
    return f"fixed: {reference:g} deg; shots presented at it + 0/45/90 deg"


def chooser(reference: Reference) -> Callable[..., float | np.ndarray]:
    """A function (images, angles_deg, reference_deg, trial) → the reference to present at (deg,
    a number or an H×W map): ``reference_deg`` if given, else ``reference`` chosen as every
    separation in urd chooses it (`separate.reference.resolve_reference`; ``trial``, the
    method's own silent run, settles an assumed side)."""
    reference = check_reference(reference)

    def choose(images: np.ndarray, angles_deg: list[float], reference_deg: float | np.ndarray | None,
               trial: Run) -> float | np.ndarray:
        if reference_deg is not None:
            return reference_deg if np.ndim(reference_deg) == 2 else float(reference_deg)
        return resolve_reference(images, angles_deg, reference, trial)[1]

    return choose


def present_at(images: np.ndarray, angles_deg: list[float], reference: float | np.ndarray) -> tuple[np.ndarray, list[float]]:
    """`present` at one reference (deg) or `present_field` at an H×W map of them."""
    if np.ndim(reference) == 2:
        return present_field(images, angles_deg, reference)
    return present(images, angles_deg, float(reference))


def network(weights: Path | None = None, tile: int | None = None, precision: str = "auto", colour_match: bool = False,
            progress=None, reference: Reference = "auto", uses_reference: bool = True,
            return_copies: bool = True, incidence_deg: float | None = None, device: str = "auto") -> tuple[Run, dict]:
    """The paper's network (`separate.model`) with shipped or given weights, tiled
    (`separate.infer.separate_stack`, ``tile`` px, default `separate.infer.default_tile`, rounded down
    by `separate.tiling.check_tiling` and recorded as used) on
    ``device`` (auto, cpu or cuda: `separate.precision.resolve_device`); the
    shots presented at the reference unless ``uses_reference`` is False (a network that sees only S0,
    `ceilnet`; CEILNet's weights are refused otherwise);
    with ``return_copies`` the part of R̂ that copies T̂ moved back into T̂ (`separate.copies`).
    A physics-anchored network takes the angle of incidence ``incidence_deg`` (deg) where given,
    else estimates it per pixel from each stack; the returned info's ``"incidence"`` records the
    last run's (`separate.incidence.Incidence.record`).
    Its side decision's trial separations (``trial=True``) are Schechner's closed-form inversion:
    on the assumed-side stacks of 600 bsds500/val patches the network's T̂ was 32.94 dB with them
    against 31.78 with its own backbone's (bsds500-test: 33.89 against 33.38)."""
    from separate.copies import return_copies as returned
    from separate.infer import default_tile, load_model, match_histograms, separate_stack
    from separate.tiling import OVERLAP, check_tiling
    from separate.precision import resolve, resolve_device

    for option, value in (("colour_match", colour_match), ("return_copies", return_copies), ("uses_reference", uses_reference)):
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"expected {option} True or False, got {value!r}")
    if incidence_deg is not None and (isinstance(incidence_deg, (bool, np.bool_)) or not isinstance(incidence_deg, numbers.Real)):
        raise TypeError(f"expected an angle of incidence in (0, 90) deg as a number, got {incidence_deg!r}")
    if incidence_deg is not None and not 0 < incidence_deg < 90:
        raise ValueError(f"expected an angle of incidence in (0, 90) deg, got {incidence_deg!r}")
    target = resolve_device(device)
    model, weights_info = load_model(weights)
    name = Path(weights_info["file"]).name
    if uses_reference and weights_info["config"].get("variant") == "ceilnet":
        raise ValueError(f"weights {name} hold CEILNet, not the polarization network: use the method 'ceilnet' for them")
    anchored = getattr(model, "base", "canonical") == "fresnel"
    if incidence_deg is not None and not anchored:
        raise ValueError(f"an angle of incidence is for a physics-anchored network (urd-anchored), not {name}")
    tile = check_tiling(default_tile(model, target, precision) if tile is None else tile, OVERLAP)[0]
    chosen = resolve(precision, target).value
    choose = chooser(reference)
    side_trial = METHODS["schechner"]()[0]

    def run(images: np.ndarray, angles_deg: list[float], reference_deg: float | np.ndarray | None = None,
            trial: bool = False) -> tuple[np.ndarray, np.ndarray]:
        if trial:
            return side_trial(images, angles_deg, reference_deg, trial=True)
        # separate_stack presents the shots tile by tile (no second full-size stack)
        chosen_deg = choose(images, angles_deg, reference_deg, partial(run, trial=True)) if uses_reference else None
        incidence = incidence_deg
        if anchored and incidence_deg is None:
            incidence = estimate_incidence(images, angles_deg, angles_deg[0] if chosen_deg is None else chosen_deg)
            info["incidence"] = incidence.record()
        elif anchored:
            info["incidence"] = {"median_deg": incidence_deg, "range_deg": [incidence_deg, incidence_deg],
                                 "given": True, "gate": True}
        r_hat, t_hat = separate_stack(model, images, list(angles_deg), tile, OVERLAP, chosen, progress,
                                      reference_deg=chosen_deg, theta_deg=incidence, device=target)
        if return_copies:
            r_hat, t_hat = returned(r_hat, t_hat)
        if colour_match:
            darkest = int(np.argmin([shot.mean(dtype=np.float64) for shot in images]))
            t_hat = match_histograms(t_hat, 2.0 * optics.to_float(images[darkest]))    # the shot in S0's units
        return r_hat, t_hat

    info = {"weights": {"file": name, "sha256": weights_info["sha256"],
                        "config": weights_info["config"]},
            "parameters": {"tile": tile, "overlap": OVERLAP, "precision": chosen, "colour_match": colour_match,
                           "return_copies": return_copies, **({"incidence_deg": incidence_deg} if anchored else {}),
                           **({"device": target.type} if target.type != "cpu" else {})},
            "reference_policy": reference_policy(check_reference(reference)) if uses_reference else "not used: S0 only"}
    return run, info


def citation(module) -> str:
    """A baseline's citation: the first paragraph of its module docstring, on one line."""
    return " ".join(module.__doc__.strip().split("\n\n")[0].split())


def ceilnet(weights: Path | None = None, reference: Reference = "auto", tile: int | None = None, precision: str = "auto",
            colour_match: bool = False, progress=None, device: str = "auto") -> tuple[Run, dict]:
    """The CEILNet baseline (`separate.baselines.ceilnet`), run like the network: tiled, with
    the network's options that apply to it, its weights hash in the manifest; it sees only S0."""
    from separate.baselines import ceilnet as module

    check_reference(reference)
    run, info = network(weights or module.WEIGHTS, tile, precision, colour_match, progress, uses_reference=False,
                        return_copies=False, device=device)
    if info["weights"]["config"].get("variant") != "ceilnet":
        raise ValueError(f"weights {weights} hold a {info['weights']['config'].get('variant')} network, not CEILNet: "
                         "use the method 'network' for them")

    def clipped(*args, **kwargs) -> tuple[np.ndarray, np.ndarray]:    # R̂ = S0 − T̂ goes below 0: no light is
        return tuple(np.maximum(layer, 0.0, out=layer) for layer in run(*args, **kwargs))

    return clipped, {**info, "paper": citation(module)}


def no_separation(reference: Reference = "auto") -> tuple[Run, dict]:
    """The reference point: T̂ = S0 (the unpolarized image), R̂ = 0."""
    check_reference(reference)

    def run(images: np.ndarray, angles_deg: list[float], reference_deg: float | np.ndarray | None = None,
            trial: bool = False, rows: int = 256) -> tuple[np.ndarray, np.ndarray]:
        s0 = np.empty(images.shape[1:], np.float32)           # a block of rows at a time: codes stay codes
        for y in range(0, images.shape[1], rows):
            s0[y : y + rows] = optics.stokes_from_images(optics.to_float(images[:, y : y + rows]), np.radians(angles_deg))[0]
        return np.zeros_like(s0), s0

    return run, {"parameters": {}, "reference_policy": "not used: S0 only"}


def check_param(module: ModuleType, name: str, value: object, default: object) -> int | float | None:
    """``value`` of the baseline ``module``'s parameter ``name``, of its ``default``'s type: an
    integer (NumPy's included) for an int, as int; a finite real number for a float, as float, or
    also None for None; within the module's ``PARAM_RANGES[name]``. ValueError naming the
    parameter, its type and range otherwise."""
    method = module.__name__.rsplit(".", 1)[1]
    if default is None and value is None:
        return None
    integer = isinstance(default, int)
    number = not isinstance(value, bool) and isinstance(value, numbers.Integral if integer else numbers.Real)
    if number and (integer or math.isfinite(value)) and value in module.PARAM_RANGES[name]:
        return int(value) if integer else float(value)
    kind = "an integer" if integer else "a finite number"
    none = " or null" if default is None else ""
    raise ValueError(f"expected {method} parameter {name} to be {kind} {module.PARAM_RANGES[name]}{none}, got {value!r}")


def baseline(module_name: str, s0_only: bool) -> Callable[..., tuple[Run, dict]]:
    """A factory for the baseline in ``separate.baselines.<module_name>``; options are its
    keyword parameters (paper defaults when omitted; each checked when the method is made,
    `check_param`), ``reference`` and ``progress`` (called with
    (done, total) where the baseline reports progress; not a recorded parameter). Polarization baselines
    get the shots presented at the reference; S0-only ones get them as they are. Their layers come
    back clipped at 0, as the network's do and as the result files hold them (the side trial's
    separations, ``trial=True``, keep the inversion's negative values: the side decision reads them)."""

    def make(reference: Reference = "auto", progress: Callable[[int, int], None] | None = None,
             **params) -> tuple[Run, dict]:
        import importlib
        import inspect

        module = importlib.import_module(f"separate.baselines.{module_name}")
        defaults = {name: parameter.default for name, parameter in list(inspect.signature(module.separate).parameters.items())[2:]
                    if name != "progress"}
        unknown = sorted(set(params) - set(defaults))
        if unknown:
            raise ValueError(f"unknown parameters {unknown} for {module_name}; expected some of {list(defaults)}")
        params = {name: check_param(module, name, value, defaults[name]) for name, value in params.items()}
        choose = chooser(reference)
        reports = {"progress": progress} if progress is not None and "progress" in inspect.signature(module.separate).parameters else {}

        def run(images: np.ndarray, angles_deg: list[float], reference_deg: float | np.ndarray | None = None,
                trial: bool = False) -> tuple[np.ndarray, np.ndarray]:
            said = {} if trial else reports                           # trial separations report no progress
            if s0_only:
                layers = module.separate(optics.to_float(images), list(angles_deg), **params, **said)
            else:
                chosen = choose(images, angles_deg, reference_deg, partial(run, trial=True))
                shots, angles = present_at(images, angles_deg, chosen)
                layers = module.separate(shots, angles, **params, **said)
            return layers if trial else tuple(np.maximum(layer, 0.0) for layer in layers)   # no negative light, as the network

        policy = "not used: S0 only" if s0_only else reference_policy(check_reference(reference))
        return run, {"parameters": params, "paper": citation(module), "reference_policy": policy}

    return make


#: The methods that run a network (torch; tiles, precision, device).
NETWORKS = ("network", "ceilnet")

METHODS: dict[str, Callable[..., tuple[Run, dict]]] = {
    "network": network,
    "none": no_separation,
    "schechner": baseline("schechner", s0_only=False),
    "kong": baseline("kong", s0_only=False),
    "farid": baseline("farid", s0_only=False),
    "li-brown": baseline("li_brown", s0_only=True),
    "arvanitopoulos": baseline("arvanitopoulos", s0_only=True),
    "ceilnet": ceilnet,
}


#: The methods that see S0 alone: a reference angle does not change their layers.
S0_ONLY = ("none", "li-brown", "arvanitopoulos", "ceilnet")


def sees_polarization_of(info: dict) -> bool:
    """Whether a method (its ``info`` from `get_method`) uses the polarization, and so a reference
    angle; the single-image methods see S0 only."""
    return not str(info.get("reference_policy", "")).startswith("not used")


def separate_inspected(images: np.ndarray, angles: list[float], run, reference: str | float,
                       sees_polarization: bool = True) -> tuple[np.ndarray, np.ndarray, Inspection, float | np.ndarray]:
    """Inspect the stack and choose the reference as every separation in urd does
    (`separate.reference.resolve_reference`: for "auto" the estimated field, or the estimated
    angle where the polarization is weak and of one orientation; for "global" the estimated
    angle; or the given angle; an assumed side settled by separating both sides with
    ``run(..., trial=True)``, unless the method does not ``sees_polarization``), then run the method there.

    Returns:
        R̂, T̂, the inspection, and the reference used (deg: a field on the reduced grid, or an angle).
    """
    trial = partial(run, trial=True) if sees_polarization else None      # silent, a fresnel network ungated
    inspection, chosen = resolve_reference(images, angles, reference, trial)
    r_hat, t_hat = run(images, angles, chosen)
    return r_hat, t_hat, inspection, inspection.field if np.ndim(chosen) == 2 else chosen


def get_method(name: str, reference: Reference = "auto", **options) -> tuple[Run, dict]:
    """The method called ``name`` with its options and reference policy ("auto", "global" or degrees);
    ValueError naming the known methods, the bad reference, or an option the method does not take."""
    if not isinstance(name, str) or name not in METHODS:
        raise ValueError(f"unknown method {name!r}; expected one of {sorted(METHODS)}")
    factory = METHODS[name]
    parameters = inspect.signature(factory).parameters
    taken = {p for p, kind in parameters.items() if kind.kind is not kind.VAR_KEYWORD} - {"reference", "uses_reference"}
    unknown = sorted(set(options) - taken)          # uses_reference: how `ceilnet` runs the network, not an option
    if unknown and not any(p.kind is p.VAR_KEYWORD for p in parameters.values()):      # a baseline checks its own
        raise ValueError(f"unknown options {unknown} for {name}; expected some of {sorted(taken)}")
    if "uses_reference" in options:
        raise ValueError(f"unknown options ['uses_reference'] for {name}; expected some of {sorted(taken)}")
    return factory(reference=check_reference(reference), **options)
