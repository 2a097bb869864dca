"""urd's Python API: open a dataset, take a scene's stack, separate it, get arrays back.

    import urd
    ds = urd.open_dataset("dataset")
    images, angles_deg = ds.scene("scene_01").load_stack()
    layers = urd.separate(images, angles_deg)                 # the network, reference estimated
    layers.transmission, layers.reflection                    # H×W×C float32, linear

Conventions as everywhere in urd: images float32, linear (1.0 = sensor white), (N, H, W, C)
stacks; angles in degrees, from the image's +x axis, counter-clockwise. `docs/api.md` shows a
whole script (``docs/examples/separate_scene.py``).
"""

from __future__ import annotations

import numbers
import warnings
from functools import partial
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from urd.core.dataset import Dataset
from urd.core.errors import RawFormatError
from urd.core.images import check_float_scale


class Layers(NamedTuple):
    """A separation: ``transmission`` T̂ and ``reflection`` R̂, each H×W×C float32 linear, T̂ + R̂ ≈ S0."""

    transmission: np.ndarray
    reflection: np.ndarray


def open_dataset(root: str | Path) -> Dataset:
    """An existing urd dataset (`urd.core.dataset.Dataset`); DatasetError when ``root`` holds none."""
    return Dataset.open(Path(root))


def separate(images: np.ndarray, angles_deg: Sequence[float], method: str = "network",
             reference: str | float = "auto", **options) -> Layers:
    """Separate an aligned polarization stack into transmission and reflection.

    Args:
        images: (N, H, W, C) float32 linear shots (or uint16 / uint8 codes, 65535 / 255 = 1.0),
            N ≥ 3, C 1 (grey) or 3 (RGB).
        angles_deg: the N polarizer angles (deg).
        method: "network" (default), "schechner", "kong", "farid", "li-brown",
            "arvanitopoulos", "ceilnet" or "none" (`separate.methods.METHODS`).
        reference: "auto" (the glass's s-direction estimated per pixel, or one angle where the
            polarization is weak and of one orientation), "global" (one angle for the view) or an
            angle in degrees.
        options: the method's options, e.g. ``weights``, ``tile``, ``precision`` for the network.

    Returns:
        `Layers` (transmission, reflection).

    Raises:
        TypeError, ValueError: a stack or angles urd cannot separate (`separate.presentation.check_stack`),
            float values on another scale than 0.0 = black and 1.0 = white, an unknown method or option.

    The warnings `urd separate` prints about the stack (clipped pixels, identical shots, too
    little polarization, an assumed side of the reference) are issued as ``UserWarning``.
    """
    from separate.methods import get_method, sees_polarization_of, separate_inspected

    angles = checked_stack(images, angles_deg)
    run, info = get_method(method, reference=reference, **options)
    r_hat, t_hat, inspection, _ = separate_inspected(images, angles, run, reference, sees_polarization_of(info))
    for message in inspection.warnings:
        warnings.warn(message, UserWarning, stacklevel=2)
    return Layers(t_hat, r_hat)


def checked_stack(images: np.ndarray, angles_deg: Sequence[float]) -> list[float]:
    """The angles (deg) as floats, once the stack and its angles are ones urd can separate
    (`separate.presentation.check_stack`) and float values are on urd's scale, 0.0 black and 1.0
    white (`urd.core.images.check_float_scale`, as for image files); TypeError or ValueError."""
    from separate.presentation import check_stack

    try:
        given = None if isinstance(angles_deg, (str, bytes)) else list(angles_deg)
    except TypeError:
        given = None
    if given is None or not all(isinstance(a, numbers.Real) and not isinstance(a, (bool, np.bool_)) for a in given):
        raise TypeError(f"expected the polarizer angles as a sequence of numbers in degrees, one per shot, got {angles_deg!r}")
    angles = [float(a) for a in given]
    check_stack(images, angles)
    if images.dtype.kind == "f":
        try:
            check_float_scale(images, "16-bit codes: pass them as uint16, or divide by 65535")
        except RawFormatError as exc:                       # a file's error class; an array's is a ValueError
            raise ValueError(str(exc)) from None
    return angles


def polarization_maps(images: np.ndarray, angles_deg: Sequence[float], reference: str | float = "auto",
                      method: str = "schechner") -> dict[str, np.ndarray]:
    """S0, S1, S2 (H×W×C), DoLP, AoLP, φ⊥ and θ (H×W) of a stack (`separate.maps.MAPS`: units;
    DoLP in [0, 1], DoLP and AoLP NaN at dark pixels).

    ``reference`` as in `separate`, chosen the same way (`separate.reference.resolve_reference`):
    the φ⊥ map is the estimated field ("auto"), one estimated angle ("global") or the given
    angle; an assumed side is settled by separating both sides with ``method``: by default the
    classical Schechner inversion (a fraction of a second; the network's side trial is the same).
    The warnings about the stack are issued as in `separate`.
    """
    from separate.maps import polarization_maps as maps
    from separate.methods import check_reference, get_method, sees_polarization_of
    from separate.reference import resolve_reference

    angles = checked_stack(images, angles_deg)
    reference = check_reference(reference)
    run, info = get_method(method)
    if not sees_polarization_of(info):
        raise ValueError(f"method {method!r} sees only S0, so its trial separations cannot tell the two sides of the "
                         "reference apart; settle the side with 'schechner' (the default), 'kong', 'farid' or 'network'")
    trial = partial(run, trial=True) if reference in ("auto", "global") else None
    inspection, chosen = resolve_reference(images, angles, reference, trial)
    for message in inspection.warnings:
        warnings.warn(message, UserWarning, stacklevel=2)
    return maps(images, angles, chosen)
