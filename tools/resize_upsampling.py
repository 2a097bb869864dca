"""Turn a network's transposed-convolution up-sampling into resize up-sampling, for fine-tuning.

    python tools/resize_upsampling.py [--weights separate/weights/urd-canonical-transposed.pt] --out runs/resize-init.pt

Writes a weights file (``{"model", "model_config"}``, as `separate.infer.load_model` and
``urd train --init`` read) whose decoder up-samples with `separate.model.ResizeUp` (1×1
convolution + bilinear ×2, initialized with the transposed convolutions' weights averaged over
their four output phases), every other weight kept; prints T̂/R̂ PSNR of both networks on 16
benchmark patches, to show where fine-tuning starts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from separate.bench import run_benchmark
from separate.infer import WEIGHTS_DIR, load_model
from separate.model import with_resize_upsampling
from urd.core.errors import UrdError

from toolargs import Formatter


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("--weights", type=Path, default=WEIGHTS_DIR / "urd-canonical-transposed.pt",
                        help="the network with transposed-convolution up-sampling (.pt)")
    parser.add_argument("--out", type=Path, required=True, help="the weights file to write (.pt; must not exist)")
    args = parser.parse_args()
    if args.out.exists():
        print(f"error: {args.out} exists; remove it or choose another --out", file=sys.stderr)
        return 1
    try:
        model, _ = load_model(args.weights)
        resized = with_resize_upsampling(model)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"model": resized.state_dict(), "model_config": resized.config()}, args.out)
        print(f"wrote {args.out.resolve()}")
        for row in run_benchmark([f"transposed={args.weights}", f"resize={args.out}"], count=16, size=256):
            print(f"{row['method']:12s} T {row['psnr_t']:.2f} dB, R {row['psnr_r']:.2f} dB")
    except UrdError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"error: cannot write {args.out} ({exc.strerror or exc})", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
