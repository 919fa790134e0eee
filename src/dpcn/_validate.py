"""Checks of plain settings (numbers from a config file or the command line).

A value such as ``model.lr=abc`` arrives as a string and would otherwise fail deep inside
torch or Lightning with ``'<=' not supported between 'float' and 'str'``. These checks name
the setting instead. They sit below every other module (no dpcn imports).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

__all__ = ["check_bool", "check_device", "check_int", "check_ints", "check_number", "check_sequence"]


def check_bool(name: str, value: object) -> bool:
    """``value`` as a ``bool``; ``ValueError`` naming ``name`` otherwise.

    Only ``True``/``False`` (numpy's too) pass: a switch given as ``maybe`` or ``2`` on the
    command line is a typo, not a truthy value.
    """
    if type(value).__name__ not in ("bool", "bool_"):
        raise ValueError(f"{name} must be true or false, got {value!r}")
    return bool(value)


def check_device(name: str, value: object) -> torch.device:
    """``value`` (a device name such as ``cpu``, ``cuda:1``, or a ``torch.device``) as a
    ``torch.device`` this machine has; ``ValueError`` naming ``name`` otherwise. torch would
    say so only when the first tensor moves, deep in a load or a match, or call a checkpoint
    mapped to a missing GPU corrupt."""
    import torch  # here, not at the top: these checks sit below everything and load fast

    try:
        device = torch.device(value)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"{name} must be a device such as cpu, cuda or cuda:0, got {value!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{name}={value} requested but CUDA is not available")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise ValueError(f"{name}={value} requested but this machine has {torch.cuda.device_count()} CUDA device(s)")
    if device.type == "meta":
        raise ValueError(f"{name}={value}: the meta device holds no values to compute with")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{name}={value} requested but MPS (Apple GPUs) is not available")
    if device.type not in ("cpu", "cuda", "mps"):
        try:
            torch.empty(0, device=device)
        except Exception as error:  # backends fail as they may: RuntimeError, AssertionError, ImportError
            reason = " ".join(str(error).split()).split(". ")[0]
            raise ValueError(f"{name}={value} requested but this machine cannot use it ({reason})") from None
    return device


def check_int(name: str, value: object, low: int | None = None) -> int:
    """``value`` as an ``int`` (``>= low`` if given); ``ValueError`` naming ``name`` otherwise.

    Python and numpy integers pass; floats (even ``4.0``: sizes and counts are used as
    given), booleans and strings do not.
    """
    bound = "" if low is None else f" >= {low}"
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if not ok or (low is not None and value < low):
        raise ValueError(f"{name} must be an integer{bound}, got {value!r}")
    return int(value)


def check_ints(prefix: str, *settings: tuple[str, object, int]) -> None:
    """:func:`check_int` for each ``(name, value, low)``, named ``prefix + name``; ``None``
    values (optional settings left unset) are skipped."""
    for name, value, low in settings:
        if value is not None:
            check_int(f"{prefix}{name}", value, low)


def check_sequence(name: str, value: object, length: int, what: str) -> None:
    """``ValueError`` unless ``value`` is a list or tuple (not a string) of ``length`` items;
    ``what`` describes it in the message (``"an (H, W) pair of integers"``)."""
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != length:
        raise ValueError(f"{name} must be {what}, got {value!r}")


def check_number(
    name: str,
    value: object,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
) -> float:
    """``value`` as a finite ``float`` in ``[low, high]`` (``(low, high]`` with ``low_open``).

    Raises ``ValueError`` naming ``name`` and the allowed range otherwise.
    """
    if low is not None and high is not None:
        bound = f" in {'(' if low_open else '['}{low:g}, {high:g}]"
    elif low is not None:
        bound = f" {'>' if low_open else '>='} {low:g}"
    else:
        bound = "" if high is None else f" <= {high:g}"
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        raise ValueError(f"{name} must be a finite number{bound}, got {value!r}")
    return float(value)
