"""Deprecated: moved to `urd.core.dataset`, `urd.core.files` (atomic files, hashes, locks) and
`urd.core.manifest` (the schema and its checks); this module re-exports their public names for
one release (urd 0.2 removes it). Import from those modules instead."""

import warnings

from urd.core.dataset import *  # noqa: F401,F403 - the re-export is this module's whole job
from urd.core.files import *  # noqa: F401,F403
from urd.core.manifest import *  # noqa: F401,F403

warnings.warn("urd.dataset moved to urd.core.dataset, urd.core.files and urd.core.manifest; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
