"""Deprecated: moved to `urd.core.images`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.images` instead."""

import warnings

from urd.core.images import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.images moved to urd.core.images; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
