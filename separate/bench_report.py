"""Writing a run of the paper's evaluation: ``tables.md`` (Markdown), CSV files and PNG plots, atomically."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Sequence

from separate.bench import SEED, format_table
from separate.bench_check import weights_line
from separate.plots import plot_bars, plot_lines
from separate.robustness import AXES
from urd.core.files import atomic_path


def write_text(path: Path, text: str) -> None:
    """Write a text file atomically."""
    with atomic_path(Path(path), overwrite=True) as tmp:
        tmp.write_text(text)


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence]) -> None:
    """Write a CSV file (floats with 6 significant digits) atomically."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in row])
    write_text(path, buffer.getvalue())


def _robust_cell(row: dict | None) -> str:
    """A robustness table cell: T̂ / R̂ PSNR (dB) and the refusals; a dash where not measured."""
    if row is None:
        return "–"
    cell = f"{row['psnr_t']:.2f} / {row['psnr_r']:.2f}"
    return cell + (f" ({row['failed']} of {len(row['psnr_t_per_patch'])} refused)" if row["failed"] else "")


def _gap_cell(g: dict | None) -> str:
    """A paired gap (dB): mean, 95% interval and wins over patches; a dash where there is none."""
    if g is None:
        return "–"
    return f"{g['mean']:+.2f} ({g['ci95'][0]:+.2f} to {g['ci95'][1]:+.2f}), {g['wins']}/{g['count']}"


def format_report(result: dict) -> str:
    """The Markdown report (``tables.md``) of a `run_evaluation` result."""
    env, settings = result["environment"], result["settings"]
    mode = "quick" if settings.quick else "full"
    lines = [f"# urd evaluation ({mode})", "",
             f"* command: `{env['command']}`",
             f"* commit: {env['commit']}",
             f"* date: {env['date']}",
             f"* CPU: {env['cpu']}, {env['cores']} cores; torch {env['torch']}, {env['torch_threads']} threads; "
             f"capability flags: {' '.join(env['flags']) or 'none reported'}",
             f"* precision (auto): {env['precision_note']}",
             f"* weights: {weights_line(result['weights'])}",
             "* runtime: " + ", ".join(f"{k} {v:.0f} s" for k, v in result["seconds"].items()),
             "", "Linear values, peak 1, PSNR floored at 60 dB per patch; means over patches. Every method picks its "
             "reference itself (\"auto\"). Gaps are paired per patch: mean, 95% bootstrap interval, patches where the "
             "first method scores higher.", ""]
    lines += ["## 1. Cross-validation on held-out synthetic sets (paper Table 1)", "",
              f"{settings.crossval_count} patches of {settings.crossval_size}² per set (seed {SEED}), the full synthesis "
              "pipeline (DR + NRD + LCG, the paper's angles with ±4° errors, sensor noise); the methods get the nominal "
              "angles 0/45/90. No shipped model saw these photos (training: bsds500/train + sunhays80; validation: "
              "bsds500/val).", ""]
    for name, description, rows in result["crossval_sets"]:
        lines += [f"### {name}: {description}", ""]
        if rows is None:
            lines += ["Not measured: the photos are not on this machine.", ""]
            continue
        lines += [format_table(rows), ""]
        lines += [f"* {r['method']} refused {r['failed']} of {len(r['psnr_t_per_patch'])} patches (left out of its means): "
                  f"{r['failure']}" for r in rows if r["failed"]]
        for g in result["crossval_gaps"].get(name, []):
            lines.append(f"* T PSNR {g['a']} − {g['b']}: {_gap_cell(g)} patches")
        lines.append("")
    lines += ["## 2. Robustness", "",
              f"{settings.robust_count} patches of {settings.robust_size}² ({result['robust_source']}, seed {SEED + 1}): "
              "the synthesizer's layers rendered again with `separate.optics`, one factor varied at a time from the "
              "base condition (exact angles 0/45/90, no misalignment, medium noise, φ⊥ − φ0 ~ U[−45°, 45°] per patch, "
              "no non-rigid deformation); every condition of a patch shares its random draws. Cells: T̂ / R̂ PSNR (dB).", ""]
    methods = list(settings.robust_methods)
    for axis in AXES:
        levels = axis.conditions(settings.quick)
        refusals: dict[str, str] = {}
        lines += [f"### {axis.title}", "",
                  "| " + axis.x_title + " | " + " | ".join(methods) + " | T network − direct (interval), wins |",
                  "|---|" + "---|" * (len(methods) + 1)]
        for label, _ in levels:
            cells = []
            for m in methods:
                row = result["robust_index"].get((axis.name, label, m))
                if row and row["failed"]:
                    refusals.setdefault(m, row["failure"])
                cells.append(_robust_cell(row))
            lines.append(f"| {label} | " + " | ".join(cells) + f" | {_gap_cell(result['robust_gap_index'].get((axis.name, label)))} |")
        lines += [""] + [f"* {m} refused some patches (means over the rest; gaps over patches both accepted): {msg}"
                         for m, msg in refusals.items()] + ([""] if refusals else [])
    lines += ["## 3. Speed and memory", "",
              f"One call per method on a {settings.speed_shape[1]}×{settings.speed_shape[0]} scene (three shots), each "
              "in a fresh process, first call (setup included); peak resident memory from just before the call (input "
              "stack, weights and interpreter included; the baseline in brackets). Other load on the machine slows them.", "",
              "| method | size | seconds | peak RSS (MB) |", "|---|---|---|---|"]
    for row in result["speed"]:
        size = f"{row['width']}×{row['height']}"
        if "error" in row:
            lines.append(f"| {row['method']} | {size} | failed: {row['error']} | |")
        else:
            lines.append(f"| {row['method']} | {size} | {row['seconds']:.2f} | {row['peak_rss_mb']:.0f} ({row['rss_before_mb']:.0f}) |")
    lines += ["", "| throughput | figure |", "|---|---|"]
    for row in result["synthesis"]:
        lines.append(f"| synthesis, {row['size']}² patches, full pipeline, angles {row['mode']} | "
                     f"{row['patches_per_s']:.1f} patches/s ({row['rejected']} rejected draws) |")
    t = result["training"]
    if "error" in t:
        lines.append(f"| training | failed: {t['error']} |")
    else:
        lines.append(f"| training, {t['patch']}² × {t['batch']} patches, {t['threads']} thread, {t['precision']} "
                     f"({t['steps_timed']} steps timed) | {t['steps_per_s']:.2f} steps/s ({t['patches_per_s']:.1f} patches/s) |")
    lines += ["", "## Check", "", result["check"]["line"], ""]
    lines += ["## Files", "", ", ".join(f"`{f}`" for f in result["files"]), ""]
    return "\n".join(lines)


def write_outputs(result: dict, folder: Path) -> list[str]:
    """Write a `run_evaluation` result's CSV files and PNG plots into ``folder``; returns the file
    names, ``tables.md`` (written by the caller, `format_report`) last."""
    settings = result["settings"]
    files = []

    def name(file: str) -> Path:
        files.append(file)
        return folder / file

    crossval_rows, patch_rows, gap_rows = [], [], []
    for set_name, _, rows in result["crossval_sets"]:
        for row in rows or []:
            crossval_rows.append([set_name, row["method"], settings.crossval_count, settings.crossval_size, row["failed"],
                                  *(row[k] for k in ("rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r", "ssim_r", "seconds_per_patch"))])
            patch_rows += [[set_name, row["method"], i, t, r] for i, (t, r) in enumerate(zip(row["psnr_t_per_patch"], row["psnr_r_per_patch"]))]
        for g in result["crossval_gaps"].get(set_name, []):
            gap_rows.append([set_name, g["a"], g["b"], g["mean"], g["ci95"][0], g["ci95"][1], g["wins"], g["count"]])
    write_csv(name("crossval.csv"), ["set", "method", "patches", "size", "refused", "rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r",
                                     "ssim_r", "seconds_per_patch"], crossval_rows)
    write_csv(name("crossval_patches.csv"), ["set", "method", "patch", "psnr_t", "psnr_r"], patch_rows)
    write_csv(name("crossval_gaps.csv"), ["set", "a", "b", "mean_db", "ci95_lo", "ci95_hi", "wins", "patches"], gap_rows)
    write_csv(name("robustness.csv"), ["axis", "condition", "method", "patches", "refused", "psnr_t", "psnr_r"],
              [[r["axis"], r["condition"], r["method"], len(r["psnr_t_per_patch"]), r["failed"], r["psnr_t"], r["psnr_r"]]
               for r in result["robustness"]])
    write_csv(name("robustness_gaps.csv"), ["axis", "condition", "a", "b", "mean_db", "ci95_lo", "ci95_hi", "wins", "patches"],
              [[g["axis"], g["condition"], g["a"], g["b"], g["mean"], g["ci95"][0], g["ci95"][1], g["wins"], g["count"]]
               for g in result["robust_gaps"]])
    write_csv(name("speed.csv"), ["method", "width", "height", "seconds", "peak_rss_mb", "rss_before_mb"],
              [[r["method"], r["width"], r["height"], r.get("seconds", float("nan")), r.get("peak_rss_mb", float("nan")),
                r.get("rss_before_mb", float("nan"))] for r in result["speed"]])
    t = result["training"]
    write_csv(name("throughput.csv"), ["what", "figure", "unit"],
              [[f"synthesis {r['mode']} {r['size']}px", r["patches_per_s"], "patches/s"] for r in result["synthesis"]]
              + ([["training 64px x16", t["steps_per_s"], "steps/s"]] if "steps_per_s" in t else []))

    measured = [(n, d, rows) for n, d, rows in result["crossval_sets"] if rows]
    if measured:
        methods = [r["method"] for r in measured[0][2]]
        for layer, title in (("t", "T"), ("r", "R")):
            by_set = {n: {r["method"]: r[f"psnr_{layer}"] for r in rows} for n, _, rows in measured}
            plot_bars(name(f"crossval_psnr_{layer}.png"), methods,
                      {n: [by_set[n].get(m, float("nan")) for m in methods] for n in by_set},
                      f"Cross-validation: {title} PSNR per method and held-out set", f"{title} PSNR (dB)", "method")
    for axis in AXES:
        labels = [label for label, _ in axis.conditions(settings.quick)]
        series = {m: [result["robust_index"][(axis.name, lb, m)]["psnr_t"] for lb in labels] for m in settings.robust_methods}
        plot_lines(name(f"robustness_{axis.name}.png"), labels, series, f"Robustness ({axis.name}): T PSNR",
                   axis.x_title, "T PSNR (dB)")
    gaps = result["robust_gaps"]
    if gaps:
        letters = {axis.name: axis.letter for axis in AXES}
        labels = [f"{letters[g['axis']]}: {g['condition']}" for g in gaps]
        plot_lines(name("robustness_gap.png"), labels, {"network - direct": [g["mean"] for g in gaps]},
                   "T PSNR network - direct per condition, 95% bootstrap interval", "axis (a-f, see tables.md): condition",
                   "gap (dB)",
                   intervals={"network - direct": [g["ci95"] for g in gaps]}, size=(max(900, 75 * len(gaps) + 300), 540),
                   zero_line=True, connect=False)
    files.append("tables.md")
    return files
