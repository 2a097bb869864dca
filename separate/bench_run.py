"""The paper's evaluation (ECCV 2018 §4) reproduced: tables (Markdown, CSV) and plots (PNG).

`run_evaluation` runs three parts and writes them into ``out_dir/quick`` or ``out_dir/full``
(`separate.bench_report`):

1. **Cross-validation** (the paper's Table 1, `separate.crossval`): RMSE, PSNR and SSIM of R̂
   and T̂ for every method on held-out synthetic sets made from photos no shipped model saw in
   training: ``bsds500-test`` (../shared/data; skipped where absent, never replaced),
   scikit-image's bundled photos (``skimage-bundled``) and any folder the user names.
2. **Robustness** (`separate.robustness`): the layers of seeded bsds500/test patches (of the
   bundled photos where bsds500/test is absent; the quick check then skips these figures)
   rendered again under controlled conditions, one factor at a time, on paired data; the
   network − direct T̂ PSNR gap gets a paired bootstrap interval (`separate.bench.paired_gain`).
3. **Speed and memory** (`separate.speed`): each method on a 1-megapixel scene in a fresh
   process (seconds and peak resident memory of the call), synthesis throughput (patches/s)
   and training throughput (steps/s of `separate.train` on a tiny config); 24 MP with ``large``.

Quick mode (`separate.bench_plan.settings_for`) runs a reduced version in minutes and checks its
figures against ``separate/expected-quick.json`` (`separate.bench_check`, tolerances
`separate.bench_check.TOLERANCES`), raising `BenchmarkMismatch` naming every figure out of
tolerance; ``update_expected`` rewrites it. Figures are linear values, peak 1, PSNR floored at
60 dB per patch (`separate.metrics`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from separate.bench_check import (UPDATE_COMMAND, BenchmarkMismatch, TOLERANCES, expected_document, flatten_figures,
                                  verify_expected)
from separate.bench_plan import LARGE_METHODS, settings_for
from separate.bench_report import format_report, write_outputs, write_text
from separate.crossval import cross_validate, photo_pools, synthetic_set
from separate.provenance import REPO, environment
from separate.robustness import AXES, ROBUST_SEED, robustness
from separate.scoring import gap, make_method
from separate.speed import run_isolated, synthesis_throughput, time_method, time_training
from urd.core.progress import Progress

#: Where `urd bench` writes by default: ./urd-bench in the working folder, never the source tree
#: (the project's record in docs/bench is renewed with ``--out docs/bench``).
DEFAULT_OUT = Path("urd-bench")
#: The quick run's expected figures, shipped inside the package (`separate.bench_check`).
EXPECTED_QUICK = Path(__file__).resolve().parent / "expected-quick.json"


def run_evaluation(out_dir: Path, quick: bool, images_dir: Path | None = None, progress: Progress | None = None, *,
                   large: bool = False, update_expected: bool = False, expected_path: Path = EXPECTED_QUICK,
                   command: str | None = None) -> dict:
    """Run the evaluation and write ``tables.md``, CSV files and PNG plots into
    ``out_dir/quick`` or ``out_dir/full``.

    Args:
        out_dir: the output folder (`DEFAULT_OUT`); created when missing.
        quick: the quick run (`settings_for`), checked against ``expected_path``.
        images_dir: a folder of photos (JPEG, PNG, TIFF, 8 or 16 bit) to cross-validate on as
            well; its figures are reported, never checked.
        progress: called with (done, total, label) per patch, label naming the part.
        large: the full run also times `LARGE_METHODS` at 24 MP (6000×4000).
        update_expected: (quick only) write the figures as the new expected values instead of
            checking them.
        expected_path: the expected values of the quick run.
        command: the command line printed in the report (default: this process's).

    Returns:
        A dict: ``environment``, ``settings``, ``figures`` (flat, `flatten_figures`),
        ``crossval_sets`` [(name, description, rows or None)], ``crossval_gaps``,
        ``robustness`` rows, ``robust_gaps``, ``speed``, ``synthesis``, ``training``,
        ``seconds`` per part, ``check`` ({"status", "line", "notes"}), ``files``, ``folder``.

    Raises:
        BenchmarkMismatch: (quick) a figure is out of tolerance or the expected file is
            missing or stale; the outputs are written first.
    """
    if update_expected and not quick:
        raise ValueError("expected update_expected only with quick=True (the expected values are the quick run's)")
    if images_dir is not None and not Path(images_dir).is_dir():
        raise ValueError(f"expected a folder of photos for images_dir, got {images_dir}")
    settings = settings_for(quick, large)
    folder = Path(out_dir) / ("quick" if quick else "full")
    folder.mkdir(parents=True, exist_ok=True)
    env = environment(command)
    seconds: dict[str, float] = {}
    started = time.perf_counter()

    names = list(dict.fromkeys(settings.crossval_methods + settings.robust_methods))
    loaded = {name: make_method(name) for name in names}
    weights = {name: {"file": info["weights"]["file"], "sha256": info["weights"]["sha256"]}
               for name, (_, info) in loaded.items() if name in ("network", "direct")}
    runs = {name: run for name, (run, _) in loaded.items()}

    crossval_sets, crossval_gaps = [], {}
    robust_pool, robust_source = None, ""
    for name, description, pool in photo_pools(images_dir):
        if pool is None:
            crossval_sets.append((name, description, None))
            continue
        if robust_pool is None and name in ("bsds500-test", "skimage-bundled"):
            robust_pool, robust_source = pool, name
        data = synthetic_set(pool, settings.crossval_count, settings.crossval_size)
        rows = cross_validate(data, {m: runs[m] for m in settings.crossval_methods}, progress=progress,
                              label=f"cross-validation {name}")
        crossval_sets.append((name, description, rows))
        baselines = [r for r in rows if r["method"] not in ("none", "network", "direct")]
        pairs = [gap(rows, "network", "direct")]
        if baselines:
            pairs.append(gap(rows, "network", max(baselines, key=lambda r: r["psnr_t"])["method"]))
        crossval_gaps[name] = [g for g in pairs if g]
    seconds["cross-validation"] = time.perf_counter() - started

    mark = time.perf_counter()
    layers = synthetic_set(robust_pool, settings.robust_count, settings.robust_size, seed=ROBUST_SEED)
    robust = robustness(layers, AXES, {m: runs[m] for m in settings.robust_methods}, quick, progress)
    robust_index = {(r["axis"], r["condition"], r["method"]): r for r in robust}
    robust_gaps = []
    for axis in AXES:
        for label, _ in axis.conditions(quick):
            g = gap([r for r in robust if r["axis"] == axis.name and r["condition"] == label])
            if g:
                robust_gaps.append({"axis": axis.name, "condition": label, **g})
    seconds["robustness"] = time.perf_counter() - mark

    mark = time.perf_counter()
    del runs, loaded
    jobs = [(m, *settings.speed_shape) for m in settings.speed_methods]
    if settings.large:
        jobs += [(m, 4000, 6000) for m in LARGE_METHODS]
    speed = []
    for k, (method, height, width) in enumerate(jobs):
        row = {"method": method, "height": height, "width": width}
        try:
            row.update(run_isolated(time_method, (method, height, width)))
        except (RuntimeError, TimeoutError) as exc:
            row["error"] = str(exc).splitlines()[-1]
        speed.append(row)
        if progress:
            progress(k + 1, len(jobs) + 2, "speed")
    synthesis = synthesis_throughput(settings.synthesis_count)
    if progress:
        progress(len(jobs) + 1, len(jobs) + 2, "speed")
    try:
        training = run_isolated(time_training, (settings.train_steps,))
    except (RuntimeError, TimeoutError) as exc:
        training = {"error": str(exc).splitlines()[-1]}
    if progress:
        progress(len(jobs) + 2, len(jobs) + 2, "speed")
    seconds["speed"] = time.perf_counter() - mark
    seconds["total"] = time.perf_counter() - started

    figures = flatten_figures({n: rows for n, _, rows in crossval_sets if rows and not n.startswith("images-")},
                              robust, robust_gaps)
    result = {"environment": env, "settings": settings, "weights": weights, "figures": figures,
              "crossval_sets": crossval_sets, "crossval_gaps": crossval_gaps, "robustness": robust,
              "robust_index": robust_index, "robust_gaps": robust_gaps, "robust_gap_index": {(g["axis"], g["condition"]): g for g in robust_gaps},
              "robust_source": robust_source, "speed": speed, "synthesis": synthesis, "training": training,
              "seconds": seconds, "folder": folder}

    failure = None
    if not quick:
        result["check"] = {"status": "not checked", "line": "Full run: not checked against expected values.", "notes": []}
    elif update_expected:
        write_text(Path(expected_path), json.dumps(expected_document(figures, settings, env, weights, robust_source), indent=1, sort_keys=True) + "\n")
        result["check"] = {"status": "updated", "line": f"Expected values written to `{_display(expected_path)}` ({len(figures)} figures).",
                           "notes": []}
    else:
        absent = [f"crossval/{n}/" for n, _, rows in crossval_sets if rows is None]
        try:
            if not Path(expected_path).is_file():
                raise BenchmarkMismatch(f"no expected values at {expected_path}; make them with: {UPDATE_COMMAND}")
            notes = verify_expected(figures, json.loads(Path(expected_path).read_text()), settings, weights, absent,
                                    source=_display(expected_path), robust_source=robust_source)
            line = f"All figures agree with `{_display(expected_path)}` within the tolerances ({_tolerance_text()})."
            result["check"] = {"status": "passed", "line": " ".join([line] + notes), "notes": notes}
        except BenchmarkMismatch as exc:
            failure = exc
            result["check"] = {"status": "failed", "line": "FAILED:\n\n```\n" + str(exc) + "\n```", "notes": []}
    result["files"] = write_outputs(result, folder)
    write_text(folder / "tables.md", format_report(result))
    if failure is not None:
        raise failure
    return result


def _tolerance_text() -> str:
    """`TOLERANCES` in words, for the report's check line."""
    return ", ".join(f"{kind} ±{value:g}" + (" relative" if how == "rel" else "") for kind, (how, value) in TOLERANCES.items())


def _display(path: Path) -> str:
    """``path`` relative to the repository when inside it, else absolute."""
    path = Path(path).resolve()
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)
