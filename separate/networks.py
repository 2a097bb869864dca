"""Networks by config: the one place that knows every trainable architecture.

`build_model` turns a network's ``config()`` (as stored in weights files and checkpoints) back
into a module: the separation network of `separate.model` (variants "canonical" and
"direct") or the CEILNet baseline (`separate.baselines.ceilnet`, variant "ceilnet"). It lives
here, above both, so that the network does not import its baselines.
"""

from __future__ import annotations

from torch import nn

from separate.baselines.ceilnet import CEILNet
from separate.model import VARIANTS, SeparationNet


def build_model(config: dict) -> nn.Module:
    """A network from its ``config()``: SeparationNet for variant "canonical" or "direct"
    (the default), CEILNet for "ceilnet"; ValueError naming the known variants otherwise."""
    variant = config.get("variant", "canonical")
    if variant == "ceilnet":
        return CEILNet(**{k: v for k, v in config.items() if k != "variant"})
    if variant not in VARIANTS:
        raise ValueError(f"expected a network variant in {VARIANTS + ('ceilnet',)}, got {variant!r}")
    return SeparationNet(**config)
