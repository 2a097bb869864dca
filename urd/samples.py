"""Deprecated: moved to `urd.core.samples`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.samples` instead."""

import warnings

from urd.core.samples import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.samples moved to urd.core.samples; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
