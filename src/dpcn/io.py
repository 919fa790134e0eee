"""Reading images and turning user inputs into validated ``(B, C, H, W)`` tensors."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from ._validate import check_device
from .pose import Pose

__all__ = [
    "DpcnInputError",
    "read_image",
    "load_image",
    "zero_no_data",
    "to_image_tensor",
    "to_grey",
    "prepare_pair",
    "is_tensor_pair",
    "featureless_pairs",
    "flag_featureless",
]

_MIN_SIZE = 8
# Integer tensors read as images of that bit depth (torch.uint16 exists from torch 2.3 on).
_BIT_DEPTHS = {torch.uint8: 255.0, **({torch.uint16: 65535.0} if hasattr(torch, "uint16") else {})}


class DpcnInputError(ValueError):
    """A user-facing problem with an input (file, array or tensor); the message names it."""


def read_image(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode an image file: ``(image, valid)``.

    ``image`` is ``(H, W)`` grey or ``(H, W, 3)`` RGB, of dtype uint8 or uint16 (scaled by
    :func:`load_image` by their range) or float32 in ``[0, 1]``: other integer and float
    rasters (e.g. an elevation GeoTIFF in metres) are min-max normalised over their finite
    pixels unless already within ``[0, 1]``. ``valid`` is a bool ``(H, W)`` mask of the
    observed pixels, or ``None`` when the file marks none as missing: an alpha channel's zeros
    and non-finite floats (NaN, inf) are no data. No-data pixels read as 0 in ``image``, the
    convention of the whole project (the built-in maps store 0 there), so what is under an
    alpha of 0 never reaches a model.

    The bytes are read by numpy and decoded by OpenCV, so any path the OS accepts works.
    """
    path = Path(path)
    if not path.exists():
        raise DpcnInputError(f"image file not found: {path}")
    if not path.is_file():
        raise DpcnInputError(f"not a file: {path}")
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        raise DpcnInputError(f"cannot read image file {path}: {e}") from e
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise DpcnInputError(f"cannot read image file (unsupported or corrupt): {path}")
    valid = None
    if image.ndim == 3:
        if image.shape[2] in (2, 4):  # grey + alpha, BGR + alpha
            valid = image[..., -1] > 0
            image = image[..., :-1]
        if image.shape[2] == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        elif image.shape[2] == 1:
            image = image[..., 0]
        else:
            raise DpcnInputError(f"{path}: unsupported number of channels {image.shape[2]}")
    if image.dtype not in (np.uint8, np.uint16):
        image = image.astype(np.float32)
        finite = np.isfinite(image) if image.ndim == 2 else np.isfinite(image).all(-1)
        if not finite.all():
            valid = finite if valid is None else (valid & finite)
        values = image[finite]
        if values.size == 0:
            raise DpcnInputError(f"{path}: no finite pixel values")
        image = _unit_range(image, float(values.min()), float(values.max()))
    if valid is not None:
        image = zero_no_data(image, valid)
    return np.ascontiguousarray(image), valid


def zero_no_data(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``image`` ``(H, W)`` or ``(H, W, C)`` with 0 wherever the bool ``(H, W)`` mask ``valid``
    is False (the project's no-data value); same dtype."""
    return np.where(valid[..., None] if image.ndim == 3 else valid, image, 0).astype(image.dtype)


def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as ``(H, W)`` grey or ``(H, W, 3)`` RGB, float32 in ``[0, 1]``.

    8- and 16-bit PNG/JPEG/TIFF and float TIFF are supported, read as the map-pair data sets
    read them (:func:`read_image`): no-data pixels (alpha 0, NaN, inf) are 0, and float
    rasters outside ``[0, 1]`` are min-max normalised, so a crop matched at inference looks
    like the crops a model was trained on.
    """
    image, _ = read_image(path)
    return _to_unit_float(image, str(path))


def _unit_range(image: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``image`` min-max normalised from ``[lo, hi]`` to ``[0, 1]``, unless already within it."""
    return image if lo >= 0.0 and hi <= 1.0 else (image - lo) / max(hi - lo, 1e-12)


def _to_unit_float(array: np.ndarray, name: str) -> np.ndarray:
    if array.dtype == np.bool_:
        return array.astype(np.float32)
    if array.dtype in (np.uint8, np.uint16):  # 8- and 16-bit images: their full range
        return array.astype(np.float32) / float(np.iinfo(array.dtype).max)
    if np.issubdtype(array.dtype, np.integer):
        # Other integers are values, not a bit depth: int64 pixels of 0-255 (``.astype(int)``
        # of an 8-bit image) over the int64 range would all round to one float32 value.
        image = array.astype(np.float32)
        return _unit_range(image, float(image.min()), float(image.max())) if image.size else image
    if np.issubdtype(array.dtype, np.floating):
        return array.astype(np.float32, copy=False)
    raise DpcnInputError(f"{name} has unsupported dtype {array.dtype} (need integer, bool or float pixels)")


def to_image_tensor(image: np.ndarray | Tensor, name: str = "image") -> Tensor:
    """Convert a numpy ``(H, W)``/``(H, W, C)`` array or a torch ``(H, W)``/``(C, H, W)``/
    ``(B, C, H, W)`` tensor into a floating ``(B, C, H, W)`` tensor, with checks.

    8- and 16-bit unsigned integers are read by their bit depth (``/ 255``, ``/ 65535``), bool
    as 0 and 1; other integers (``int64`` from ``.astype(int)``, signed types) as values, as
    :func:`read_image` reads such rasters: min-max normalised per image unless within
    ``[0, 1]``. Float tensors keep their dtype, device and values.
    """
    if isinstance(image, (str, Path)):
        image = load_image(image)
    if isinstance(image, np.ndarray):
        if image.ndim == 2:
            image = image[:, :, None]
        if image.ndim != 3 or image.shape[2] not in (1, 3, 4):
            raise DpcnInputError(
                f"{name}: a numpy image must be (H, W) or (H, W, C) with C in 1, 3, 4; got shape {image.shape}"
            )
        if image.shape[2] == 4:  # RGBA: an alpha of 0 is no data, which reads as 0 (as in files)
            image = zero_no_data(image[:, :, :3], image[:, :, 3] > 0)
        tensor = torch.from_numpy(np.ascontiguousarray(_to_unit_float(image, name))).permute(2, 0, 1)[None]
    elif isinstance(image, Tensor):
        tensor = image
        if tensor.ndim == 2:
            tensor = tensor[None, None]
        elif tensor.ndim == 3:
            tensor = tensor[None]
        if tensor.ndim != 4:
            raise DpcnInputError(
                f"{name}: a tensor must be (H, W), (C, H, W) or (B, C, H, W); got shape {tuple(image.shape)}"
            )
        if not tensor.is_floating_point():
            if tensor.dtype == torch.bool:
                tensor = tensor.float()
            elif tensor.is_complex():
                raise DpcnInputError(f"{name}: complex tensors are not images")
            elif tensor.dtype in _BIT_DEPTHS:
                tensor = tensor.float() / _BIT_DEPTHS[tensor.dtype]
            elif tensor.numel():  # other integers: values, min-max normalised per image (as arrays)
                tensor = tensor.float()
                lo, hi = tensor.amin(dim=(1, 2, 3), keepdim=True), tensor.amax(dim=(1, 2, 3), keepdim=True)
                if bool((lo < 0).any() | (hi > 1).any()):
                    tensor = (tensor - lo) / (hi - lo).clamp_min(1e-12)
            else:
                tensor = tensor.float()
    else:
        raise DpcnInputError(f"{name}: expected a numpy array, torch tensor or file path, got {type(image).__name__}")
    if tensor.shape[0] == 0 or tensor.shape[1] == 0 or tensor.shape[-1] == 0 or tensor.shape[-2] == 0:
        raise DpcnInputError(f"{name} is empty: shape {tuple(tensor.shape)}")
    if tensor.shape[-2] < _MIN_SIZE or tensor.shape[-1] < _MIN_SIZE:
        raise DpcnInputError(
            f"{name} is {tensor.shape[-2]}x{tensor.shape[-1]} pixels; at least {_MIN_SIZE}x{_MIN_SIZE} is needed"
        )
    if not torch.isfinite(tensor).all():
        raise DpcnInputError(f"{name} contains NaN or infinite pixel values")
    return tensor


def to_grey(image: Tensor) -> Tensor:
    """``(B, 3, H, W)`` RGB -> ``(B, 1, H, W)`` luminance (ITU-R BT.601); other inputs unchanged."""
    if image.shape[1] != 3:
        return image
    weights = torch.tensor([0.299, 0.587, 0.114], device=image.device, dtype=image.dtype)
    return (image * weights[None, :, None, None]).sum(dim=1, keepdim=True)


def prepare_pair(
    template: object, source: object, device: torch.device | str | None = None, channels: int | None = None
) -> tuple[Tensor, Tensor]:
    """Validate and convert a (template, source) pair into matching ``(B, C, H, W)`` tensors.

    Channel counts that differ (grey vs colour) are reconciled by converting to grey; a
    batch of one on either side is broadcast against the other side's batch. ``channels``
    (a model's input channels, 1 or 3) converts both as the data sets read images for such a
    model: colour to grey (ITU-R BT.601, as OpenCV's ``COLOR_RGB2GRAY``), grey repeated.
    """
    t = to_image_tensor(template, "template")
    s = to_image_tensor(source, "source")
    if t.shape[-2:] != s.shape[-2:]:
        raise DpcnInputError(
            "template and source must have the same size, got "
            f"{t.shape[-2]}x{t.shape[-1]} and {s.shape[-2]}x{s.shape[-1]} (H x W)"
        )
    if t.shape[1] != s.shape[1]:
        t, s = to_grey(t), to_grey(s)
        if t.shape[1] != s.shape[1]:
            raise DpcnInputError(f"template has {t.shape[1]} channels and source {s.shape[1]}; cannot reconcile")
    if channels is not None and t.shape[1] != channels:
        if channels == 1:
            t, s = to_grey(t), to_grey(s)
        elif channels == 3 and t.shape[1] == 1:
            t, s = t.expand(-1, 3, -1, -1), s.expand(-1, 3, -1, -1)
        if t.shape[1] != channels:
            raise DpcnInputError(f"cannot convert {t.shape[1]}-channel images to the {channels} channels asked for")
    if t.shape[0] != s.shape[0] and 1 not in (t.shape[0], s.shape[0]):
        raise DpcnInputError(f"template batch {t.shape[0]} and source batch {s.shape[0]} differ")
    dtype = torch.promote_types(t.dtype, s.dtype)
    target = check_device("device", device) if device is not None else s.device
    t, s = t.to(target, dtype), s.to(target, dtype)
    # Expanded after the conversion, so the batch stays a view of one image (stride 0): DPCN
    # then runs that image's U-Nets once.
    batch = max(t.shape[0], s.shape[0])
    return t.expand(batch, -1, -1, -1), s.expand(batch, -1, -1, -1)


def is_tensor_pair(template: object, source: object) -> bool:
    """Whether ``template`` and ``source`` are already floating ``(B, C, H, W)`` tensors, which
    a matcher takes as they are; anything else goes through :func:`prepare_pair`."""
    return all(isinstance(x, Tensor) and x.ndim == 4 and x.is_floating_point() for x in (template, source))


def featureless_pairs(template: Tensor, source: Tensor) -> Tensor:
    """``(B,)`` bool: the pairs of two ``(B, C, H, W)`` batches whose template or source is
    constant (a blank image, a crop that is all no-data), from which no pose can be read."""

    def constant(images: Tensor) -> Tensor:
        flat = images.flatten(1)
        return flat.amax(dim=1) == flat.amin(dim=1)

    return constant(template) | constant(source)


def flag_featureless(pose: Pose, template: Tensor, source: Tensor, stacklevel: int = 3) -> Pose:
    """``pose`` of the ``(B, C, H, W)`` pairs with confidence 0, and a warning, for the
    :func:`featureless_pairs`: a matcher still returns a pose for them, an arbitrary one, and
    the height of its correlation peak says nothing about it. ``stacklevel``: the warning's,
    counted from this function (3: the caller's caller)."""
    blank = featureless_pairs(template, source)
    if not bool(blank.any()):
        return pose
    warnings.warn(
        f"{int(blank.sum())} of {len(blank)} pair(s) have a constant template or source (e.g. all no-data): "
        "nothing to match, so their pose is arbitrary and their confidence is set to 0",
        UserWarning,
        stacklevel=stacklevel,
    )
    confidence = pose.confidence if pose.confidence is not None else torch.ones_like(pose.tx)
    pose.confidence = confidence.masked_fill(blank.to(confidence.device), 0.0)
    return pose
