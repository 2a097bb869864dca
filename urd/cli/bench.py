"""``urd bench``: the methods scored on data with ground truth (a quick table, the paper's evaluation,
the ablation, the semi-real and the virtual-camera sets)."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Optional

import typer

from urd.cli.common import bad, given, parse_seeds, run_guarded, usage, within
from urd.core.progress import TerminalProgress


def bench(
    ctx: typer.Context,
    quick: bool = typer.Option(False, "--quick", help="The paper's evaluation, reduced (< 10 min on 2 cores): tables, CSV and plots in OUT/quick, checked against the expected figures shipped with urd (separate/expected-quick.json)."),
    full: bool = typer.Option(False, "--full", help="The paper's full evaluation (20-50 min on 2 cores): cross-validation, robustness, speed into OUT/full."),
    large: bool = typer.Option(False, "--24mp", help="With --full: also time the network and Schechner on a 24 MP scene."),
    images: Optional[Path] = typer.Option(None, help="With --quick/--full: also cross-validate on the photos of this folder (JPEG, PNG, 8/16-bit TIFF)."),
    out: Optional[Path] = typer.Option(None, help="With --quick/--full/--ablation/--semireal/--virtual: output folder (default: ./urd-bench; the project's record: --out docs/bench)."),
    count: int = typer.Option(64, callback=within(1), help="Benchmark patches (seeded, from bsds500/test or bundled photos)."),
    size: int = typer.Option(256, callback=within(32), help="Patch size (px)."),
    methods: str = typer.Option("none,network", help="Comma-separated methods, plus 'direct' for the direct variant (shipped urd-direct.pt or --direct-weights), and LABEL=PATH for the network with other weights."),
    direct_weights: Optional[Path] = typer.Option(None, help="With 'direct' in --methods: weights of the direct variant (default: the shipped urd-direct.pt)."),
    ablation: bool = typer.Option(False, "--ablation", help="The paper's pipeline ablation (DR, DR+NRD, DR+NRD+LCG) with several seeds: trains the runs missing from --runs (configs/ablation-*.toml, about 1 h of CPU each), scores them on --count patches, writes OUT/ablation; needs a source checkout (its configs/)."),
    seeds: str = typer.Option("0,1", help="With --ablation: comma-separated training seeds (at least two)."),
    jobs: int = typer.Option(2, callback=within(1), help="With --ablation: training runs side by side (one thread each)."),
    runs: Optional[Path] = typer.Option(None, help="With --ablation: folder of the training runs (unfinished ones resume; default runs/ablation, or runs/ablation-STEPS with --steps)."),
    steps: Optional[int] = typer.Option(None, callback=within(1), help="With --ablation: training steps of every run (default: the configs' 4000; e.g. 16000 on a GPU); its runs in runs/ablation-STEPS and its report in OUT/ablation-STEPS."),
    semireal: bool = typer.Option(False, "--semireal", help="The semi-real set: held-out real captures without glass (../shared/data/polarization) as the transmitted layer behind a rendered pane reflecting a bsds500/test photo, exact ground truth; 3, 4 and 6 shots, mono, and the no-glass R share; every method of --methods (default none, Schechner, Kong, Farid, network; LABEL=PATH adds the network with other weights); tables in OUT/semireal. About 15 min on 2 cores."),
    weights: Optional[Path] = typer.Option(None, help="With --semireal: the network's weights (default: shipped)."),
    virtual: bool = typer.Option(False, "--virtual", help="The virtual-camera set: flat panes rendered by urd's virtual camera at angles of incidence 20-75 deg and a wide view (phi_perp turning 50 deg), the network against Schechner, Kong, Farid and no separation (4 photo pairs of 768x512; --methods to choose); tables in OUT/virtual."),
) -> None:
    """Benchmark the methods on synthetic data with ground truth: by default one table of RMSE /
    PSNR / SSIM of R and T per method (with network and direct: their paired T PSNR difference);
    with --quick or --full the paper's tables, robustness study and speed figures; with
    --ablation the multi-seed pipeline ablation. One mode (--quick, --full, --ablation,
    --semireal, --virtual) per run.

    \b
    Example:
      urd bench --methods none,schechner,network --count 16
      urd bench --quick
      urd bench --virtual
    """
    if large and not full:
        raise usage("--24mp goes with --full")
    modes = [flag for flag, on in (("--quick", quick), ("--full", full), ("--ablation", ablation),
                                   ("--semireal", semireal), ("--virtual", virtual)) if on]
    if len(modes) > 1:
        raise usage(f"{' or '.join(modes)}, not both" if len(modes) == 2 else f"{', '.join(modes)}: one of them per run")
    mode = bool(modes)
    unused = [f"--{name.replace('_', '-')}" for name in ("out",) if not mode and given(ctx, name)]
    unused += [f"--{name.replace('_', '-')}" for name in ("images",) if not (quick or full) and given(ctx, name)]
    unused += [f"--{name.replace('_', '-')}" for name in ("methods", "count", "size", "direct_weights")
               if (quick or full) and given(ctx, name)]
    unused += [f"--{name.replace('_', '-')}" for name in ("methods", "direct_weights") if ablation and given(ctx, name)]
    if not mode and direct_weights is not None and "direct" not in methods.split(","):
        unused.append("--direct-weights")
    if unused:
        raise usage(f"{', '.join(unused)}: not used by this run (see each option's help for the modes it goes with)")
    if given(ctx, "methods"):
        from separate.methods import METHODS

        if not [m for m in methods.split(",") if m]:
            raise bad("--methods", f"expected at least one method, got {methods!r}")
        known = sorted(METHODS) + ["direct"]
        unknown = [m for m in methods.split(",") if m and "=" not in m and m not in known]
        if unknown:
            raise bad("--methods", f"unknown {', '.join(map(repr, unknown))}; expected some of {', '.join(known)}, "
                                   "or LABEL=PATH for the network with other weights")
    if (semireal or virtual) and given(ctx, "methods") and any(m == "direct" or ("=" in m and virtual) for m in methods.split(",")):
        raise bad("--methods", "--virtual takes the methods by name, --semireal those and LABEL=PATH; 'direct' is for "
                               "the plain benchmark")
    if semireal:
        if given(ctx, "count") or given(ctx, "size"):
            raise usage("--semireal goes alone (with --methods, --weights and --out): it has its own scenes")
        bench_semireal(methods if given(ctx, "methods") else None, weights, out)
        return
    if weights is not None:
        raise usage("--weights goes with --semireal")
    if virtual:
        if given(ctx, "count") or given(ctx, "size"):
            raise usage("--virtual goes alone (with --methods and --out): it has its own scenes")
        bench_virtual(methods if given(ctx, "methods") else None, out)
        return
    if not ablation and (seeds != "0,1" or jobs != 2 or runs is not None or steps is not None):
        raise usage("--seeds, --jobs, --runs and --steps go with --ablation")
    if ablation:
        from separate.ablation import ablation_runs, check_budgets, run_ablation
        from separate.bench_run import DEFAULT_OUT

        seed_list = parse_seeds(seeds)
        check_size(size)
        runs = runs or Path("runs/ablation" + (f"-{steps}" if steps else ""))
        run_guarded(check_budgets, run_guarded(ablation_runs, seed_list, runs, steps=steps))   # before making folders
        folder = writable((out or DEFAULT_OUT) / ("ablation" + (f"-{steps}" if steps else "")))
        bar = TerminalProgress()
        result = run_guarded(run_ablation, folder, runs, seed_list, jobs, count, size,
                             progress=lambda done, total: bar(done, total, "ablation training runs"),
                             command=" ".join(["urd"] + sys.argv[1:]), steps=steps)
        bar.close()
        typer.echo(Path(result["files"][0]).read_text())
        typer.echo(f"table, CSV, plot and weights in {folder.resolve()}")
        return
    if quick or full:
        from separate.bench_run import DEFAULT_OUT, run_evaluation

        writable((out or DEFAULT_OUT) / ("quick" if quick else "full"))
        result = run_guarded(run_evaluation, out or DEFAULT_OUT, quick, images, progress=TerminalProgress(),
                             large=large, command=" ".join(["urd"] + sys.argv[1:]))
        typer.echo(f"tables, CSV and plots in {Path(result['folder']).resolve()}")
        return
    from separate.bench import format_paired, format_table, run_benchmark

    check_size(size)
    rows = run_guarded(run_benchmark, [m for m in methods.split(",") if m], count, size, direct_weights)
    typer.echo(format_table(rows))
    if {"network", "direct"} <= {r["method"] for r in rows}:
        typer.echo(format_paired(rows, "network", "direct"))


def bench_semireal(methods: Optional[str], weights: Optional[Path], out: Optional[Path]) -> None:
    """``urd bench --semireal``: print the tables and write them, with the per-scene figures, into OUT/semireal."""
    import json

    from separate.bench_run import DEFAULT_OUT
    from separate.semireal import DEFAULT_METHODS, run_semireal
    from urd.core.files import write_bytes_atomic

    chosen = tuple(methods.split(",")) if methods else DEFAULT_METHODS
    folder = writable((out or DEFAULT_OUT) / "semireal")
    bar = TerminalProgress()
    tables, records = run_guarded(run_semireal, chosen, weights, progress=bar)
    bar.close()
    typer.echo(tables)                                   # shown first: a folder gone or a disk full loses no result
    run_guarded(write_bytes_atomic, folder / "tables.md", tables.encode(), overwrite=True)
    run_guarded(write_bytes_atomic, folder / "scenes.json", json.dumps(records, indent=1).encode(), overwrite=True)
    typer.echo(f"wrote {(folder / 'tables.md').resolve()} and scenes.json")


def bench_virtual(methods: Optional[str], out: Optional[Path]) -> None:
    """``urd bench --virtual``: print the tables and write them into OUT/virtual/tables.md."""
    from separate.bench_run import DEFAULT_OUT
    from urd.core.files import write_bytes_atomic
    from urd.virtual_bench import DEFAULT_METHODS, run_virtual_bench

    chosen = tuple(methods.split(",")) if methods else DEFAULT_METHODS
    folder = writable((out or DEFAULT_OUT) / "virtual")
    bar = TerminalProgress()
    tables = run_guarded(run_virtual_bench, chosen, progress=bar)
    bar.close()
    typer.echo(tables)                                   # shown first: a folder gone or a disk full loses no result
    run_guarded(write_bytes_atomic, folder / "tables.md", tables.encode(), overwrite=True)
    typer.echo(f"wrote {(folder / 'tables.md').resolve()}")


def check_size(size: int) -> None:
    """A usage error naming --size when the benchmark's photos are too small for ``size`` (px) patches."""
    from separate.bench import largest_size

    largest = largest_size()
    if size > largest:
        raise bad("--size", f"expected at most {largest} px (the shorter side of the benchmark's test photos), got {size}")


def writable(folder: Path) -> Path:
    """``folder``, made where missing, once a file can be written in it: checked before a run of
    minutes to hours, not after it; a usage error naming --out otherwise."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise bad("--out", f"cannot write in {folder} ({exc.strerror or exc}); choose another folder") from None
    return folder
