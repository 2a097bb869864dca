"""Deprecated: moved to `urd.core.dataset`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.dataset` instead."""

import warnings

from urd.core.dataset import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.dataset moved to urd.core.dataset; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
