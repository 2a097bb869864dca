"""Deprecated: moved to `urd.core.errors`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.errors` instead."""

import warnings

from urd.core.errors import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.errors moved to urd.core.errors; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
