#!/usr/bin/env bash
# One call on a lent GPU machine (the device tool's `run`, ../shared/docs/GPU.md), prepared here:
#   1. what the machine has (GPU, torch, packages);
#   2. urd separate on the GPU: tools/bench_24mp.py (a 24 MP scene of the simulated rig, ingest,
#      two separations, --device auto: the GPU), then urd demo's scene on the GPU and again with
#      --device cpu, and the two T.tiff compared;
#   3. the training configs of $CONFIGS side by side (default configs/gpu-semireal-a.toml and -b.toml,
#      $WORKERS synthesis processes each), from the shipped weights, with snapshots of each run's
#      weights every $SNAPSHOT_S s;
#   4. back under $OUT (at most 8 files: two configs): session.log, each run's console log and
#      log.jsonl, and each run's snapshots, last and best checkpoints as float16 weights in one file
#      (RUN-snapshots.pt: a dict of checkpoints without their optimizer state, each one a file
#      tools/export_weights.py reads once saved alone).
# Before the call, here: python tools/gpu_pool.py (the training data, ~50 MB, in .pool) and the
# rawpy and pyserial wheels in .whl (the device README says how); carry .pool and .whl. The tree
# that travels and both must stay within the device's 64 MiB: move the tracked files the call does
# not read (docs/bench/ablation*/weights, docs/report, the weights other than urd-anchored.pt and
# urd-canonical.pt, ~35 MB) out of the tree for the call, and back after it.
# There:  bash tools/gpu_session.sh
# Here, to try it on the CPU in about 2 minutes:
#   OUT=/tmp/gpu-out MINUTES=0.5 WORKERS=1 BENCH_SIZE=1536x1024 bash tools/gpu_session.sh
set -u
OUT=${OUT:?set OUT to the folder that comes back}
MINUTES=${MINUTES:-5.5}
WORKERS=${WORKERS:-7}
BENCH_SIZE=${BENCH_SIZE:-6000x4000}
SNAPSHOT_S=${SNAPSHOT_S:-75}
CONFIGS=${CONFIGS:-configs/gpu-semireal-a.toml configs/gpu-semireal-b.toml}
RUNS=$(for config in $CONFIGS; do basename "$config" .toml; done | xargs)
export RUNS
export PYTHONUNBUFFERED=1
LOG=$OUT/session.log
mkdir -p "$OUT"
say() { echo "== $(date +%T) $*" | tee -a "$LOG"; }

say "1. the machine"
if ! python3 -c "import rawpy, serial" 2>/dev/null && compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
if [ ! -e ../shared/data ] && [ -d .pool ]; then mkdir -p ../shared && ln -s "$PWD/.pool" ../shared/data; fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | tee -a "$LOG"
python3 - 2>&1 <<'EOF' | tee -a "$LOG"
import os, torch, numpy, cv2, rawpy, serial, tifffile, typer, skimage
from separate.provenance import cpu_model
print(f"torch {torch.__version__}, CUDA {torch.cuda.is_available()}, numpy {numpy.__version__}, cv2 {cv2.__version__}, "
      f"rawpy {rawpy.__version__}; CPU {cpu_model()}, {os.cpu_count()} cores")
EOF

say "2. separation on the GPU: tools/bench_24mp.py --size $BENCH_SIZE --runs 2"
timeout 150 python3 tools/bench_24mp.py --size "$BENCH_SIZE" --runs 2 --folder /tmp/urd-bench 2>&1 | tee -a "$LOG"
rm -rf /tmp/urd-bench
say "urd demo (device auto), then its scene again with --device cpu"
timeout 60 python3 -m urd.cli demo /tmp/urd-demo 2>&1 | grep -v "\[" | tee -a "$LOG"
cp /tmp/urd-demo/scene_01/results/network/T.tiff /tmp/T-auto.tiff
for device in cuda cpu; do
  say "urd separate scene_01 --device $device --force"
  begun=$EPOCHREALTIME
  timeout 60 python3 -m urd.cli separate scene_01 --dataset /tmp/urd-demo --device $device --force 2>&1 \
    | grep -v "\[" | tee -a "$LOG"
  say "wall $(python3 -c "print(f'{$EPOCHREALTIME - $begun:.2f}')") s"
  cp /tmp/urd-demo/scene_01/results/network/T.tiff /tmp/T-$device.tiff
done
python3 - 2>&1 <<'EOF' | tee -a "$LOG"
import numpy as np, tifffile
from separate.metrics import psnr
t = {d: tifffile.imread(f"/tmp/T-{d}.tiff").astype(np.float32) / 65535 for d in ("cuda", "cpu")}
diff = np.abs(t["cuda"] - t["cpu"])
print(f"T.tiff, cuda against cpu (codes / 65535): PSNR {psnr(t['cuda'], t['cpu']):.2f} dB, "
      f"largest difference {diff.max():.2e}, mean {diff.mean():.2e}")
EOF

say "3. training: $RUNS, $MINUTES minutes, $WORKERS synthesis processes each"
mkdir -p /tmp/snaps
pids=()
for config in $CONFIGS; do
  run=$(basename "$config" .toml)
  sed -e "s/^max_minutes = .*/max_minutes = $MINUTES/" -e "s/^schedule_minutes = .*/schedule_minutes = $MINUTES/" \
      -e "s/^workers = .*/workers = $WORKERS/" "$config" > "/tmp/gpu-$run.toml"
  rm -rf "runs/$run"
  timeout $(( ${MINUTES%.*} * 60 + 120 )) python3 -m urd.cli train "/tmp/gpu-$run.toml" "runs/$run" --init separate/weights/urd-anchored.pt > "$OUT/$run.log" 2>&1 &
  pids+=($!)
done
started=$SECONDS
next=$SNAPSHOT_S
while kill -0 "${pids[@]}" 2>/dev/null; do
  sleep 2
  if (( SECONDS - started >= next )); then
    for run in $RUNS; do
      [ -f "runs/$run/last.pt" ] && cp "runs/$run/last.pt" "/tmp/snaps/$run-$(printf %04d $((SECONDS - started))).pt"
    done
    next=$((next + SNAPSHOT_S))
  fi
done
wait
for run in $RUNS; do tail -3 "$OUT/$run.log" | tee -a "$LOG"; cp "runs/$run/log.jsonl" "$OUT/$run-log.jsonl"; done

say "4. snapshots"
python3 - 2>&1 <<'EOF' | tee -a "$LOG"
import glob, os, torch
for run in os.environ["RUNS"].split():
    paths = sorted(glob.glob(f"/tmp/snaps/{run}-[0-9][0-9][0-9][0-9].pt")) + [f"runs/{run}/last.pt", f"runs/{run}/best.pt"]
    states = {}
    for path in paths:
        state = torch.load(path, map_location="cpu", weights_only=True)
        state.pop("optim", None)
        state["model"] = {k: v.half() for k, v in state["model"].items()}
        states[os.path.basename(path)] = state
    torch.save(states, f"{os.environ['OUT']}/{run}-snapshots.pt")
    print(run, {name: s["step"] for name, s in states.items()})
EOF
say "done"
