"""The training precision that ``trainer.precision=auto`` picks for the hardware at hand.

bfloat16 mixed precision runs the U-Nets' convolutions in bfloat16 and, by
:func:`dpcn.ops._checks.full_precision`, every DFT, log-polar resampling and correlation in
float32. On a CPU that computes bfloat16 in hardware it trained 1.5x faster, to the same accuracy
(README, Benchmarks); elsewhere bfloat16 would only be emulated (not measured: no such machine
here). So ``auto`` chooses by the device, and evaluation (``validate`` / ``test``) always runs in
float32.
"""

from __future__ import annotations

import torch

__all__ = ["AUTO", "BF16", "FP32", "LIGHTNING_PRECISIONS", "auto_precision", "cpu_computes_bfloat16"]

AUTO = "auto"
BF16 = "bf16-mixed"
FP32 = "32-true"
# What Lightning's Trainer accepts as ``precision`` (besides AUTO, which dpcn resolves first).
LIGHTNING_PRECISIONS = ("32-true", "bf16-mixed", "16-mixed", "bf16-true", "16-true", "64-true",
                        "transformer-engine", "transformer-engine-float16", "32", "16", "bf16", "64")  # fmt: skip


def cpu_computes_bfloat16() -> bool:
    """Whether this CPU has bfloat16 arithmetic in hardware (x86 AVX512-BF16 or AMX).

    PyTorch reports these through private probes; a build without them answers ``False``.
    """
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in probes)


def _cuda_computes_bfloat16() -> bool:
    try:  # PyTorch >= 2.3: emulated bfloat16 (pre-Ampere GPUs) does not count
        return torch.cuda.is_bf16_supported(including_emulation=False)
    except TypeError:
        return torch.cuda.is_bf16_supported()


def auto_precision(accelerator: str) -> tuple[str, str]:
    """Lightning's precision for training on ``accelerator``, and why.

    Args:
        accelerator: the trainer's ``accelerator`` (``cpu``, ``gpu``, ``cuda`` or ``auto``;
            ``auto`` means a CUDA GPU if there is one, else the CPU, as Lightning picks).

    Returns:
        ``("bf16-mixed", reason)`` where the device computes bfloat16 in hardware (a CUDA GPU of
        the Ampere generation or later; a CPU with AVX512-BF16 or AMX), else ``("32-true", reason)``.
    """
    name = str(accelerator).lower()
    on_gpu = name in ("gpu", "cuda") or (name == AUTO and torch.cuda.is_available())
    if on_gpu:
        if torch.cuda.is_available() and _cuda_computes_bfloat16():
            return BF16, "this GPU computes bfloat16"
        return FP32, "no GPU that computes bfloat16 in hardware"
    if name not in ("cpu", AUTO):
        return FP32, f"accelerator={accelerator}: bfloat16 is chosen only for CPUs and CUDA GPUs"
    if cpu_computes_bfloat16():
        return BF16, "this CPU computes bfloat16 in hardware (AVX512-BF16 or AMX)"
    return FP32, "this CPU has no bfloat16 arithmetic in hardware (it would only be emulated)"
