"""Deprecated: moved to `urd.core.raw`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.raw` instead."""

import warnings

from urd.core.raw import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.raw moved to urd.core.raw; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
