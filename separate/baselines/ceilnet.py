"""Fan, Yang, Hua, Chen & Wipf, "A generic deep architecture for single image reflection
removal and image smoothing" (CEILNet), ICCV 2017 — re-implemented and trained by urd.

A single-image method: it sees only the unpolarized image S0. Two cascaded networks:

1. E-CNN maps S0 and its edge map E(S0) to the edge map of the transmission layer;
2. I-CNN maps S0 and that predicted edge map to the transmission image T̂.

The edge map is Fan et al.'s: E(I)(x) = ¼ Σ_c Σ_{4 neighbours y} |I_c(x) − I_c(y)|. Both
networks share Fan et al.'s shape — a full-resolution convolution, a stride-2 convolution,
residual blocks at half resolution, a stride-2 transposed convolution back and an output
convolution — trained jointly with ℓ2 losses on the edge map, the image and its gradients.

Deviations, for a CPU budget: 32 channels and 6 residual blocks per network (Fan et al.: 64
channels, 13 blocks, batch normalization); I-CNN predicts a correction to S0 rather than T̂
itself; both networks trained together from the start rather than in two phases; training
data from urd's synthesis pipeline (paper §3.3) instead of Fan et al.'s blurred-reflection
synthesis. The reflection is the remainder R̂ = S0 − T̂ (urd's layers add up to S0).
Weights: ``separate/weights/ceilnet.pt`` (trained with ``configs/ceilnet.toml``); run through
`separate.methods` (``urd separate --method ceilnet``), tiled like the network.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from separate import optics
from separate.model import NOMINAL_ANGLES, TARGET_MEAN, ResBlock, check_obs

WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "ceilnet.pt"


def edge_map(image: torch.Tensor) -> torch.Tensor:
    """Fan et al.'s edge map: (B, C, H, W) → (B, 1, H, W), the mean absolute difference to the
    4 neighbours summed over channels (replicated borders)."""
    padded = F.pad(image, (1, 1, 1, 1), mode="replicate")
    centre = padded[..., 1:-1, 1:-1]
    diffs = [padded[..., 1:-1, :-2], padded[..., 1:-1, 2:], padded[..., :-2, 1:-1], padded[..., 2:, 1:-1]]
    return sum((centre - d).abs() for d in diffs).sum(dim=1, keepdim=True) / 4


class _Stage(nn.Module):
    """One CEILNet network: conv, stride-2 conv, residual blocks, stride-2 transposed conv, conv."""

    def __init__(self, n_in: int, n_out: int, width: int, blocks: int):
        super().__init__()
        self.head = nn.Conv2d(n_in, width, 3, padding=1)
        self.down = nn.Conv2d(width, width, 3, stride=2, padding=1)
        self.body = nn.Sequential(*[ResBlock(width) for _ in range(blocks)])
        self.up = nn.ConvTranspose2d(width, width, 4, stride=2, padding=1)
        self.tail = nn.Conv2d(width, n_out, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.down(F.relu(self.head(x))))
        return self.tail(F.relu(self.up(self.body(x))))


class CEILNet(nn.Module):
    """Edge-then-image reflection removal from the unpolarized image.

    Args:
        width: channels of each network.
        blocks: residual blocks of each network.
        channels: colour channels.
    """

    def __init__(self, width: int = 32, blocks: int = 6, channels: int = 3):
        super().__init__()
        self.width, self.blocks, self.channels = width, blocks, channels
        self.edge_net = _Stage(channels + 1, 1, width, blocks)
        self.image_net = _Stage(channels + 1, channels, width, blocks)

    def config(self) -> dict:
        return {"variant": "ceilnet", "width": self.width, "blocks": self.blocks, "channels": self.channels}

    def forward(self, obs: torch.Tensor, angles: Sequence[float] = NOMINAL_ANGLES,
                scale: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """Separate a batch using only its unpolarized image.

        Args:
            obs: (B, N, C, H, W) linear shots at ``angles`` (rad), N ≥ 3, any H, W.
            angles: polarizer angles (rad), used to form S0.
            scale: (B,) exposure scale; default mean(S0) per sample.

        Returns:
            (R̂, T̂) in the units of ``obs``; in training mode also Ê (B, 1, H, W), the predicted
            edge map of the transmission, for `loss`.
        """
        check_obs(obs)
        with torch.autocast(obs.device.type, enabled=False):      # the optics stay float32 under bf16
            s0 = optics.stokes_from_images(obs.float().transpose(0, 1), angles)[0]
        if scale is None:
            scale = s0.mean(dim=(1, 2, 3)).clamp_min(1e-6)
        gain = (TARGET_MEAN / scale).view(-1, 1, 1, 1).to(obs.dtype)
        h, w = s0.shape[-2:]
        x = F.pad(s0 * gain, (0, w % 2, 0, h % 2), mode="replicate")
        e_hat = self.edge_net(torch.cat([x, edge_map(x)], dim=1))
        t_hat = x + self.image_net(torch.cat([x, e_hat], dim=1))
        t_hat = t_hat[..., :h, :w].float() / gain
        r_hat = s0 - t_hat
        if self.training:
            return r_hat, t_hat, e_hat[..., :h, :w].float() / gain
        return r_hat, t_hat

    @staticmethod
    def loss(outputs: tuple[torch.Tensor, ...], r: torch.Tensor, t: torch.Tensor, kind: str = "l2") -> torch.Tensor:
        """ℓ2 on T̂, on its horizontal and vertical gradients, and on the edge map Ê against
        E(T); ``outputs`` from ``forward`` in training mode. ``kind`` is "l2", CEILNet's only loss."""
        if kind != "l2":
            raise ValueError(f"CEILNet trains with its l2 loss only, got {kind!r}")
        _, t_hat, e_hat = outputs
        err = t_hat - t
        grad = torch.mean(err.diff(dim=-1) ** 2) + torch.mean(err.diff(dim=-2) ** 2)
        return torch.mean(err**2) + grad + torch.mean((e_hat - edge_map(t)) ** 2)

