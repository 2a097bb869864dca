"""Export a training checkpoint as shipped weights plus a model card
(`separate.train.export_weights`).

    python tools/export_weights.py runs/cpu/best.pt separate/weights/urd-canonical.pt [--device "..."]

Weights are stored as float16 (half the size; loaded as float32). The card (same name, .json)
records the training config, steps, patches seen, wall time, device, and the validation figures
logged at that checkpoint. A run started with ``urd train --init W`` is a later training stage:
pass W's card as ``--parent`` (read before the export replaces it, with --force, where OUTPUT is W)
and the card lists every stage and the totals.

An existing OUTPUT or card is replaced only with --force, unless the export leaves both as they
are (the same checkpoint exported again with the same options).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from separate.precision import resolve
from separate.provenance import cpu_model
from separate.train import export_weights, holds_weights, load_checkpoint
from urd.core.errors import UrdError

from toolargs import Formatter


def default_device(train_config: dict) -> str:
    """The card's device line for a checkpoint that does not record it (`separate.train.training_setup`):
    this machine's CPU with the run's precision and threads (from its config)."""
    precision = train_config.get("precision", "auto")
    chosen = resolve(precision).value if precision == "auto" else precision
    compute = "bf16 autocast" if chosen == "bf16" else "fp32"
    if precision == "auto":
        compute += " (precision auto, as resolved on the exporting machine)"
    threads = train_config.get("threads", 0)
    return (f"{cpu_model()} (the machine that exported it), {compute}, "
            + (f"{threads} thread{'s' if threads > 1 else ''}" if threads else "torch's default threads"))


def read_parent(path: Path) -> dict:
    """The parent card at ``path``; a one-line reason (ValueError) when it is not one."""
    try:
        card = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"--parent: {path} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"--parent: {path} is a folder, not a model card (.json)") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"--parent: {path} is not a model card (JSON): {exc}") from None
    except OSError as exc:
        raise ValueError(f"--parent: cannot read {path} ({exc.strerror or exc})") from None
    missing = [key for key in ("weights", "sha256", "training") if not isinstance(card, dict) or key not in card]
    if missing:
        raise ValueError(f"--parent: {path} is not a model card: expected the keys weights, sha256 and training, "
                         f"missing {', '.join(missing)}")
    return card


def unchanged(output: Path, trial: Path) -> bool:
    """Whether ``output`` and its card already hold what the trial export ``trial`` (and its card) holds."""
    card, trial_card = output.with_suffix(".json"), trial.with_suffix(".json")
    if not (output.is_file() and card.is_file()):
        return False
    try:
        old_card = json.loads(card.read_text(encoding="utf-8"))
    except (ValueError, OSError):
        return False
    new_card = json.loads(trial_card.read_text(encoding="utf-8"))
    return holds_weights(output, load_checkpoint(trial)) and {**old_card, "sha256": None} == {**new_card, "sha256": None}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=Formatter)
    parser.add_argument("checkpoint", type=Path, help="the training checkpoint (a run's best.pt or last.pt)")
    parser.add_argument("output", type=Path, help="the weights file to write (.pt); its card goes beside it, as .json")
    parser.add_argument("--device", default=None,
                        help="what the run trained on, for the card (default: what the checkpoint records, "
                             "each training session's GPU or CPU, precision and threads; for checkpoints from before "
                             f"urd recorded it, this machine's CPU, '{cpu_model()} (the machine that exported it)', "
                             "with the precision and threads of the run's config)")
    parser.add_argument("--note", default=None, help="a free-text note for the card (default: none)")
    parser.add_argument("--parent", type=Path, default=None,
                        help="the card (.json) of the weights the run was initialized from, with urd train --init "
                             "(default: none, a run from scratch)")
    parser.add_argument("--force", action="store_true", help="replace an existing OUTPUT and its card")
    args = parser.parse_args()
    output, card = args.output, args.output.with_suffix(".json")
    if output.suffix == ".json":
        parser.error(f"output: expected a weights file name (.pt), got {output}: its card is the .json beside it")
    if output.is_dir():
        parser.error(f"output: {output} is a folder; give a file name in it, e.g. {output / 'weights.pt'}")
    if card.is_dir():
        parser.error(f"output: the card's path {card} is a folder")
    if output.resolve() == args.checkpoint.resolve():
        parser.error(f"output: {output} is the checkpoint itself; choose another file")
    try:
        parent = read_parent(args.parent) if args.parent else None
    except ValueError as exc:
        parser.error(str(exc))
    try:
        state = load_checkpoint(args.checkpoint)
        if not isinstance(state, dict) or not {"model", "model_config", "train_config", "step"} <= state.keys():
            raise SystemExit(f"error: {args.checkpoint} is not a training checkpoint (a run's best.pt or last.pt: "
                             "weights with their training config and step)")
        device = args.device or state.get("trained_on") or default_device(state["train_config"])
        existing = [path for path in (output, card) if path.exists()]
        if existing and not args.force:
            with tempfile.TemporaryDirectory(prefix="urd-export-") as folder:
                trial = Path(folder) / output.name
                export_weights(args.checkpoint, trial, device, args.note or "", parent)
                if not unchanged(output, trial):
                    one = len(existing) == 1
                    raise SystemExit(f"error: {' and '.join(map(str, existing))} {'exists' if one else 'exist'}; remove "
                                     f"{'it' if one else 'them'}, choose another output, or pass --force to replace "
                                     f"{'it' if one else 'them'}")
        result = export_weights(args.checkpoint, output, device, args.note or "", parent)
    except UrdError as exc:
        raise SystemExit(f"error: {exc}") from None
    except OSError as exc:
        raise SystemExit(f"error: cannot write {output} or its card ({exc.strerror or exc})") from None
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
