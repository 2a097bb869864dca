"""Deprecated: moved to `urd.core.mosaic`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.mosaic` instead."""

import warnings

from urd.core.mosaic import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.mosaic moved to urd.core.mosaic; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
