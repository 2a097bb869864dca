"""Deprecated: moved to `urd.core.progress`; this module re-exports its public names for one release
(urd 0.2 removes it). Import from `urd.core.progress` instead."""

import warnings

from urd.core.progress import *  # noqa: F401,F403 - the re-export is this module's whole job

warnings.warn("urd.progress moved to urd.core.progress; urd 0.2 removes the old name", DeprecationWarning, stacklevel=2)
