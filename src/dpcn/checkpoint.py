"""DPCN checkpoints without the training stack: read one safely, build its matcher.

:func:`load_model` gives the trained :class:`~dpcn.models.DPCN` of a ``dpcn fit`` checkpoint,
ready for ``.match(template, source)``, without importing Lightning or Hydra (what a robot or
a script that only matches needs, and about 2.5 s less start-up). :func:`read_checkpoint`
checks a file before torch reads it; the training package's loaders use it too.
"""

from __future__ import annotations

import pickle
import re
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ._validate import check_device
from .models.dpcn import DPCN

__all__ = [
    "CheckpointError",
    "checkpoint_file",
    "does_not_fit",
    "inference_settings",
    "load_fitting_weights",
    "load_model",
    "read_checkpoint",
    "set_inference_settings",
    "weight_differences",
]

INFERENCE_SETTINGS = (  # DPCN's settings that a loader may replace for inference (all inference-only but scale_range)
    "rotation_hypotheses",
    "hypothesis_ratio",
    "spectrum_window_grid",
    "rotation_views",
    "unet_dtype",
    "inference_radii",
    "inference_sigma",
    "rotation_range",
    "scale_range",
    "half_turn_pass",
)


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or not a dpcn checkpoint."""


def _damaged_member(path: Path) -> str | None:
    """What fails the CRC check of a torch zip archive, or ``None``. torch reads the members
    without checking them, so damage inside a tensor's bytes would load as wrong weights."""
    if not zipfile.is_zipfile(path):  # not a zip (or one without its end): torch.load tells
        return None
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as error:
        return f"a torch archive that cannot be read through ({first_sentence(error)})"
    if bad is None:
        return None
    return f"archive member {bad!r} fails its CRC check (the file changed after it was written)"


def _unreadable_reason(path: Path, error: Exception) -> str:
    """What is wrong with a file ``torch.load`` failed on, in words: torch's own message names
    its unpickler or zip reader (e.g. "Ran out of input", "[Errno 22] Invalid argument")."""
    size = path.stat().st_size
    if size == 0:
        return "the file is empty (0 bytes)"
    with path.open("rb") as f:
        head = f.read(8)
    if head.startswith(b"PK"):  # torch's zip format, the only one it has written since 1.6
        if not zipfile.is_zipfile(path):
            ending = "without its end (an interrupted write or copy?)"
            return f"the file ends too early: a torch archive of {size} bytes {ending}"
        return f"a torch archive whose contents are damaged ({first_sentence(error)})"
    if head.startswith(b"\x80"):  # a pickle: torch's legacy format
        return f"a damaged legacy torch file ({first_sentence(error)})"
    return f"not a torch file: it begins with {head!r}"


def first_sentence(error: Exception) -> str:
    """An exception's message up to its first full stop, on one line (at most 160 characters)."""
    text = " ".join(str(error).split()) or type(error).__name__
    return text.split(". ")[0].rstrip(".")[:160]


def checkpoint_file(path: str | Path) -> Path:
    """``path`` as a :class:`Path` if it is a file; :class:`CheckpointError` if it does not
    exist, or if it is a folder (a run's folder or its ``checkpoints/``), naming the
    checkpoints inside it."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise CheckpointError(f"checkpoint not found: {path}")
    found = sorted(path.glob("*.ckpt")) or sorted(path.glob("checkpoints/*.ckpt"))
    inside = ", ".join(str(p) for p in found[:3]) + (", ..." if len(found) > 3 else "")
    raise CheckpointError(
        f"{path} is a folder, not a checkpoint file; "
        + (f"it holds {inside}" if found else "it holds no .ckpt file (nor does a checkpoints/ folder in it)")
    )


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The contents of a DPCN Lightning checkpoint; :class:`CheckpointError` naming the problem
    for a missing, corrupt or foreign file. The archive's CRCs are checked first (a damaged
    tensor would otherwise load as wrong weights), and only tensors and plain values are read:
    no code in the file runs."""
    if isinstance(map_location, (str, torch.device)):  # else a mapping or function for torch.load
        check_device("map_location", map_location)
    path = checkpoint_file(path)
    unreadable = f"cannot read checkpoint {path} (corrupt or not a torch file)"
    damaged = _damaged_member(path)
    if damaged is not None:
        raise CheckpointError(f"{unreadable}: {damaged}")
    try:  # tensors and plain values only: a checkpoint from elsewhere cannot run code here
        checkpoint = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as error:
        code = re.search(r"GLOBAL ([\w.]+)", str(error))
        if code is None:
            raise CheckpointError(f"{unreadable}: {_unreadable_reason(path, error)}") from None
        raise CheckpointError(
            f"{path} holds Python objects that loading it would run ({code.group(1)}); dpcn reads only "
            "tensors and plain values from checkpoints (is the file from a source you trust?)"
        ) from None
    except Exception as error:  # torch raises many types for a damaged file
        raise CheckpointError(f"{unreadable}: {_unreadable_reason(path, error)}") from None
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint or "hyper_parameters" not in checkpoint:
        raise CheckpointError(f"{path} is not a Lightning checkpoint of a dpcn model")
    if not any(key.startswith("model.") for key in checkpoint["state_dict"]):
        raise CheckpointError(f"{path} holds no DPCN weights (was it written by `dpcn fit`?)")
    return checkpoint


def weight_differences(own: Mapping[str, torch.Tensor], weights: Mapping[str, torch.Tensor]) -> str | None:
    """Why ``weights`` do not load into a model whose state dict is ``own``, in one line (the
    first two differences and how many more: torch's own message lists every tensor), or
    ``None`` when they fit."""
    problems = [
        f"{key} is {tuple(weights[key].shape)} there, {tuple(value.shape)} here"
        for key, value in own.items()
        if key in weights and weights[key].shape != value.shape
    ]
    problems += [f"{key} missing" for key in own if key not in weights]
    problems += [f"{key} unexpected" for key in weights if key not in own]
    if not problems:
        return None
    return "; ".join(problems[:2]) + (f"; and {len(problems) - 2} more" if len(problems) > 2 else "")


def does_not_fit(path: str | Path, reason: str) -> CheckpointError:
    """The error for a checkpoint that an older or newer release wrote."""
    return CheckpointError(f"checkpoint {path} does not fit this version of dpcn: {reason}")


def load_fitting_weights(path: str | Path, module: torch.nn.Module, weights: Mapping[str, torch.Tensor]) -> None:
    """Load checkpoint ``path``'s ``weights`` into ``module``, or :func:`does_not_fit` naming the
    first differences."""
    differences = weight_differences(module.state_dict(), weights)
    if differences is not None:
        raise does_not_fit(path, f"its weights are not its model's ({differences})")
    module.load_state_dict(weights)


def dpcn_network(
    net: dict[str, Any] | None = None, temperature: float | list[float] = 0.02, learnable_temperature: bool = True
) -> DPCN:
    """The :class:`DPCN` of a ``DPCNModule``'s settings: ``net`` (``model.net``), with the
    losses' softmax temperature, learnable or fixed, as its training temperature."""
    net = dict(net or {})
    net.setdefault("train_temperature", temperature if isinstance(temperature, (int, float)) else list(temperature))
    net.setdefault("learnable_temperature", learnable_temperature)
    return DPCN(**net)


def inference_settings(**settings: Any) -> dict[str, Any]:
    """The given inference settings (names in :data:`INFERENCE_SETTINGS`) that replace a
    model's, ``None`` left out; checked for what DPCN's setters cannot tell (an unknown name,
    ``inference_radii`` as a string other than ``"trained"``), before a checkpoint is read."""
    unknown = sorted(set(settings) - set(INFERENCE_SETTINGS))
    if unknown:
        raise TypeError(f"unknown inference setting {', '.join(unknown)}; choose from {', '.join(INFERENCE_SETTINGS)}")
    radii = settings.get("inference_radii")
    if isinstance(radii, str) and radii != "trained":
        raise ValueError(f"inference_radii must be an integer >= 2 or 'trained', got {radii!r}")
    return {name: value for name, value in settings.items() if value is not None}


def set_inference_settings(model: DPCN, **settings: Any) -> DPCN:
    """Replace ``model``'s inference settings by the given values (:func:`inference_settings`;
    ``None`` keeps one). ``inference_radii="trained"`` infers with the radii the model was
    trained with (``n_radii``), whatever the checkpoint stores; DPCN's setters check the
    values. Returns ``model``."""
    for name, value in inference_settings(**settings).items():
        setattr(model, name, None if (name, value) == ("inference_radii", "trained") else value)
    return model


def load_model(
    ckpt_path: str | Path,
    map_location: str | torch.device = "cpu",
    rotation_hypotheses: int | None = None,
    hypothesis_ratio: float | None = None,
    spectrum_window_grid: int | None = None,
    rotation_views: int | None = None,
    unet_dtype: str | None = None,
    inference_radii: int | str | None = None,
    inference_sigma: float | None = None,
    rotation_range: tuple[float, float] | list[float] | None = None,
    scale_range: tuple[float, float] | list[float] | None = None,
    half_turn_pass: str | None = None,
) -> DPCN:
    """The trained :class:`~dpcn.models.DPCN` of a ``dpcn fit`` checkpoint, in eval mode on
    ``map_location``, without Lightning: ``load_model(path).match(template, source) -> Pose``.

    The inference settings replace the checkpoint's, as in
    :func:`dpcn.training.load_matcher` (``None`` keeps one; see :class:`~dpcn.models.DPCN`).
    The weights are those ``DPCNModule.load_from_checkpoint`` gives (with ``ema_decay``, the
    average). Raises :class:`CheckpointError` naming the problem for a missing, corrupt or
    foreign file.
    """
    settings = inference_settings(
        rotation_hypotheses=rotation_hypotheses,
        hypothesis_ratio=hypothesis_ratio,
        spectrum_window_grid=spectrum_window_grid,
        rotation_views=rotation_views,
        unet_dtype=unet_dtype,
        inference_radii=inference_radii,
        inference_sigma=inference_sigma,
        rotation_range=rotation_range,
        scale_range=scale_range,
        half_turn_pass=half_turn_pass,
    )
    path = Path(ckpt_path)
    checkpoint = read_checkpoint(path, map_location)
    saved = checkpoint["hyper_parameters"]
    weights = {k[len("model.") :]: v for k, v in checkpoint["state_dict"].items() if k.startswith("model.")}
    try:
        model = dpcn_network(**{k: saved[k] for k in ("net", "temperature", "learnable_temperature") if k in saved})
    except (TypeError, ValueError) as error:  # settings this release does not know or take
        raise does_not_fit(path, first_sentence(error)) from None
    load_fitting_weights(path, model, weights)
    return set_inference_settings(model, **settings).to(map_location).eval()
