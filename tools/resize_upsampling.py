"""Turn a network's transposed-convolution up-sampling into resize up-sampling, for fine-tuning.

    python tools/resize_upsampling.py [--weights separate/weights/urd-canonical-transposed.pt] --out runs/resize-init.pt

Writes a weights file (``{"model", "model_config"}``, as `separate.infer.load_model` and
``urd train --init`` read) whose decoder up-samples with `separate.model.ResizeUp` (1×1
convolution + bilinear ×2, initialized with the transposed convolutions' weights averaged over
their four output phases), every other weight kept; prints T̂/R̂ PSNR of both networks on 16
benchmark patches, to show where fine-tuning starts.
"""

import argparse
from pathlib import Path

import torch

from separate.bench import run_benchmark
from separate.infer import WEIGHTS_DIR, load_model
from separate.model import with_resize_upsampling

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--weights", type=Path, default=WEIGHTS_DIR / "urd-canonical-transposed.pt")
parser.add_argument("--out", type=Path, required=True)
args = parser.parse_args()
if args.out.exists():
    raise SystemExit(f"{args.out} exists; remove it or choose another --out")
model, _ = load_model(args.weights)
resized = with_resize_upsampling(model)
args.out.parent.mkdir(parents=True, exist_ok=True)
torch.save({"model": resized.state_dict(), "model_config": resized.config()}, args.out)
print(f"wrote {args.out.resolve()}")
for row in run_benchmark([f"transposed={args.weights}", f"resize={args.out}"], count=16, size=256):
    print(f"{row['method']:12s} T {row['psnr_t']:.2f} dB, R {row['psnr_r']:.2f} dB")
