"""What a run of the paper's evaluation measures, quick or full (`Settings`, `settings_for`)."""

from __future__ import annotations

import dataclasses

from separate.bench import SEED
from separate.robustness import AXES, ROBUST_SEED

ALL_METHODS = ("none", "network", "direct", "schechner", "kong", "farid", "li-brown", "arvanitopoulos", "ceilnet")
QUICK_METHODS = ("none", "network", "direct", "schechner")
#: Methods timed at 24 MP (full run with ``large``).
LARGE_METHODS = ("network", "schechner")


@dataclasses.dataclass(frozen=True)
class Settings:
    """What a run measures (quick or full; `settings_for`)."""

    quick: bool
    crossval_methods: tuple[str, ...]
    crossval_count: int
    crossval_size: int
    robust_methods: tuple[str, ...]
    robust_count: int
    robust_size: int
    speed_methods: tuple[str, ...]
    speed_shape: tuple[int, int]
    large: bool
    synthesis_count: int
    train_steps: int

    def fingerprint(self) -> dict:
        """Everything that determines the figures (not the speed measurements), for the expected file."""
        axes = {axis.name: [label for label, _ in axis.conditions(self.quick)] for axis in AXES}
        return {"crossval_methods": list(self.crossval_methods), "crossval_count": self.crossval_count,
                "crossval_size": self.crossval_size, "robust_methods": list(self.robust_methods),
                "robust_count": self.robust_count, "robust_size": self.robust_size, "seed": SEED,
                "robust_seed": ROBUST_SEED, "axes": axes}


def settings_for(quick: bool, large: bool = False) -> Settings:
    """The quick run or the full one.

    Quick: none/network/direct/schechner, 12 + 12 cross-validation patches of 256², 10
    robustness patches of 128² at two levels per axis, 1 MP timings; about 4 CPU-minutes
    (6.5-8.5 min wall on 2 shared cores). Full: every method on 64 + 64 cross-validation
    patches (the bsds500-test set is `tools/bench_synthetic.py`'s), 48 robustness patches at
    every level for the polarization methods (none/network/direct/schechner/kong/farid),
    every method timed at 1 MP, and the network and Schechner at 24 MP with ``large``; about half
    an hour on 2 cores (1804 s measured; Kong ~1.1 s per 256² patch, Schechner ~1.2 s, the rest less).
    """
    if quick and large:
        raise ValueError("expected large (24 MP) timings only in the full run, got quick=True, large=True")
    if quick:
        return Settings(True, QUICK_METHODS, 12, 256, QUICK_METHODS, 10, 128, QUICK_METHODS, (816, 1224), False, 24, 6)
    return Settings(False, ALL_METHODS, 64, 256, ("none", "network", "direct", "schechner", "kong", "farid"), 48, 128,
                    ALL_METHODS, (816, 1224), large, 96, 12)
