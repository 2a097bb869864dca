"""Full-resolution inference with the separation network.

Images of any size are processed in overlapping tiles (`separate.tiling`: equal tiles on the
network's 8-pixel grid, blended by ramps that are ~0 where a tile's receptive field is cut),
which leaves no seams: with the default 160 px overlap, tiled and whole-image results agree within
3.9e-5 in fp32 (781×776 px test image in 2 × 2 tiles of 512 px; 1.1e-3 with 128 px). Memory is bounded by the
tile size, not the image size: besides the input stack and the two results, a tile takes about
230 bytes per pixel of resident memory in bf16 and 310 in fp32 (measured on a 24 MP scene,
whose 2048 px tiles are 1632×1456: 0.51 and 0.69 GiB; 0.16 and 0.26 GiB with 1024 px tiles),
plus the freed blocks glibc keeps for the next tile while the tiles run (`_freed_blocks_kept`;
24 MP peak 2.33–2.43 GiB in bf16, 2.32–2.42 GiB in fp32 with its 1408 px tiles, `FP32_TILE`). The default 2048 px tiles put
a 24 MP image through the network as 1.19× its pixels (1.39× with 1024 px tiles; 3072 px gave
no further gain): bf16 23.2 s instead of 26.3 s, fp32 38.4 s instead of 43.9 s on the
development machine (2-core AMD EPYC with AVX-512 BF16; measured before the strips below). A stack of uint16 codes (as scenes are
stored) is converted to float a tile at a time. One exposure scale, mean(S0) of the whole image,
is used for every tile.

Speed: the separation network runs through `FusedNet`, which calls oneDNN's fused
convolutions (convolution + ReLU, convolution + residual sum + ReLU, transposed convolution +
ReLU) on channels-last tensors with weights converted once. On a CPU that does about twice the
work per CPU second of the module's own forward pass, which spends ~60% of its time outside
the convolutions (separate ReLU and sum passes, layout conversions): ~70% of the large-matmul
rate in fp32 and in native bf16, one thread, network alone (``tools/bench_speed.py``). The
convolutions between two changes of resolution run in strips of rows (`STRIP_ROWS`) whose
activations stay in cache instead of each convolution streaming the whole tile through
memory (24 MP `separate_stack`, transposed decoder: bf16 23.1–24.6 → 21.2–22.0 s, fp32 with
AVX-512 37.0 → 32.5 s). Other
networks (the CEILNet baseline) run as modules, under bf16 autocast where chosen.

Input handling: NaN or infinite pixels are an error; negative pixels (linear decoding noise
below black) are clipped to 0; the angles must span at least `separate.optics.MIN_SPAN_DEG`. The outputs hold no
negative light: each tile's R̂ and T̂ from urd's network (not the CEILNet baseline, whose R̂ is
S0 − T̂ by design) are clipped below at 0, as the physics-anchored network's anchor clips them
(`separate.model.SeparationNet.anchor`). Without its gate (a θ estimate that is not clear) that
network's backbone alone can go below 0 where its training clipped it (views without glass: R̂
down to −9% of the light with T̂ right, so R̂ is clipped, not moved into T̂). Monochrome shots (one
channel, or colour channels that are all equal, as urd stores a mono sensor's frames) carry no
colour: the network sees the grey image in each of its colour channels and its outputs are
averaged over them, so R̂ and T̂ are grey too (an RGB-trained network otherwise invents tints).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import hashlib
import json
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, Sequence

import numpy as np
import torch

from separate import optics
from separate.model import TARGET_MEAN, ResBlock, ResizeUp, SeparationNet, canonical_inputs
from separate.networks import build_model
from separate.precision import Precision, gpu_tile, resolve
from separate.tiling import OVERLAP, TILE, blend_weights, check_tiling, tile_spans
from urd.core.errors import WeightsError

if TYPE_CHECKING:
    from separate.incidence import Incidence

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
#: Rows (full resolution) of the strips `FusedNet` runs its runs of same-resolution convolutions
#: in: a 2048 px tile's backbone 1.33 → 1.14 s (bf16, 2 threads; 256 → 512 rows within ±5%).
STRIP_ROWS = 384
#: Rows of the strips in which `separate_stack` converts, presents and clips a tile's shots: a 24 MP
#: scene's 1632×1456 tiles with a reference field 0.21 → 0.06 s each (whole tile at once → 64 rows).
PATCH_ROWS = 64
#: The CPU tile (px) in fp32, whose activations take twice the memory of bf16's: with the freed
#: blocks kept for reuse (`_freed_blocks_kept`) a 24 MP scene peaks at 2.70 GiB with 2048 px tiles,
#: 2.44-2.59 GiB with 1536 px and 2.32-2.42 GiB with 1408 px, as fast (AVX2: 39.6-39.9 s either way).
FP32_TILE = 1408
MODULE_TILE = 1024  # px for networks run as modules (CEILNet, or torch without oneDNN): their memory per pixel is higher
DEFAULT_WEIGHTS = WEIGHTS_DIR / "urd-anchored.pt"


def load_model(path: Path | str | None = None) -> tuple[torch.nn.Module, dict]:
    """Load shipped or trained weights; WeightsError if missing, corrupt or mismatched.

    Accepts a weights file (``{"model", "model_config"}``), a training checkpoint, or the name
    of a shipped weights file without its suffix (e.g. "urd-canonical-transposed", `shipped_weights`).
    Returns the model in eval mode and a description (file, sha256, config, card).
    """
    path = Path(path or DEFAULT_WEIGHTS)
    if not path.is_file() and path.name == str(path) and (WEIGHTS_DIR / f"{path}.pt").is_file():
        path = WEIGHTS_DIR / f"{path}.pt"
    if not path.exists():
        raise WeightsError(f"weights file {path} not found (shipped: {', '.join(shipped_weights())}; "
                           "train your own with 'urd train')")
    state = read_weights(path)
    if not isinstance(state.get("model_config"), dict):
        raise WeightsError(f"{path} is not a urd weights or checkpoint file (no 'model_config': the network it holds is unknown)")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    try:
        with torch.device("meta"):                         # no memory: a small file's config may name a huge network
            skeleton = {k: tuple(v.shape) for k, v in build_model(state["model_config"]).state_dict().items()}
        tensors = {k: tuple(v.shape) for k, v in state["model"].items()}
        if tensors != skeleton:
            wrong = sorted(set(skeleton) ^ set(tensors)) or [k for k in skeleton if skeleton[k] != tensors[k]]
            raise ValueError(f"its tensors are not those of the network its model_config names ({len(tensors)} "
                             f"tensors for {len(skeleton)}; first difference: {wrong[0]})")
        with torch.random.fork_rng():                      # the weights' random start must not move the caller's RNG
            model = build_model(state["model_config"])
        model.load_state_dict({k: v.float() for k, v in state["model"].items()})
    except Exception as exc:  # noqa: BLE001 - any failure to build or fill the network means the file is unusable
        raise WeightsError(f"weights file {path} is corrupt or does not fit the model: {_one_line(exc)}") from exc
    model.eval()
    card_path = path.with_suffix(".json")
    card = None
    if card_path.is_file():
        try:
            card = json.loads(card_path.read_text())
            problem = None if isinstance(card, dict) else f"a JSON {type(card).__name__}, not an object"
        except (OSError, ValueError, RecursionError) as exc:
            problem = str(exc)
        if problem:
            raise WeightsError(f"model card {card_path} (beside the weights {path.name}) is unreadable: {problem:.200}; "
                               "restore it, or move it away to use the weights without their card")
    info = {"file": str(path), "sha256": digest, "config": state["model_config"], "card": card}
    return model, info


#: The first bytes of a zip archive, torch.save's format since torch 1.6.
ZIP_MAGIC = b"PK\x03\x04"


def read_weights(path: Path, device: torch.device | str = "cpu") -> dict:
    """A weights or checkpoint file's contents (a dict whose ``model`` maps names to tensors),
    read with tensors and plain data only (``weights_only``: no code runs on loading);
    WeightsError in one line naming ``path`` and why it is not such a file otherwise."""
    path = Path(path)
    if path.is_dir():
        run = " (a run folder: pass its best.pt or last.pt)" if (path / "best.pt").is_file() or (path / "last.pt").is_file() else ""
        raise WeightsError(f"{path} is a folder, expected a weights or checkpoint file{run}")
    if not path.exists():
        raise WeightsError(f"{path}: no such file")
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure to read means the file is unusable; say why in one line
        raise WeightsError(f"{path} is not a urd weights or checkpoint file ({_load_failure(path, exc)})") from exc
    if not isinstance(state, dict) or not isinstance(state.get("model"), dict) \
            or not all(isinstance(v, torch.Tensor) for v in state["model"].values()):
        held = f"a {type(state).__name__}" if not isinstance(state, dict) else f"a dict of {sorted(map(str, state))[:6]}"
        raise WeightsError(f"{path} is not a urd weights or checkpoint file (it holds {held}, not a 'model' of tensors)")
    return state


def _load_failure(path: Path, exc: Exception) -> str:
    """A short reason why ``torch.load(path, weights_only=True)`` raised ``exc``."""
    if isinstance(exc, OSError):
        return f"cannot be read: {exc.strerror or exc}"
    try:
        with open(path, "rb") as f:
            head = f.read(1024)
    except OSError as err:
        return f"cannot be read: {err.strerror or err}"
    if not head:
        return "the file is empty"
    found = re.search(r"Unsupported global: GLOBAL (\S+)", str(exc))
    if found:
        return f"it holds a Python object ({found.group(1)}) besides tensors and plain data, which urd does not load"
    if head.startswith(ZIP_MAGIC):
        return "a damaged or truncated archive: corrupt, or not written by torch.save"
    if _looks_like_text(head):
        return "a text file, not one written by torch.save"
    return "not written by torch.save"


def _looks_like_text(head: bytes) -> bool:
    """Whether a file's first bytes ``head`` read as UTF-8 text (no NUL; a character cut at the end is allowed)."""
    if b"\0" in head:
        return False
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        return exc.start >= len(head) - 3
    return True


def _one_line(exc: BaseException) -> str:
    """An error's message on one line (torch's state-dict errors run over many), at most 300 characters."""
    return " ".join(line.strip() for line in str(exc).splitlines() if line.strip())[:300] or type(exc).__name__


def shipped_weights() -> list[str]:
    """Names of the weights files shipped with urd (`load_model` accepts them as paths)."""
    return sorted(p.stem for p in WEIGHTS_DIR.glob("*.pt"))


def check_inputs(images: np.ndarray, angles_deg: list[float]) -> None:
    """Validate a stack (N, H, W, C), float or codes (`separate.optics.code_scale`), and its
    angles (deg) without copying the stack: type, then shape, then values."""
    if not isinstance(images, np.ndarray):
        raise TypeError(f"expected images as a numpy array, got {type(images).__name__}")
    optics.code_scale(images)                                           # float or unsigned codes
    if images.ndim != 4 or images.shape[0] < 3 or images.shape[-1] not in (1, 3):
        raise ValueError(f"expected at least 3 shots stacked as (N>=3, H, W, C in 1,3), got {images.shape}")
    if len(angles_deg) != images.shape[0]:
        raise ValueError(f"expected {images.shape[0]} angles (one per image), got {len(angles_deg)}")
    optics.check_angles(np.radians(angles_deg), min_span=np.radians(optics.MIN_SPAN_DEG))
    if images.dtype.kind == "f" and not np.isfinite(images.sum(dtype=np.float64)):   # NaN and inf propagate
        bad = sum(int((~np.isfinite(shot)).sum()) for shot in images)
        raise ValueError(f"expected finite pixel values, got {bad} NaN or infinite values")


class FusedNet:
    """A `SeparationNet`'s forward pass through oneDNN's fused convolutions, for inference.

    Same arithmetic as ``model(obs, angles, scale)`` (within 1e-5 in fp32; bf16 rounds the
    network's activations as autocast does), without the module's separate ReLU, residual-sum
    and layout passes: activations are channels-last, each convolution carries its ReLU and,
    in the residual blocks, the skip sum; weights are converted to ``dtype`` once, here.
    The module is read, not changed; later changes to its weights are not seen.

    Args:
        model: a SeparationNet (any width, either variant).
        dtype: torch.float32 or torch.bfloat16, the network's arithmetic (the optics before
            and the mixing after it stay float32).
        strip_rows: rows of the strips in which the convolutions between two changes of
            resolution run at full resolution (`_chain`; halved at each coarser level, at least 8).
    """

    def __init__(self, model: SeparationNet, dtype: torch.dtype = torch.float32, strip_rows: int = STRIP_ROWS):
        if not isinstance(model, SeparationNet):
            raise TypeError(f"expected a SeparationNet, got {type(model).__name__}")
        if dtype not in (torch.float32, torch.bfloat16):
            raise ValueError(f"expected dtype torch.float32 or torch.bfloat16, got {dtype}")
        if strip_rows < 8:
            raise ValueError(f"expected strip_rows of at least 8, got {strip_rows}")
        self.model, self.dtype, self.strip_rows = model, dtype, strip_rows
        self._weights = {}
        for module in model.modules():
            if isinstance(module, (torch.nn.Conv2d, torch.nn.ConvTranspose2d)):
                self._weights[module] = (module.weight.detach().to(dtype).contiguous(memory_format=torch.channels_last),
                                         module.bias.detach().to(dtype))

    @staticmethod
    def available() -> bool:
        """True where torch has oneDNN's fused convolution operators (CPU builds with mkldnn)."""
        return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")

    def _conv(self, conv: torch.nn.Conv2d, x: torch.Tensor, unary: str = "none") -> torch.Tensor:
        w, b = self._weights[conv]
        return torch.ops.mkldnn._convolution_pointwise(x, w, b, conv.padding, conv.stride, conv.dilation, conv.groups,
                                                       unary, [], "")

    def _res_block(self, block: ResBlock, x: torch.Tensor) -> torch.Tensor:
        """relu(x + conv2(relu(conv1(x)))) in two fused calls."""
        y = self._conv(block.conv1, x, "relu")
        conv = block.conv2
        w, b = self._weights[conv]
        return torch.ops.mkldnn._convolution_pointwise.binary(y, x, w, b, conv.padding, conv.stride, conv.dilation,
                                                              conv.groups, "add", 1.0, "relu", [], "")

    def _network_input(self, obs: torch.Tensor, angles: Sequence[float], gain: torch.Tensor,
                       rows: int = 128) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The model's network input ``cat(shots, I⊥, I∥) · gain``, replicate-padded to the
        8-px grid, as one ``dtype`` channels-last tensor, and the residual bases B_R = I⊥ − I∥,
        B_T = 2·I∥ (float32, unscaled; empty for the direct variant). Built ``rows`` rows at a
        time (`canonical_inputs` is per pixel), so its temporaries stay small."""
        b, _, c, h, w = obs.shape
        canonical = self.model.variant == "canonical"
        n_in = c * (5 if canonical else 3)
        x = torch.empty((b, n_in, -(-h // 8) * 8, -(-w // 8) * 8), dtype=self.dtype, memory_format=torch.channels_last)
        shape = (b, c, h, w) if canonical else (b, c, 0, 0)         # channels-last: so are R̂ and T̂
        base_r, base_t = (torch.empty(shape, dtype=torch.float32, memory_format=torch.channels_last) for _ in range(2))
        for y in range(0, h, rows):
            y1 = min(h, y + rows)
            shots, perp, par = canonical_inputs(obs[..., y:y1, :], angles)
            parts = [*shots.unbind(1)] + ([perp, par] if canonical else [])
            if canonical:
                base_r[..., y:y1, :], base_t[..., y:y1, :] = perp - par, 2.0 * par
            for k, part in enumerate(parts):
                torch.mul(part, gain, out=x[:, k * c : (k + 1) * c, y:y1, :w])
        x[:, :, h:, :w] = x[:, :, h - 1 : h, :w]
        x[:, :, :, w:] = x[:, :, :, w - 1 : w]
        return x, base_r, base_t

    def _run(self, ops: Sequence[ResBlock | tuple[torch.nn.Conv2d, str]], x: torch.Tensor) -> torch.Tensor:
        """``ops`` (residual blocks and (convolution, unary) pairs) applied to ``x`` in turn."""
        for op in ops:
            x = self._res_block(op, x) if isinstance(op, ResBlock) else self._conv(op[0], x, op[1])
        return x

    def _chain(self, ops: Sequence[ResBlock | tuple[torch.nn.Conv2d, str]], x: torch.Tensor, level: int) -> torch.Tensor:
        """Run ``ops`` (residual blocks and (convolution, unary) pairs, all at the resolution of
        ``level``, stride 1, 'same' padding) on ``x`` a strip of rows at a time (`strip_rows`,
        halved per level), so that a strip's activations stay in the CPU's cache from one
        convolution to the next. Each strip is read with as many extra rows on either side as the
        convolutions reach and only its own rows are kept: the result is that of the ops on the
        whole of ``x``, bit for bit."""
        convs = [conv for op in ops for conv in ((op.conv1, op.conv2) if isinstance(op, ResBlock) else op[:1])]
        if any(conv.stride[0] != 1 or 2 * conv.padding[0] != conv.dilation[0] * (conv.kernel_size[0] - 1) for conv in convs):
            raise ValueError("expected stride-1 convolutions with 'same' padding in a chain")
        reach = sum(conv.padding[0] for conv in convs)
        rows = max(8, self.strip_rows >> level)
        h = x.shape[2]
        if h <= rows:
            return self._run(ops, x)
        out = None
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            top = max(0, y0 - reach)
            strip = self._run(ops, x[:, :, top : min(h, y1 + reach)])
            if out is None:
                out = torch.empty((x.shape[0], strip.shape[1], h, x.shape[3]), dtype=strip.dtype,
                                  memory_format=torch.channels_last)
            out[:, :, y0:y1] = strip[:, :, y0 - top : y1 - top]
        return out

    def backbone(self, x: torch.Tensor) -> torch.Tensor:
        """`SeparationNet.backbone` on (B, n_in, H, W) ``dtype`` channels-last, H and W
        multiples of 8; returns (B, n_out, H, W) ``dtype`` channels-last."""
        m = self.model
        skips = []
        for i, stage in enumerate(m.enc):
            x = self._chain(([(m.head, "relu")] if i == 0 else []) + list(stage), x, i)
            if i < len(m.down):
                skips.append(x)
                x = self._conv(m.down[i], x, "relu")
        for i in reversed(range(len(m.up))):
            up = m.up[i]
            if isinstance(up, ResizeUp):
                x = torch.nn.functional.interpolate(self._conv(up.conv, x), scale_factor=2, mode="bilinear",
                                                    align_corners=False).relu_()
            else:
                w, b = self._weights[up]
                x = torch.ops.mkldnn._convolution_transpose_pointwise(x, w, b, up.padding, up.output_padding, up.stride,
                                                                      up.dilation, up.groups, "relu", [], "")
            x += skips.pop()
            x = self._chain(list(m.dec[i]) + ([(m.tail, "none")] if i == 0 else []), x, i)
        return x

    def __call__(self, obs: torch.Tensor, angles: Sequence[float], scale: torch.Tensor,
                 theta: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`SeparationNet.forward`: (B, N, C, H, W) float32 linear shots at ``angles`` (rad),
        (B,) exposure scale and, for ``base="fresnel"``, θ (rad, (B,) or (B, 1, H, W)) → (R̂, T̂),
        each (B, C, H, W) float32 (channels-last strides). Pass ``obs`` as a temporary to let its
        memory go once the network's input is built."""
        if (theta is None) != (self.model.base != "fresnel"):
            raise ValueError(f"expected theta exactly when base is 'fresnel', got base {self.model.base!r}")
        gain = (TARGET_MEAN / scale.float()).view(-1, 1, 1, 1)
        c, h, w = obs.shape[-3:]
        x, base_r, base_t = self._network_input(obs.float(), angles, gain)
        del obs
        held = [x]
        del x
        out = self.backbone(held.pop())[..., :h, :w]         # the only reference: x goes after the first level
        out = out.float()                                    # one pass; the channels are sliced from it
        if self.model.variant != "canonical":
            return out[:, :c] / gain, out[:, c : 2 * c] / gain
        xi = torch.sigmoid(out[:, 2 * c :].contiguous(memory_format=torch.channels_last))   # ξ∥, ξ⊥ (dense: sigmoid's vector path)
        r_hat = torch.lerp(base_r, out[:, c : 2 * c] / gain, xi[:, 1:])   # ξ⊥·R̃ + (1 − ξ⊥)·B_R
        t_hat = torch.lerp(base_t, out[:, :c] / gain, xi[:, :1])          # ξ∥·T̃ + (1 − ξ∥)·B_T
        if self.model.base == "fresnel":
            r_hat, t_hat = self._anchor(r_hat, t_hat, base_r, base_t, gain, theta.float())
        return r_hat, t_hat

    def _gate(self, t_net: torch.Tensor, s0: torch.Tensor, d_bands: Sequence[torch.Tensor], theta: torch.Tensor) -> torch.Tensor:
        """`FresnelGate.forward` through the fused convolutions, at ``dtype``: g (B, 3, H, W) float32."""
        convs = self.model.gate.convs
        x = self.model.gate.inputs(t_net, s0, d_bands, theta, self.dtype)
        x = self._run([(conv, "relu") for conv in convs[:-1]] + [(convs[-1], "none")], x)
        return torch.sigmoid(x.float())

    def _anchor(self, r_hat: torch.Tensor, t_hat: torch.Tensor, base_r: torch.Tensor, base_t: torch.Tensor,
                gain: torch.Tensor, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`SeparationNet.anchor` on (B, C, H, W) float32 R̂, T̂ and the canonical bases, ``strip_rows``
        rows at a time, each read with `ANCHOR_HALO` rows on either side (more than the gate and
        the band blurs reach: the whole tile's result, with a strip's temporaries; a few pixels may
        differ by one float32 rounding, where an elementwise function's vector loop ends elsewhere)."""
        h = r_hat.shape[2]
        theta = theta.view(-1, 1, 1, 1) if theta.ndim == 1 else theta
        out_r, out_t = torch.empty_like(r_hat), torch.empty_like(t_hat)
        for y0 in range(0, h, self.strip_rows):
            y1 = min(h, y0 + self.strip_rows)
            top, bottom = max(0, y0 - ANCHOR_HALO), min(h, y1 + ANCHOR_HALO)
            rows = slice(top, bottom)
            i_par = base_t[:, :, rows] * (0.5 * gain)
            with torch.no_grad():
                r, t = self.model.anchor(r_hat[:, :, rows] * gain, t_hat[:, :, rows] * gain, base_r[:, :, rows] * gain + i_par,
                                         i_par, theta if theta.shape[2] == 1 else theta[:, :, rows], gate=self._gate)
            out_r[:, :, y0:y1] = r[:, :, y0 - top : y1 - top] / gain
            out_t[:, :, y0:y1] = t[:, :, y0 - top : y1 - top] / gain
        return out_r, out_t


#: Rows read beyond a strip by `FusedNet._anchor`: the gate reaches 8 px, the band blurs 12.
ANCHOR_HALO = 32


def runner(model: torch.nn.Module, precision: str | Precision = "auto", device: torch.device | str = "cpu") -> Callable:
    """The fastest way to run ``model(obs, angles, scale)`` for inference at ``precision``
    (`separate.precision.resolve`) on ``device``, returning float32 (R̂, T̂) on the CPU: on the
    CPU `FusedNet` for a SeparationNet where oneDNN is there, the module itself (under bf16
    autocast where chosen) otherwise; on a GPU the module, moved there, each tile moved in and out."""
    device = torch.device(device)
    bf16 = resolve(precision, device) is Precision.BF16
    if device.type == "cpu" and isinstance(model, SeparationNet) and FusedNet.available():
        return FusedNet(model, torch.bfloat16 if bf16 else torch.float32)
    model = model.to(device)

    def run(obs: torch.Tensor, angles: Sequence[float], scale: torch.Tensor,
            theta: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        extra = {} if theta is None else {"theta": theta.to(device)}
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            r_hat, t_hat = model(obs.to(device), angles, scale.to(device), **extra)[:2]
        return r_hat.float().cpu(), t_hat.float().cpu()

    return run


def default_tile(model: torch.nn.Module, device: torch.device | str = "cpu", precision: str | Precision = "auto") -> int:
    """The default tile (px): on the CPU, for a network `runner` runs through `FusedNet`, `TILE`
    in bf16 and `FP32_TILE` in fp32, else `MODULE_TILE`; on a GPU the tile that fits its free
    memory (`separate.precision.gpu_tile`), at least `MODULE_TILE`."""
    device = torch.device(device)
    bf16 = resolve(precision, device) is Precision.BF16
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return max(MODULE_TILE, gpu_tile(free, bf16))
    if isinstance(model, SeparationNet) and FusedNet.available():
        return TILE if bf16 else FP32_TILE
    return MODULE_TILE


@torch.inference_mode()
def separate_stack(model: torch.nn.Module, images: np.ndarray, angles_deg: list[float], tile: int = TILE,
                   overlap: int = OVERLAP, precision: str = "auto",
                   progress: Callable[[int, int], None] | None = None,
                   reference_deg: float | np.ndarray | None = None,
                   theta_deg: float | np.ndarray | Incidence | None = None,
                   device: torch.device | str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Separate an aligned stack into (R̂, T̂), each H×W×C float32 linear.

    Args:
        model: the network (``model.channels`` colour channels).
        images: (N, H, W, C) linear shots, N ≥ 3, C = ``model.channels`` or 1; monochrome
            stacks give monochrome results (module docstring). Float, or uint16 codes
            (65535 = 1.0, `separate.optics.code_scale`): converted a tile at a time, so a
            stack of codes takes half the memory of float32 shots.
        angles_deg: polarizer angles of the shots (deg), spanning at least `separate.optics.MIN_SPAN_DEG`.
        tile, overlap: tile size and overlap (px), `check_tiling`: tile ≥ 128 and ≥ 2·overlap,
            rounded down to a multiple of 8; overlap ≥ 0.
        precision: "auto", "fp32" or "bf16" (`separate.precision.resolve`: auto takes bf16
            only where the CPU runs it natively).
        progress: called with (tiles done, tiles total).
        reference_deg: if given, the network sees the shots presented at this reference + 0/45/90°
            (`separate.presentation.present`'s matrix, `presenting_matrix`), rendered tile by
            tile: the same results as presenting the stack first, without a second stack in memory.
            An H×W map (deg, `separate.presentation.field_at`) presents each pixel at its own
            reference (`separate.presentation.present_field`), again tile by tile.
        theta_deg: the angle of incidence (deg) of a physics-anchored network (``base="fresnel"``),
            a number or a map of any size (resized to H×W, `separate.presentation.field_at`), or
            an estimate (`separate.incidence.Incidence`); estimated per pixel from the shots at
            the reference when None (`separate.incidence.estimate_incidence`). Where an estimate
            is not clear (`separate.incidence.Incidence.clear`) the network runs without its
            gate. Ignored by other networks.
        device: where the network runs (`runner`; `separate.precision.resolve_device` chooses
            it); the tiles are built and blended on the CPU.
    """
    check_inputs(images, angles_deg)
    tile, overlap = check_tiling(tile, overlap)
    n, h, w, c = images.shape
    if c not in (1, model.channels):
        raise ValueError(f"expected shots with 1 or {model.channels} channels for this network, got {c}")
    field = reference_deg is not None and np.ndim(reference_deg) == 2
    if field and np.shape(reference_deg) != (h, w):
        raise ValueError(f"expected a reference map of shape {(h, w)}, got {np.shape(reference_deg)}")
    if reference_deg is not None and not np.isfinite(reference_deg).all():
        raise ValueError("expected a finite reference angle (deg), map or None, got non-finite values")
    theta = None
    if getattr(model, "base", "canonical") == "fresnel":
        from separate.model import without_gate
        from separate.presentation import field_at
        from separate.incidence import Incidence, estimate_incidence

        if theta_deg is None:
            theta_deg = estimate_incidence(images, angles_deg, angles_deg[0] if reference_deg is None else reference_deg)
        if isinstance(theta_deg, Incidence):
            theta_deg = theta_deg.field_deg if theta_deg.clear else None
        if theta_deg is None:
            model = without_gate(model)                   # no anchor to an angle of incidence the shots do not tell
        elif np.ndim(theta_deg) not in (0, 2) or not np.isfinite(theta_deg).all() or not (
                (np.asarray(theta_deg) > 0).all() and (np.asarray(theta_deg) < 90).all()):
            raise ValueError(f"expected an angle of incidence in (0, 90) deg, or a 2-D map of them, got "
                             f"{theta_deg if np.ndim(theta_deg) == 0 else f'a map of shape {np.shape(theta_deg)}'}")
        else:
            full = np.full((h, w), theta_deg, np.float32) if np.ndim(theta_deg) == 0 else field_at(theta_deg, (h, w))
            theta = torch.from_numpy(np.radians(full, out=full))          # in place: one full-size map, not two
    run = runner(model, precision, device)
    clip = isinstance(model, SeparationNet)
    mono = c == 1 or _equal_channels(images)
    angles = [float(a) for a in np.radians(angles_deg)]
    unit = optics.code_scale(images)
    shot_means = np.array([_clipped_mean(shot) for shot in images]) * unit   # mean(S0) is linear in them
    s0_mean = float(optics.stokes_fit(angles)[0] @ shot_means)
    scale = torch.tensor([max(s0_mean, 1e-6)], dtype=torch.float32)
    mixing = np.eye(n, dtype=np.float32)
    if field:
        mixing = optics.stokes_fit(angles).astype(np.float32)           # shots → Stokes
        reference_field = np.asarray(reference_deg, np.float32)         # to radians a strip at a time (no full-size copy)
        angles = [float(a) for a in np.radians(optics.PAPER_ANGLES_DEG)]
    elif reference_deg is not None:
        from separate.presentation import presented_angles_deg, presenting_matrix

        mixing = presenting_matrix(angles_deg, float(reference_deg))
        angles = [float(a) for a in np.radians(presented_angles_deg(float(reference_deg)))]
    mixing = torch.from_numpy(mixing * np.float32(unit))
    wrappable = images.dtype in (np.uint8, np.uint16, np.float32, np.float64)     # native byte order
    source = images if wrappable and images.flags.writeable and all(s > 0 for s in images.strides) else None

    def patch(y: int, y1: int, x: int, x1: int) -> torch.Tensor:
        """(1, N', C, h, w) float32 shots of a tile (N' = 3 when presented), linear, negatives
        clipped; built `PATCH_ROWS` rows at a time, so that a strip's temporaries stay in the
        CPU's cache, with torch ops, so the conversion runs on every intra-op thread."""
        out = torch.empty((3 if field else len(mixing), c, y1 - y, x1 - x), dtype=torch.float32)
        for r in range(y, y1, PATCH_ROWS):
            r1 = min(y1, r + PATCH_ROWS)
            if source is None:                              # a copy torch can wrap, values unscaled
                shots = torch.from_numpy(np.ascontiguousarray(images[:, r:r1, x:x1], dtype=np.float32))
            else:
                shots = torch.from_numpy(source)[:, r:r1, x:x1]
            shots = shots.permute(0, 3, 1, 2).to(torch.float32, memory_format=torch.contiguous_format)
            mixed = torch.matmul(mixing, shots.reshape(n, -1)).view(-1, c, r1 - r, x1 - x)
            if field:                                       # Stokes → each pixel's frame → its 0/45/90° shots
                local = optics.rotate_stokes(mixed, torch.from_numpy(np.radians(reference_field[r:r1, x:x1])))
                for k, phi in enumerate(angles):
                    out[k, :, r - y : r1 - y] = optics.intensity_from_stokes(local, phi)
            else:
                out[:, :, r - y : r1 - y] = mixed
        out = out.clamp_(min=0.0)[None]
        return out.expand(-1, -1, model.channels, -1, -1) if c == 1 else out

    # torch's zeroing touches the memory on every thread up front; np.zeros leaves it to the first tile
    # of each row of tiles, which on the development VM took 80-160 ms each (huge-page faults)
    r_out, t_out = (torch.zeros((h, w, c), dtype=torch.float32).numpy() for _ in range(2))
    rows, cols = tile_spans(h, tile, overlap), tile_spans(w, tile, overlap)
    row_weights, col_weights = blend_weights(rows, h, overlap), blend_weights(cols, w, overlap)
    done, total = 0, len(rows) * len(cols)
    with _freed_blocks_kept():
        for (y, y1), wy in zip(rows, row_weights):
            for (x, x1), wx in zip(cols, col_weights):
                extra = {} if theta is None else {"theta": theta[y:y1, x:x1][None, None]}
                r_hat, t_hat = run(patch(y, y1, x, x1), angles, scale, **extra)      # a temporary: freed inside once used
                if clip:                                                     # no negative light (module docstring)
                    r_hat.clamp_(min=0.0)
                    t_hat.clamp_(min=0.0)
                weight = torch.from_numpy(wy[:, None, None] * wx[None, :, None])
                for out, hat in ((r_out, r_hat), (t_out, t_hat)):
                    hat = hat[0].permute(1, 2, 0)                            # (h, w, C)
                    if mono:
                        hat = hat.mean(dim=-1, keepdim=True)
                    torch.from_numpy(out)[y:y1, x:x1].addcmul_(hat, weight)
                del r_hat, t_hat
                done += 1
                if progress:
                    progress(done, total)
    return r_out, t_out


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The C library where it is glibc (``malloc_trim`` and ``mallopt``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "malloc_trim") and hasattr(libc, "mallopt") else None
    except OSError:
        return None


#: glibc's ``mallopt`` parameters; the size up to which `_freed_blocks_kept` keeps freed blocks
#: (bytes); and the thresholds it leaves: glibc's own once it has freed a block of 32 MB or more
#: (its adaptive mmap threshold at its ceiling, the trim threshold twice that).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
KEPT_BLOCK_BYTES = 1 << 30
ADAPTED_MMAP_BYTES = 32 << 20


@contextlib.contextmanager
def _freed_blocks_kept() -> Iterator[None]:
    """Within the block, glibc serves blocks of up to `KEPT_BLOCK_BYTES` from its heap and keeps
    them when freed: by default it maps each block above 32 MB (a tile's activations take up to
    70 MB) afresh, and the kernel zeroes every page of it again, convolution after convolution
    and tile after tile (24 MP: 2.7 M page faults and 11 s of system time; 0.5 M and 4-5 s with
    the blocks kept). What was freed before is handed back on entering (`_release_freed_memory`);
    on leaving, the thresholds are glibc's adapted ones (`ADAPTED_MMAP_BYTES`) and what was kept
    is handed back too."""
    _release_freed_memory()
    libc = _glibc()
    if libc is not None:
        libc.mallopt(M_MMAP_THRESHOLD, KEPT_BLOCK_BYTES)
        libc.mallopt(M_TRIM_THRESHOLD, KEPT_BLOCK_BYTES)
    try:
        yield
    finally:
        if libc is not None:
            libc.mallopt(M_MMAP_THRESHOLD, ADAPTED_MMAP_BYTES)
            libc.mallopt(M_TRIM_THRESHOLD, 2 * ADAPTED_MMAP_BYTES)
        _release_freed_memory()


def _release_freed_memory() -> None:
    """Give the memory freed so far back to the system where the C library is glibc
    (``malloc_trim``: the free pages of its heaps)."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


def _equal_channels(images: np.ndarray) -> bool:
    """True if every shot's colour channels are equal (a coarse sample first, as most are not)."""
    coarse = images[:, ::61, ::67]
    if not all(np.array_equal(coarse[..., 0], coarse[..., k]) for k in range(1, images.shape[-1])):
        return False
    return all(np.array_equal(shot[..., 0], shot[..., k]) for shot in images for k in range(1, images.shape[-1]))


def _clipped_mean(shot: np.ndarray, rows: int = 256) -> float:
    """mean(max(shot, 0)) in float64 (in the shot's units), a block of rows at a time (no copy
    of the whole shot)."""
    if shot.dtype.kind == "u":
        return float(shot.mean(dtype=np.float64))
    total = sum(np.clip(shot[y : y + rows], 0.0, None).sum(dtype=np.float64) for y in range(0, shot.shape[0], rows))
    return float(total / shot.size)


def match_histograms(estimate: np.ndarray, reference: np.ndarray, quantiles: int = 1024) -> np.ndarray:
    """Parameter-free colour correction (paper §3.4): each channel of ``estimate`` (H×W×C) gets
    the value distribution of the same channel of ``reference`` by a monotone quantile mapping
    (``quantiles`` points, linear between; quantiles from at most ~1 M pixels of each image)."""
    if estimate.ndim != 3 or reference.ndim != 3 or estimate.shape[-1] != reference.shape[-1]:
        raise ValueError(f"expected two H×W×C images with equal C, got {estimate.shape} and {reference.shape}")
    q = np.linspace(0.0, 1.0, quantiles)
    out = np.empty_like(estimate)
    for c in range(estimate.shape[-1]):
        src, ref = estimate[..., c], reference[..., c]
        src_q = np.quantile(src.ravel()[:: max(1, src.size // 1_000_000)], q)
        ref_q = np.quantile(ref.ravel()[:: max(1, ref.size // 1_000_000)], q)
        out[..., c] = np.interp(src, src_q, ref_q)
    return out
