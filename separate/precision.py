"""Numeric precision of the network, chosen from what the hardware runs natively.

bfloat16 is about 2-3× faster than float32 where the hardware has it (CUDA GPUs with bf16,
CPUs with AVX-512 BF16 or AMX), and 15-60× slower where torch has to emulate it (AVX2-only
CPUs). ``auto`` therefore takes bf16 only where torch reports native support, and where
oneDNN (which runs the network's convolutions) is not capped below it by ``ONEDNN_MAX_CPU_ISA``
(or its older name ``DNNL_MAX_CPU_ISA``): with ``ONEDNN_MAX_CPU_ISA=AVX2`` an AVX-512 machine
runs the network as an AVX2-only CPU would, which is how urd's AVX2 figures were measured.

Where the network runs (`Device`): ``auto`` takes a CUDA GPU where torch sees one, else the CPU;
``cuda`` without one is refused (`resolve_device`). On a GPU the network runs as a module,
under bf16 autocast where the GPU has bf16, in tiles sized to its free memory (`gpu_tile`).

The names are checked without torch (`parse_precision`, `parse_device`): the command line refuses
a bad option at once; torch is imported where a device is looked at.
"""

from __future__ import annotations

import enum
import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

#: oneDNN ISA caps (``ONEDNN_MAX_CPU_ISA``) at which bf16 convolutions run in hardware.
BF16_ISAS = {"AVX512_CORE_BF16", "AVX512_CORE_FP16", "AVX10_1_512", "AVX512_CORE_AMX", "AVX10_1_512_AMX",
             "AVX512_CORE_AMX_FP16", "AVX10_1_512_AMX_FP16", "ALL", "DEFAULT"}


#: Resident GPU memory (bytes) per pixel of a tile when the network runs as a module: its peak
#: over the forward pass, measured on the CPU (fp32, 512² and 1024² tiles of urd-anchored: 0.85–1.05 kB/px), with a margin.
MODULE_BYTES_PER_PIXEL = 1600
#: Share of the GPU's free memory a tile may take, and the largest tile side (px).
GPU_MEMORY_SHARE = 0.5
MAX_GPU_TILE = 8192


class Device(str, enum.Enum):
    """Where the network runs: ``auto`` (a CUDA GPU where torch sees one, else the CPU), ``cpu``, ``cuda``."""

    AUTO = "auto"
    CPU = "cpu"
    CUDA = "cuda"


def parse_device(device: str | Device) -> Device:
    """The `Device` named ``device``; ValueError for other names (no torch needed)."""
    try:
        return Device(device)
    except ValueError:
        raise ValueError(f"expected device auto, cpu or cuda, got {device!r}") from None


def resolve_device(device: str | Device) -> torch.device:
    """The torch device to run the network on (`Device`). ValueError for other names, and for
    ``cuda`` where torch sees no CUDA device (a CPU-only torch build, or no driver or GPU)."""
    import torch

    choice = parse_device(device)
    cuda = torch.cuda.is_available()
    if choice is Device.CUDA and not cuda:
        build = f"built with CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        raise ValueError(f"device 'cuda': torch {torch.__version__} ({build}) sees no CUDA device; "
                         "use device 'cpu' (or 'auto'), or install torch with CUDA on a machine with an NVIDIA GPU")
    return torch.device("cuda" if choice is Device.CUDA or (choice is Device.AUTO and cuda) else "cpu")


def gpu_tile(free_bytes: int, bf16: bool) -> int:
    """Tile side (px, a multiple of 8) whose module forward pass fits `GPU_MEMORY_SHARE` of
    ``free_bytes`` (`MODULE_BYTES_PER_PIXEL`, halved in bf16), at most `MAX_GPU_TILE`."""
    per_pixel = MODULE_BYTES_PER_PIXEL // (2 if bf16 else 1)
    side = int((GPU_MEMORY_SHARE * free_bytes / per_pixel) ** 0.5)
    return min(MAX_GPU_TILE, side) // 8 * 8


class Precision(str, enum.Enum):
    """Precision choices at the CLI and in training configs."""

    AUTO = "auto"
    FP32 = "fp32"
    BF16 = "bf16"


def native_bf16(device: torch.device | str = "cpu") -> bool:
    """True where bfloat16 runs in hardware on ``device``: a CUDA device with bf16 support, or
    a CPU that torch reports with AVX-512 BF16 or AMX-BF16, unless oneDNN is capped below
    them (module docstring)."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA") or os.environ.get("DNNL_MAX_CPU_ISA")
    if cap and cap.strip().upper() not in BF16_ISAS:
        return False
    caps = torch.cpu.get_capabilities()
    return bool(caps.get("avx512_bf16") or caps.get("amx_bf16"))


def parse_precision(precision: str | Precision) -> Precision:
    """The `Precision` named ``precision``; ValueError for other names (no torch needed)."""
    try:
        return Precision(precision)
    except ValueError:
        raise ValueError(f"expected precision auto, fp32 or bf16, got {precision!r}") from None


def resolve(precision: str | Precision, device: torch.device | str = "cpu") -> Precision:
    """The precision to run: ``auto`` becomes bf16 where native (`native_bf16`), else fp32.

    Raises ValueError for names other than auto, fp32, bf16.
    """
    choice = parse_precision(precision)
    if choice is Precision.AUTO:
        return Precision.BF16 if native_bf16(device) else Precision.FP32
    return choice


def describe(precision: Precision, device: torch.device | str = "cpu") -> str:
    """A line for the user: what runs and why, e.g. 'bf16 (native AVX-512 BF16)'."""
    native = native_bf16(device)
    if precision is Precision.BF16:
        return "bf16 (native)" if native else "bf16 (emulated on this CPU: expect it to be much slower than fp32)"
    return "fp32" + ("" if native else " (no native bf16 on this device)")
