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

from functools import partial
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from urd.core.dataset import Dataset


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
        images: (N, H, W, C) float32 linear shots (or uint16 codes, 65535 = 1.0), N ≥ 3.
        angles_deg: the N polarizer angles (deg).
        method: "network" (default), "schechner", "kong", "farid", "li-brown",
            "arvanitopoulos", "ceilnet" or "none" (`separate.methods.METHODS`).
        reference: "auto" (the glass's s-direction estimated per pixel, or one angle where the
            polarization is weak and of one orientation), "global" (one angle for the view) or an
            angle in degrees.
        options: the method's options, e.g. ``weights``, ``tile``, ``precision`` for the network.

    Returns:
        `Layers` (transmission, reflection).
    """
    from separate.methods import get_method

    run, _ = get_method(method, reference=reference, **options)
    r_hat, t_hat = run(images, [float(a) for a in angles_deg])
    return Layers(t_hat, r_hat)


def polarization_maps(images: np.ndarray, angles_deg: Sequence[float], reference: str | float = "auto",
                      method: str = "schechner") -> dict[str, np.ndarray]:
    """S0, S1, S2 (H×W×C), DoLP, AoLP, φ⊥ and θ (H×W) of a stack (`separate.maps.MAPS`: units;
    DoLP in [0, 1], DoLP and AoLP NaN at dark pixels).

    ``reference`` as in `separate`, chosen the same way (`separate.reference.resolve_reference`):
    the φ⊥ map is the estimated field ("auto"), one estimated angle ("global") or the given
    angle; an assumed side is settled by separating both sides with ``method``: by default the
    classical Schechner inversion (a fraction of a second), "network" for the network's verdict.
    """
    from separate.maps import polarization_maps as maps
    from separate.methods import get_method
    from separate.reference import resolve_reference

    angles = [float(a) for a in angles_deg]
    trial = partial(get_method(method)[0], trial=True) if reference in ("auto", "global") else None
    return maps(images, angles, resolve_reference(images, angles, reference, trial)[1])
