"""Deprecated: moved to `urd.core.align`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.align` instead."""

import warnings

from urd.core.align import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.align moved to urd.core.align; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
