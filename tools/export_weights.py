"""Export a training checkpoint as shipped weights plus a model card
(`separate.train.export_weights`).

    python tools/export_weights.py runs/cpu/best.pt separate/weights/urd-canonical.pt --device "..."

Weights are stored as float16 (half the size; loaded as float32). The card (same name, .json)
records the training config, steps, patches seen, wall time, device, and the validation figures
logged at that checkpoint. A run started with ``urd train --init W`` is a later training stage:
pass W's card as ``--parent`` (read before the export overwrites it) and the card lists every
stage and the totals.
"""

import argparse
import json
from pathlib import Path

from separate.train import export_weights
from urd.core.errors import UrdError

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("checkpoint", type=Path)
parser.add_argument("output", type=Path)
parser.add_argument("--device", default="2-core AMD EPYC CPU (bf16 autocast), 1 thread")
parser.add_argument("--note", default="")
parser.add_argument("--parent", type=Path, help="card of the weights this run was initialized from")
args = parser.parse_args()
try:
    card = export_weights(args.checkpoint, args.output, args.device, args.note,
                          json.loads(args.parent.read_text()) if args.parent else None)
except UrdError as exc:
    raise SystemExit(f"error: {exc}") from None
print(json.dumps(card, indent=2))
