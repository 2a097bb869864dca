"""Deprecated: the paper's evaluation, re-exported for one release; import from separate.<new> instead.

It now lives in one module per job:

* `separate.bench_run`: `run_evaluation`, the driver (``DEFAULT_OUT``, ``EXPECTED_QUICK``);
* `separate.bench_plan`: what a quick or full run measures (`Settings`, `settings_for`);
* `separate.crossval`: held-out photo sets and cross-validation (the paper's Table 1);
* `separate.robustness`: controlled conditions (`Condition`, `AXES`) and the robustness study;
* `separate.speed`: speed, memory and throughput in fresh processes;
* `separate.scoring`: scoring a method's R̂ and T̂ (`score`, `attempt`, `gap`, `make_method`);
* `separate.bench_check`: the quick run's expected figures and their check (`BenchmarkMismatch`);
* `separate.bench_report`: ``tables.md``, CSV and PNG outputs, atomic text and CSV writers;
* `separate.plots`: OpenCV line and bar plots;
* `separate.provenance`: what a result depends on (`environment`, `cpu_model`, `git_commit`).

Names are re-exported with ``import X as X``, the explicit re-export form.
"""

from __future__ import annotations

from separate.bench_check import (
    EXPECTED_SCHEMA as EXPECTED_SCHEMA,
    TOLERANCES as TOLERANCES,
    UPDATE_COMMAND as UPDATE_COMMAND,
    BenchmarkMismatch as BenchmarkMismatch,
    check_figures as check_figures,
    expected_document as expected_document,
    flatten_figures as flatten_figures,
    tolerance_for as tolerance_for,
    verify_expected as verify_expected,
)
from separate.bench_plan import (
    ALL_METHODS as ALL_METHODS,
    LARGE_METHODS as LARGE_METHODS,
    QUICK_METHODS as QUICK_METHODS,
    Settings as Settings,
    settings_for as settings_for,
)
from separate.bench_report import format_report as format_report, write_csv as write_csv, write_text as write_text
from separate.bench_run import DEFAULT_OUT as DEFAULT_OUT, EXPECTED_QUICK as EXPECTED_QUICK, run_evaluation as run_evaluation
from separate.crossval import (
    MAX_SIDE as MAX_SIDE,
    PHOTO_SUFFIXES as PHOTO_SUFFIXES,
    cross_validate as cross_validate,
    load_photo as load_photo,
    load_photos as load_photos,
    photo_pools as photo_pools,
    synthetic_set as synthetic_set,
    to_pool_image as to_pool_image,
)
from separate.plots import (
    PALETTE as PALETTE,
    nice_ticks as nice_ticks,
    plot_bars as plot_bars,
    plot_lines as plot_lines,
    write_png as write_png,
)
from separate.provenance import REPO as REPO, cpu_model as cpu_model, environment as environment, git_commit as git_commit
from separate.robustness import (
    AXES as AXES,
    MAX_SHOTS as MAX_SHOTS,
    NOISE_GAINS as NOISE_GAINS,
    ROBUST_SEED as ROBUST_SEED,
    Axis as Axis,
    Condition as Condition,
    Draws as Draws,
    Noise as Noise,
    draw_nuisances as draw_nuisances,
    render_condition as render_condition,
    robustness as robustness,
    shift_image as shift_image,
)
from separate.scoring import SCORES as SCORES, attempt as attempt, gap as gap, make_method as make_method, score as score
from separate.speed import (
    ISOLATED_TIMEOUT_S as ISOLATED_TIMEOUT_S,
    run_isolated as run_isolated,
    speed_stack as speed_stack,
    synthesis_throughput as synthesis_throughput,
    time_method as time_method,
    time_training as time_training,
)
from urd.core.progress import Progress as Progress
