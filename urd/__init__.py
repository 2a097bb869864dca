"""urd: capture polarization images through glass and separate reflection from transmission.

The Python API (`urd.api`): `open_dataset`, `separate` → `Layers`, `polarization_maps`.
"""

from urd.api import Layers, open_dataset, polarization_maps, separate
from urd.core import __version__

__all__ = ["Layers", "open_dataset", "polarization_maps", "separate", "__version__"]
