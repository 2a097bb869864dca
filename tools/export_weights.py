"""Export a training checkpoint as shipped weights plus a model card.

    python tools/export_weights.py runs/cpu/best.pt separate/weights/urd-canonical.pt --device "..."

Weights are stored as float16 (half the size; loaded as float32). The card (same name, .json)
records the training config, steps, patches seen, wall time, device, and the validation figures
logged at that checkpoint. A run started with ``urd train --init W`` is a later training stage:
pass W's card as ``--parent`` (read before the export overwrites it) and the card lists every
stage and the totals.
"""

import argparse
import hashlib
import json
from pathlib import Path

import torch

from separate.train import load_checkpoint

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("checkpoint", type=Path)
parser.add_argument("output", type=Path)
parser.add_argument("--device", default="2-core AMD EPYC CPU (bf16 autocast), 1 thread")
parser.add_argument("--note", default="")
parser.add_argument("--parent", type=Path, help="card of the weights this run was initialized from")
args = parser.parse_args()
parent = json.loads(args.parent.read_text()) if args.parent else None

state = load_checkpoint(args.checkpoint)
if parent is not None and state.get("init") and state["init"]["sha256"] != parent["sha256"]:
    raise SystemExit(f"--parent {args.parent} does not describe the weights the run started from ({state['init']['path']})")
args.output.parent.mkdir(parents=True, exist_ok=True)
torch.save({"model": {k: v.half() for k, v in state["model"].items()}, "model_config": state["model_config"]}, args.output)
cfg = state["train_config"]
card = {
    "weights": args.output.name,
    "sha256": hashlib.sha256(args.output.read_bytes()).hexdigest(),
    "model": state["model_config"],
    "parameters": sum(v.numel() for v in state["model"].values()),
    "training": {"config": cfg, "steps": state["step"], "patches_seen": state["step"] * cfg["batch"],
                 "wall_time_s": round(state.get("wall_s", 0.0)), "device": args.device,
                 "data": "synthesized from bsds500/train + sunhays80 (../shared/data/natural), pipeline "
                         + cfg["pipeline"]},
    "validation": state.get("val"),
    "initialized_from": state.get("init") or (parent and {"path": parent["weights"], "sha256": parent["sha256"]}),
    "note": args.note,
}
if parent is not None:
    stages = parent.get("stages", [parent["training"]]) + [card["training"]]
    card["stages"] = stages
    card["total"] = {key: sum(s[key] for s in stages) for key in ("steps", "patches_seen", "wall_time_s")}
args.output.with_suffix(".json").write_text(json.dumps(card, indent=2) + "\n")
print(json.dumps(card, indent=2))
