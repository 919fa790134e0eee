"""Input validation shared by the ops: clear errors instead of failures deep inside torch."""

from __future__ import annotations

import contextlib
import contextvars
import functools
from collections.abc import Callable, Iterator
from typing import ParamSpec, TypeVar

import torch
from torch import Tensor

P = ParamSpec("P")
R = TypeVar("R")

# Off inside a pipeline whose inputs were scanned once at its entry: every later scan would
# re-read a whole intermediate tensor (and on a GPU wait for it), for values computed from
# finite inputs.
_SCAN_VALUES = contextvars.ContextVar("dpcn_scan_values", default=True)


@contextlib.contextmanager
def inputs_checked() -> Iterator[None]:
    """Within the block, :func:`check_image` checks shapes and types but not for NaN/inf."""
    token = _SCAN_VALUES.set(False)
    try:
        yield
    finally:
        _SCAN_VALUES.reset(token)


def copies_of_one(x: Tensor) -> bool:
    """Whether the batch ``x`` is copies of one tensor made by ``expand`` (stride 0 along the
    batch): work per image on it can then be done once, on ``x[:1]``, and expanded."""
    return x.ndim > 0 and x.shape[0] > 1 and x.stride(0) == 0


def check_image(image: object, name: str = "image", min_size: int = 2) -> Tensor:
    """Check that ``image`` is a finite floating ``(B, C, H, W)`` tensor and return it."""
    if not isinstance(image, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (B, C, H, W), got {type(image).__name__}")
    if image.ndim != 4:
        raise ValueError(f"{name} must have shape (B, C, H, W), got {tuple(image.shape)}")
    if not image.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {image.dtype}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"{name} is empty: shape {tuple(image.shape)}")
    if image.shape[-2] < min_size or image.shape[-1] < min_size:
        raise ValueError(
            f"{name} is too small: {image.shape[-2]}x{image.shape[-1]} pixels, need at least {min_size}x{min_size}"
        )
    if _SCAN_VALUES.get() and not torch.isfinite(image).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return image


def check_pair(
    a: Tensor,
    b: Tensor,
    names: tuple[str, str] = ("template", "source"),
    min_size: int = 2,
    one_to_many: bool = False,
) -> None:
    """Check two image batches for shape, dtype and device agreement.

    ``one_to_many``: ``a`` may also be a batch of one, matched against every image of ``b``.
    """
    check_image(a, names[0], min_size)
    check_image(b, names[1], min_size)
    if a.shape[-2:] != b.shape[-2:]:
        raise ValueError(
            f"{names[0]} and {names[1]} must have the same size, got "
            f"{a.shape[-2]}x{a.shape[-1]} and {b.shape[-2]}x{b.shape[-1]}"
        )
    if a.shape[0] != b.shape[0] and not (one_to_many and a.shape[0] == 1):
        hint = f" (one {names[0]} may be matched against many {names[1]}s)" if one_to_many else ""
        raise ValueError(f"{names[0]} and {names[1]} have different batch sizes: {a.shape[0]} and {b.shape[0]}{hint}")
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"{names[0]} and {names[1]} have different channel counts: {a.shape[1]} and {b.shape[1]}")
    if a.dtype != b.dtype or a.device != b.device:
        raise ValueError(
            f"{names[0]} and {names[1]} must share dtype and device, got {a.dtype}/{a.device} and {b.dtype}/{b.device}"
        )


_LOW_PRECISION = (torch.float16, torch.bfloat16)


def full_precision(fn: Callable[P, R]) -> Callable[P, R]:
    """Run ``fn`` in float32 when given float16/bfloat16 tensors, and outside autocast.

    DFTs have no bfloat16 kernels (and lose the sub-pixel peak in float16), so under mixed
    precision the U-Nets run in low precision and the phase correlation in float32.
    """

    def promote(value: object) -> object:
        return value.float() if isinstance(value, Tensor) and value.dtype in _LOW_PRECISION else value

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        tensor = next((a for a in (*args, *kwargs.values()) if isinstance(a, Tensor)), None)
        device_type = tensor.device.type if tensor is not None else "cpu"
        with torch.autocast(device_type, enabled=False):
            return fn(*(promote(a) for a in args), **{k: promote(v) for k, v in kwargs.items()})

    return wrapper
