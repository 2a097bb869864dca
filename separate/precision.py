"""Numeric precision of the network, chosen from what the hardware runs natively.

bfloat16 is about 2-3× faster than float32 where the hardware has it (CUDA GPUs with bf16,
CPUs with AVX-512 BF16 or AMX), and 15-60× slower where torch has to emulate it (AVX2-only
CPUs). ``auto`` therefore takes bf16 only where torch reports native support, and where
oneDNN (which runs the network's convolutions) is not capped below it by ``ONEDNN_MAX_CPU_ISA``
(or its older name ``DNNL_MAX_CPU_ISA``): with ``ONEDNN_MAX_CPU_ISA=AVX2`` an AVX-512 machine
runs the network as an AVX2-only CPU would, which is how urd's AVX2 figures were measured.
"""

from __future__ import annotations

import enum
import os

import torch

#: oneDNN ISA caps (``ONEDNN_MAX_CPU_ISA``) at which bf16 convolutions run in hardware.
BF16_ISAS = {"AVX512_CORE_BF16", "AVX512_CORE_FP16", "AVX10_1_512", "AVX512_CORE_AMX", "AVX10_1_512_AMX",
             "AVX512_CORE_AMX_FP16", "AVX10_1_512_AMX_FP16", "ALL", "DEFAULT"}


class Precision(str, enum.Enum):
    """Precision choices at the CLI and in training configs."""

    AUTO = "auto"
    FP32 = "fp32"
    BF16 = "bf16"


def native_bf16(device: torch.device | str = "cpu") -> bool:
    """True where bfloat16 runs in hardware on ``device``: a CUDA device with bf16 support, or
    a CPU that torch reports with AVX-512 BF16 or AMX-BF16, unless oneDNN is capped below
    them (module docstring)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA") or os.environ.get("DNNL_MAX_CPU_ISA")
    if cap and cap.strip().upper() not in BF16_ISAS:
        return False
    caps = torch.cpu.get_capabilities()
    return bool(caps.get("avx512_bf16") or caps.get("amx_bf16"))


def resolve(precision: str | Precision, device: torch.device | str = "cpu") -> Precision:
    """The precision to run: ``auto`` becomes bf16 where native (`native_bf16`), else fp32.

    Raises ValueError for names other than auto, fp32, bf16.
    """
    try:
        choice = Precision(precision)
    except ValueError:
        raise ValueError(f"expected precision auto, fp32 or bf16, got {precision!r}") from None
    if choice is Precision.AUTO:
        return Precision.BF16 if native_bf16(device) else Precision.FP32
    return choice


def describe(precision: Precision, device: torch.device | str = "cpu") -> str:
    """A line for the user: what runs and why, e.g. 'bf16 (native AVX-512 BF16)'."""
    native = native_bf16(device)
    if precision is Precision.BF16:
        return "bf16 (native)" if native else "bf16 (emulated on this CPU: expect it to be much slower than fp32)"
    return "fp32" + ("" if native else " (no native bf16 on this device)")
