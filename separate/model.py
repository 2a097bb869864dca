"""The separation network (paper §3.2, Fig. 3).

A canonical projection layer turns the polarization shots into I⊥ and I∥; the three shots and
the two canonical images (15 channels for RGB) feed an encoder-decoder with skip connections:
three down-sampling stages of two ResNet blocks each and a mirrored decoder that up-samples with
transposed convolutions (kernel 2, stride 2: the paper's; ``urd-canonical-transposed.pt``), or,
with ``upsample="resize"`` (``urd-canonical.pt``, whose backbone the shipped ``urd-anchored.pt`` fine-tunes),
with a 1×1 convolution followed by bilinear ×2 interpolation (`ResizeUp`), which has no per-phase
weights and so leaves no 2/4/8-px grid texture (`tools/bench_texture.py`). The 8 output channels
are residual images T̃, R̃ and weights ξ∥, ξ⊥:

    R̂ = ξ⊥·R̃ + (1−ξ⊥)·B_R,   T̂ = ξ∥·T̃ + (1−ξ∥)·B_T.

The bases are the canonical images in the units of urd's separation target (R_obs + T_obs =
S0, see `separate.optics.observable_layers`): B_T = 2·I∥ and B_R = S0 − B_T = I⊥ − I∥. At the
Brewster angle these are the layers themselves up to the small R_s·I∥ term; the paper's bare
I⊥, I∥ are half the scale of the transmission target. The "direct" variant is the same network
fed the three shots alone, predicting R̂ and T̂ with no projection and no residual.

With ``base="fresnel"`` (the physics-anchored network) the canonical network's answer is
anchored to the closed-form Fresnel inversion of I⊥, I∥ at an estimated angle-of-incidence
field θ(x, y) (`fresnel_bases`: the layers themselves wherever one pane at θ explains the shots,
the Kong and Schechner baselines' answer). Their difference D = B_T − T̂_net is split into three
frequency bands (`bands`: fine detail below `BAND_SIGMAS_PX`[0], middle, and coarse tone above
`BAND_SIGMAS_PX`[1]), and a small gate (`FresnelGate`) weighs each band per pixel:

    T̂ = T̂_net + Σ_k g_k·D_k,   R̂ = R̂_net + Σ_k g_k·(B_R − R̂_net)_k,   g_k ∈ (0, 1),

both clipped below at 0 (bands weighed apart can overshoot where the two answers differ). All
gates at 1 give the inversion, all at 0 the network. Where the shots are noisy the inversion is
right in the coarse band only (noise averages out there) and the network keeps the detail;
where they are clean and θ is right it is right in every band. The gate starts near 0
(`with_fresnel_base`: the network's own answer) and is trained alone, the backbone frozen; the
backbone may then be fine-tuned with the gate held (``trainable = "backbone"``).

Inputs of any exposure are scaled so that mean(S0) = 0.25 before the network and back after.
`separate.networks.build_model` makes a network from its config.
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from separate import optics

NOMINAL_ANGLES = tuple(np.radians(optics.PAPER_ANGLES_DEG))
VARIANTS = ("canonical", "direct")
UPSAMPLING = ("transposed", "resize")
BASES = ("canonical", "fresnel")
LOSSES = ("l2", "log-mse")
TARGET_MEAN = 0.25


def check_obs(obs: torch.Tensor) -> None:
    if not isinstance(obs, torch.Tensor):
        raise TypeError(f"expected a torch.Tensor, got {type(obs).__name__}")
    if obs.ndim != 5 or obs.shape[1] < 3:
        raise ValueError(f"expected observations of shape (B, N>=3, C, H, W), got {tuple(obs.shape)}")


def canonical_inputs(obs: torch.Tensor, angles: Sequence[float] = NOMINAL_ANGLES) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Canonical projection layer.

    Args:
        obs: (B, N, C, H, W) linear shots, N ≥ 3.
        angles: the N polarizer angles (rad); only their differences matter.

    Returns:
        shots (B, 3, C, H, W) at angles[0] + 0/45/90° (re-rendered from the Stokes fit unless
        the input already is exactly that), I⊥ and I∥ (B, C, H, W) with φ⊥ within ±45° of
        angles[0]. `separate.methods` (and training data in ``AngleMode.ANY``) hand the network
        shots presented at the estimated s-direction (`separate.presentation.present`), so
        angles[0] is φ⊥ itself.
    """
    check_obs(obs)
    stokes = optics.stokes_from_images(obs.transpose(0, 1), angles)
    phi_ref = float(angles[0])
    if obs.shape[1] == 3 and np.allclose(np.asarray(angles) - phi_ref, NOMINAL_ANGLES, atol=1e-9):
        shots = obs
    else:
        shots = torch.stack([optics.intensity_from_stokes(stokes, phi_ref + a) for a in NOMINAL_ANGLES], dim=1)
    i_perp, i_par = optics.canonical_intensities(stokes, phi_ref)
    return shots, i_perp, i_par


#: Angles of incidence (deg) below this are read as it by `fresnel_bases`: nearer head-on R_s − R_p
#: is exactly 0 in float32 (below ~0.01°) and the inversion divides 0 by 0.
MIN_INCIDENCE_DEG = 1.0


def fresnel_bases(i_perp: torch.Tensor, i_par: torch.Tensor, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Fresnel inversion of canonical images at angle of incidence θ.

    Args:
        i_perp, i_par: (B, C, H, W) canonical images (linear, ≥ 0 up to noise).
        theta: (B,) or (B, 1, H, W) angle of incidence (rad), in (0, π/2); read as at least
            `MIN_INCIDENCE_DEG`.

    Returns:
        (B_R, B_T), each (B, C, H, W): T_obs of `separate.optics.mixture_inverse` clipped to
        [0, S0] (the inversion amplifies noise where R_s ≈ R_p), and B_R = S0 − B_T.
    """
    if theta.ndim == 1:
        theta = theta.view(-1, 1, 1, 1)
    r_s, r_p = optics.fresnel_reflectance(theta.to(i_perp.dtype).clamp_min(math.radians(MIN_INCIDENCE_DEG)))
    s0 = (i_perp + i_par).clamp_min(0.0)
    _, t_obs = optics.mixture_inverse(i_perp, i_par, r_s, r_p)
    base_t = torch.minimum(t_obs.clamp_min(0.0), s0)
    return s0 - base_t, base_t


def theta_channel(theta: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """θ (rad, (B,) or (B, 1, H, W)) as one input channel θ/(π/2), the shape of ``like``'s
    (B, ·, H, W) with one channel."""
    b, _, h, w = like.shape
    if theta.ndim == 1:
        theta = theta.view(-1, 1, 1, 1)
    return (theta.to(like.dtype) / (np.pi / 2)).expand(b, 1, h, w)


#: The Fresnel gate's starting logit, and the Gaussian blurs (px) that split a difference into bands.
GATE_START = -4.0
BAND_SIGMAS_PX = (1.0, 4.0)


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """A separable Gaussian blur (σ px, radius ⌈3σ⌉ or less than the image's side, edges mirrored
    without repeating the edge pixel) of a (B, C, H, W) tensor. Where no gradient is needed on the CPU it runs through
    OpenCV's (same taps, same edges; ~30× faster than torch's grouped convolution)."""
    radius = max(0, min(math.ceil(3 * sigma), x.shape[2] - 1, x.shape[3] - 1))     # reflection needs a radius < the side
    if x.device.type == "cpu" and not (torch.is_grad_enabled() and x.requires_grad):
        out = torch.empty_like(x, memory_format=torch.channels_last)
        for i in range(x.shape[0]):
            hwc = np.ascontiguousarray(x[i].detach().permute(1, 2, 0).numpy())
            blurred = cv2.GaussianBlur(hwc, (2 * radius + 1, 2 * radius + 1), sigma, borderType=cv2.BORDER_REFLECT_101)
            out[i] = torch.from_numpy(blurred.reshape(hwc.shape)).permute(2, 0, 1)
        return out
    taps = torch.exp(-0.5 * (torch.arange(-radius, radius + 1, dtype=x.dtype) / sigma) ** 2)
    taps = (taps / taps.sum()).to(x.device)
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="reflect"), taps.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, radius, radius), mode="reflect"), taps.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def bands(x: torch.Tensor) -> list[torch.Tensor]:
    """(B, C, H, W) → three (B, C, H, W) bands summing to it: x − blur₁(x), blur₁(x) − blur₂(x)
    and blur₂(x), the blurs of `BAND_SIGMAS_PX` (fine detail, middle, coarse tone)."""
    blurred = [gaussian_blur(x, sigma) for sigma in BAND_SIGMAS_PX]
    return [x - blurred[0], blurred[0] - blurred[1], blurred[1]]


class FresnelGate(nn.Module):
    """The per-pixel, per-band weights g of the Fresnel inversion in the physics-anchored network.

    Four 3×3 convolutions (dilations 1, 2, 4, 1; receptive field 17 px) on the network's T̂,
    S0, the three bands of D = B_T − T̂ (all at the network's exposure gain) and θ/(π/2):
    ``5·channels + 1`` channels in, one logit per band out. The last biases start at
    `GATE_START` (g ≈ 0.018: the network's own answer).
    """

    def __init__(self, channels: int = 3, width: int = 16):
        super().__init__()
        dilations = (1, 2, 4, 1)
        sizes = [5 * channels + 1] + [width] * (len(dilations) - 1) + [len(BAND_SIGMAS_PX) + 1]
        self.convs = nn.ModuleList(nn.Conv2d(a, b, 3, padding=d, dilation=d) for a, b, d in zip(sizes, sizes[1:], dilations))
        with torch.no_grad():
            self.convs[-1].weight.mul_(0.1)
            self.convs[-1].bias.fill_(GATE_START)

    def forward(self, t_net: torch.Tensor, s0: torch.Tensor, d_bands: Sequence[torch.Tensor],
                theta: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) tensors at the network's gain (T̂, S0, the bands of D) and θ (rad, (B,) or
        (B, 1, H, W)) → g (B, 3, H, W), one weight per band."""
        x = self.inputs(t_net, s0, d_bands, theta)
        for conv in self.convs[:-1]:
            x = F.relu(conv(x))
        return torch.sigmoid(self.convs[-1](x))

    @staticmethod
    def inputs(t_net: torch.Tensor, s0: torch.Tensor, d_bands: Sequence[torch.Tensor], theta: torch.Tensor,
               dtype: torch.dtype | None = None) -> torch.Tensor:
        """The gate's input channels: T̂, S0, the bands of D and θ/(π/2), (B, 5·C + 1, H, W); with
        ``dtype``, in that dtype and channels-last strides, written in one pass (the fused
        convolutions' layout, `separate.infer.FusedNet`)."""
        parts = [t_net, s0, *d_bands]
        if dtype is None:
            x = torch.cat(parts, dim=1)
            return torch.cat([x, theta_channel(theta, x)], dim=1)
        parts.append(theta_channel(theta, t_net))
        b, _, h, w = t_net.shape
        out = torch.empty((b, sum(part.shape[1] for part in parts), h, w), dtype=dtype, device=t_net.device,
                          memory_format=torch.channels_last)
        start = 0
        for part in parts:
            out[:, start : start + part.shape[1]] = part
            start += part.shape[1]
        return out


class ResBlock(nn.Module):
    """Two 3×3 convolutions with an identity shortcut."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.conv2(F.relu(self.conv1(x))))


class ResizeUp(nn.Module):
    """×2 up-sampling from ``c_in`` to ``c_out`` channels: a 1×1 convolution, then bilinear
    interpolation (the two commute: the interpolation weights sum to one; convolving first is 4×
    cheaper)."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(self.conv(x), scale_factor=2, mode="bilinear", align_corners=False)

    @classmethod
    def from_transposed(cls, up: nn.ConvTranspose2d) -> "ResizeUp":
        """The resize up-sampling closest to a kernel-2, stride-2 transposed convolution: its
        weights averaged over the four output phases (a start for fine-tuning)."""
        out = cls(up.in_channels, up.out_channels)
        with torch.no_grad():
            out.conv.weight.copy_(up.weight.mean(dim=(2, 3)).t()[..., None, None])
            out.conv.bias.copy_(up.bias)
        return out


class SeparationNet(nn.Module):
    """Encoder-decoder separating reflection and transmission from polarization shots.

    Args:
        width: channels at full resolution (doubling at each of the 3 down-sampling stages;
            16 gives 1.12 M parameters for RGB, the shipped size).
        variant: "canonical" (paper) or "direct" (no projection layer, no residual).
        channels: colour channels per shot.
        upsample: the decoder's up-sampling, "transposed" (the paper's) or "resize" (`ResizeUp`).
        base: "canonical" (the residual bases 2·I∥ and I⊥ − I∥) or "fresnel" (the same network,
            its answer blended with the Fresnel inversion at an estimated θ by a `FresnelGate`;
            ``forward`` then needs θ).
    """

    def __init__(self, width: int = 16, variant: str = "canonical", channels: int = 3, upsample: str = "transposed",
                 base: str = "canonical"):
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"expected variant in {VARIANTS}, got {variant!r}")
        if upsample not in UPSAMPLING:
            raise ValueError(f"expected upsample in {UPSAMPLING}, got {upsample!r}")
        if base not in BASES or (base == "fresnel" and variant != "canonical"):
            raise ValueError(f"expected base in {BASES} ('fresnel' only for the canonical variant), got {base!r}")
        self.variant, self.width, self.channels, self.upsample, self.base = variant, width, channels, upsample, base
        n_in = channels * (5 if variant == "canonical" else 3)
        n_out = 2 * channels + (2 if variant == "canonical" else 0)
        widths = [width, 2 * width, 4 * width, 8 * width]
        self.head = nn.Conv2d(n_in, width, 3, padding=1)
        self.enc = nn.ModuleList([nn.Sequential(ResBlock(c), ResBlock(c)) for c in widths])
        self.down = nn.ModuleList([nn.Conv2d(a, b, 3, stride=2, padding=1) for a, b in zip(widths, widths[1:])])
        pairs = list(zip(widths, widths[1:]))
        if upsample == "transposed":
            self.up = nn.ModuleList([nn.ConvTranspose2d(b, a, 2, stride=2) for a, b in pairs])
        else:
            self.up = nn.ModuleList([ResizeUp(b, a) for a, b in pairs])
        self.dec = nn.ModuleList([nn.Sequential(ResBlock(c), ResBlock(c)) for c in widths[:-1]])
        self.tail = nn.Conv2d(width, n_out, 3, padding=1)
        if base == "fresnel":
            self.gate = FresnelGate(channels)

    def config(self) -> dict:
        config = {"width": self.width, "variant": self.variant, "channels": self.channels}
        if self.upsample != "transposed":
            config["upsample"] = self.upsample
        return config if self.base == "canonical" else {**config, "base": self.base}

    def backbone(self, x: torch.Tensor) -> torch.Tensor:
        """The encoder-decoder on a (B, n_in, H, W) tensor, H and W multiples of 8."""
        x = F.relu(self.head(x))
        skips = []
        for i, block in enumerate(self.enc):
            x = block(x)
            if i < len(self.down):
                skips.append(x)
                x = F.relu(self.down[i](x))
        for i in reversed(range(len(self.up))):
            x = self.dec[i](F.relu(self.up[i](x)) + skips[i])
        return self.tail(x)

    def forward(
        self, obs: torch.Tensor, angles: Sequence[float] = NOMINAL_ANGLES, scale: torch.Tensor | None = None,
        theta: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Separate a batch.

        Args:
            obs: (B, N, C, H, W) linear shots at ``angles`` (rad), N ≥ 3, any H, W.
            angles: polarizer angles (rad) of the N shots.
            scale: (B,) exposure scale; default mean(S0) per sample. Pass one global value
                when separating tiles of one image.
            theta: (B,) or (B, 1, H, W) estimated angle of incidence (rad), for ``base="fresnel"``
                only (`separate.incidence.estimate_incidence_field`).

        Returns:
            (R̂, T̂), each (B, C, H, W), linear, in the units of ``obs``.
        """
        if (theta is None) != (self.base != "fresnel"):
            raise ValueError(f"expected theta exactly when base is 'fresnel', got base {self.base!r} and "
                             f"theta {'None' if theta is None else tuple(theta.shape)}")
        with torch.autocast(obs.device.type, enabled=False):      # the optics stay float32 under bf16
            shots, i_perp, i_par = canonical_inputs(obs.float(), angles)
        if scale is None:
            scale = (i_perp + i_par).mean(dim=(1, 2, 3)).clamp_min(1e-6)
        gain = (TARGET_MEAN / scale).view(-1, 1, 1, 1).to(obs.dtype)
        b, _, c, h, w = shots.shape
        parts = [shots.reshape(b, 3 * c, h, w)] + ([i_perp, i_par] if self.variant == "canonical" else [])
        x = torch.cat(parts, dim=1) * gain
        pad_h, pad_w = (-h) % 8, (-w) % 8
        x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        out = self.backbone(x)[..., :h, :w].float()
        if self.variant == "direct":
            return out[:, :c] / gain, out[:, c : 2 * c] / gain
        t_res, r_res = out[:, :c], out[:, c : 2 * c]
        xi_par, xi_perp = torch.sigmoid(out[:, 2 * c : 2 * c + 1]), torch.sigmoid(out[:, 2 * c + 1 :])
        r_hat = xi_perp * r_res + (1 - xi_perp) * (i_perp - i_par) * gain
        t_hat = xi_par * t_res + (1 - xi_par) * 2.0 * i_par * gain
        if self.base == "fresnel":
            with torch.autocast(obs.device.type, enabled=False):
                r_hat, t_hat = self.anchor(r_hat, t_hat, i_perp * gain, i_par * gain, theta.float())
        return r_hat / gain, t_hat / gain

    def anchor(self, r_hat: torch.Tensor, t_hat: torch.Tensor, i_perp: torch.Tensor, i_par: torch.Tensor,
               theta: torch.Tensor, gate: "FresnelGate | None" = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The fresnel network's answer: each band of the Fresnel inversion's difference from R̂, T̂
        added with the gate's weight, negative light clipped to 0 (all (B, C, H, W) float32 in one
        exposure's units; θ rad (B,) or (B, 1, H, W)). ``gate``: another implementation of
        ``self.gate`` (`separate.infer.FusedNet`'s)."""
        base_r, base_t = fresnel_bases(i_perp, i_par, theta)
        c = t_hat.shape[1]
        split = bands(torch.cat([base_t - t_hat, base_r - r_hat], dim=1))      # one pass over both layers
        d_t, d_r = [band[:, :c] for band in split], [band[:, c:] for band in split]
        g = (gate or self.gate)(t_hat, base_r + base_t, d_t, theta)
        for k in range(len(d_t)):
            t_hat = t_hat + g[:, k : k + 1] * d_t[k]
            r_hat = r_hat + g[:, k : k + 1] * d_r[k]
        return r_hat.clamp_min(0.0), t_hat.clamp_min(0.0)          # bands weighed apart can overshoot below 0

    @staticmethod
    def loss(outputs: tuple[torch.Tensor, torch.Tensor], r: torch.Tensor, t: torch.Tensor,
             kind: str = "l2") -> torch.Tensor:
        """The training loss of R̂ and T̂ (``outputs`` of ``forward``) against R and T (B, C, H, W).

        ``kind`` (`LOSSES`): "l2", the paper's mean squared error of each layer, summed; or
        "log-mse", 10⁻³ × the batch mean of each sample's log(MSE + 10⁻⁶), summed over the
        layers: the gradient of the mean PSNR, which weighs a dark or low-contrast sample as
        much as a bright one where ℓ2 lets the brightest samples decide.
        """
        r_hat, t_hat = outputs
        if kind == "l2":
            return torch.mean((r_hat - r) ** 2) + torch.mean((t_hat - t) ** 2)
        if kind != "log-mse":
            raise ValueError(f"expected loss in {LOSSES}, got {kind!r}")
        mse_r = ((r_hat - r) ** 2).float().mean(dim=(1, 2, 3))
        mse_t = ((t_hat - t) ** 2).float().mean(dim=(1, 2, 3))
        return 1e-3 * (torch.log(mse_r + 1e-6).mean() + torch.log(mse_t + 1e-6).mean())


def with_resize_upsampling(model: SeparationNet) -> SeparationNet:
    """A copy of a transposed-up-sampling network whose decoder up-samples with `ResizeUp`
    (`ResizeUp.from_transposed`), every other weight kept: the start for fine-tuning it."""
    if model.upsample != "transposed":
        raise ValueError(f"expected a network with transposed up-sampling, got {model.upsample!r}")
    out = SeparationNet(model.width, model.variant, model.channels, upsample="resize")
    out.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("up.")}, strict=False)
    for i, up in enumerate(model.up):
        out.up[i] = ResizeUp.from_transposed(up)
    return out


def with_fresnel_base(model: SeparationNet) -> SeparationNet:
    """A copy of a canonical-base network with ``base="fresnel"``: every weight kept, and a new
    `FresnelGate` that starts near g = 0 (the network's own answer): the start for training the gate."""
    if model.variant != "canonical" or model.base != "canonical":
        raise ValueError(f"expected a canonical network with canonical bases, got {model.config()}")
    out = SeparationNet(model.width, model.variant, model.channels, model.upsample, base="fresnel")
    out.load_state_dict(model.state_dict(), strict=False)
    return out


def without_gate(model: SeparationNet) -> SeparationNet:
    """The canonical network inside a fresnel one (every weight but the gate's): the answer its
    gate starts from; a canonical network comes back as it is."""
    if model.base != "fresnel":
        return model
    with torch.random.fork_rng():                # its initial weights are overwritten: leave the caller's stream alone
        out = SeparationNet(model.width, model.variant, model.channels, model.upsample)
    out.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("gate.")})
    return out.eval()
