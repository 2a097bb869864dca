"""Multi-seed ablation of the synthesis pipeline (paper §4, the table of Fig. 7): the canonical
network trained on DR, DR+NRD and DR+NRD+LCG at an equal budget (`configs/ablation-*.toml`)
with several seeds, scored on the synthetic benchmark (`separate.bench`, whose test data has
every effect); per pipeline the mean over seeds and the spread between them, and each
pipeline's paired T̂ gain over DR per seed, so that the order can be judged against the noise.

    python tools/ablation.py [--seeds 0 1] [--jobs 2] [--runs runs/ablation] [--out docs/ablation]
                             [--count 64] [--size 256]

Runs that are missing or unfinished are trained first (`urd train CONFIG RUN --seed S`, which
resumes), ``--jobs`` at a time with one thread each. Each run's best checkpoint is then
exported as float16 weights with a model card into OUT/weights, and OUT/ablation.md,
OUT/ablation.csv and OUT/ablation.png are written.
"""

import argparse
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from separate.bench import paired_gain, run_benchmark
from separate.evaluate import cpu_model, git_commit, plot_bars, write_csv, write_text
from separate.train import TrainConfig, load_checkpoint

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = {"DR": "ablation-dr", "DR+NRD": "ablation-dr-nrd", "DR+NRD+LCG": "ablation-dr-nrd-lcg"}

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
parser.add_argument("--jobs", type=int, default=2, help="training runs at a time (one thread each)")
parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "ablation")
parser.add_argument("--out", type=Path, default=ROOT / "docs" / "ablation")
parser.add_argument("--count", type=int, default=64, help="benchmark patches")
parser.add_argument("--size", type=int, default=256, help="benchmark patch size (px)")
args = parser.parse_args()
if len(set(args.seeds)) < 2:
    raise SystemExit("expected at least two different seeds: the spread between seeds is the point")

runs = [(pipeline, seed, ROOT / "configs" / f"{stem}.toml", args.runs / f"{stem.removeprefix('ablation-')}-s{seed}")
        for pipeline, stem in PIPELINES.items() for seed in args.seeds]


def finished(config: Path, run: Path) -> bool:
    """Whether ``run`` holds a checkpoint at the config's last step."""
    last = run / "last.pt"
    return last.exists() and load_checkpoint(last)["step"] >= TrainConfig.from_toml(config).steps


def train(config: Path, run: Path, seed: int) -> None:
    """Train or resume one run; its output goes to RUN.log."""
    run.parent.mkdir(parents=True, exist_ok=True)
    with open(run.with_suffix(".log"), "a") as log:
        subprocess.run([str(Path(sys.executable).with_name("urd")), "train", str(config), str(run), "--seed", str(seed)],
                       stdout=log, stderr=subprocess.STDOUT, check=True)


todo = [(config, run, seed) for _, seed, config, run in runs if not finished(config, run)]
if todo:
    print(f"training {len(todo)} runs, {args.jobs} at a time: {', '.join(r.name for _, r, _ in todo)}", flush=True)
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda job: train(*job), todo))

weights_dir = args.out / "weights"
weights_dir.mkdir(parents=True, exist_ok=True)
labels = {}
for pipeline, seed, _, run in runs:
    target = weights_dir / f"{run.name}.pt"
    subprocess.run([sys.executable, str(ROOT / "tools" / "export_weights.py"), str(run / "best.pt"), str(target),
                    "--device", f"{cpu_model()}, bf16 autocast where native, 1 thread ({args.jobs} runs shared the machine)",
                    "--note", f"ablation {pipeline}, seed {seed} (tools/ablation.py); not shipped"],
                   check=True, stdout=subprocess.DEVNULL)
    labels[(pipeline, seed)] = f"{pipeline}/s{seed}"

started = time.perf_counter()
rows = run_benchmark([f"{labels[(p, s)]}={weights_dir / f'{r.name}.pt'}" for p, s, _, r in runs], args.count, args.size)
by_label = {r["method"]: r for r in rows}
val = {(p, s): load_checkpoint(r / "best.pt")["val"]["psnr_t"] for p, s, _, r in runs}

per_run = []
for pipeline, seed, _, _run in runs:
    r = by_label[labels[(pipeline, seed)]]
    per_run.append([pipeline, seed, f"{r['rmse_t']:.4f}", f"{r['psnr_t']:.2f}", f"{r['ssim_t']:.3f}",
                    f"{r['rmse_r']:.4f}", f"{r['psnr_r']:.2f}", f"{r['ssim_r']:.3f}", f"{val[(pipeline, seed)]:.2f}"])
header = ["pipeline", "seed", "rmse_t", "psnr_t", "ssim_t", "rmse_r", "psnr_r", "ssim_r", "val_psnr_t"]
write_csv(args.out / "ablation.csv", header, per_run)

lines = [f"# Ablation of the synthesis pipeline, {len(args.seeds)} seeds",
         "",
         f"Command: `python tools/ablation.py --seeds {' '.join(map(str, args.seeds))}` (commit {git_commit()}, "
         f"{time.strftime('%Y-%m-%d')}, {cpu_model()}). Each run: `configs/ablation-*.toml` "
         f"({TrainConfig.from_toml(runs[0][2]).steps} steps); benchmark: {args.count} patches of {args.size}² "
         "(seed 2018, full pipeline, reference auto). Weights and cards: `weights/`.",
         "",
         "| pipeline | " + " | ".join(f"T PSNR s{s}" for s in args.seeds) + " | T PSNR mean | seed spread | "
         "R PSNR mean | T SSIM mean | val T PSNR mean |",
         "|---|" + "---|" * (len(args.seeds) + 5)]
for pipeline in PIPELINES:
    t = [by_label[labels[(pipeline, s)]]["psnr_t"] for s in args.seeds]
    r = [by_label[labels[(pipeline, s)]]["psnr_r"] for s in args.seeds]
    ssim = [by_label[labels[(pipeline, s)]]["ssim_t"] for s in args.seeds]
    v = [val[(pipeline, s)] for s in args.seeds]
    lines.append(f"| {pipeline} | " + " | ".join(f"{x:.2f}" for x in t) +
                 f" | {np.mean(t):.2f} | {max(t) - min(t):.2f} | {np.mean(r):.2f} | {np.mean(ssim):.3f} | {np.mean(v):.2f} |")
lines += ["", "Paired T̂ PSNR gain over the same seed's DR run (mean over patches, 95% bootstrap interval):", "",
          "| pipeline | " + " | ".join(f"seed {s}" for s in args.seeds) + " |", "|---|" + "---|" * len(args.seeds)]
for pipeline in list(PIPELINES)[1:]:
    cells = []
    for s in args.seeds:
        g = paired_gain(rows, labels[(pipeline, s)], labels[("DR", s)])
        cells.append(f"{g['mean']:+.2f} ({g['ci95'][0]:+.2f} to {g['ci95'][1]:+.2f})")
    lines.append(f"| {pipeline} | " + " | ".join(cells) + " |")
lines += ["", "Same pipeline, other seed (the noise of one training run): T̂ PSNR difference between seeds "
          + ", ".join(f"{p} {by_label[labels[(p, args.seeds[1])]]['psnr_t'] - by_label[labels[(p, args.seeds[0])]]['psnr_t']:+.2f} dB"
                      for p in PIPELINES) + f" (seed {args.seeds[1]} − seed {args.seeds[0]})."]
write_text(args.out / "ablation.md", "\n".join(lines) + "\n")
plot_bars(args.out / "ablation.png", list(PIPELINES),
          {f"seed {s}": [by_label[labels[(p, s)]]["psnr_t"] for p in PIPELINES] for s in args.seeds},
          "Ablation: T PSNR on the synthetic benchmark", "T PSNR (dB)", "training pipeline")
print("\n".join(lines))
print(f"\nscored in {time.perf_counter() - started:.0f} s; wrote {args.out}")
