"""urd: capture polarization images through glass and separate reflection from transmission.

The Python API (`urd.api`): `open_dataset`, `separate` → `Layers`, `polarization_maps`.
"""

__version__ = "0.1.0"

from urd.api import Layers, open_dataset, polarization_maps, separate  # noqa: E402 - the version first: urd.dataset reads it

__all__ = ["Layers", "open_dataset", "polarization_maps", "separate", "__version__"]
