"""The one pose convention of the project, and conversions to and from it.

A pose ``(tx, ty, angle, scale)`` (pixels, pixels, degrees counter-clockwise as displayed,
unitless) says that the *source* image is the *template* warped with OpenCV as::

    M = cv2.getRotationMatrix2D((W / 2, H / 2), angle, scale)
    M[0, 2] += tx
    M[1, 2] += ty
    source = cv2.warpAffine(template, M, (W, H))

i.e. a template pixel at ``p`` (x right, y down, pixel centres at integers) lands in the
source at ``scale * R(angle) @ (p - c) + c + t`` with ``c = (W / 2, H / 2)``. Angles are
reported in ``(-180, 180]``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import kornia
import torch
from torch import Tensor

from ._validate import check_int
from .ops._checks import check_image

__all__ = [
    "Pose",
    "pose_to_matrix",
    "matrix_to_pose",
    "warp_by_pose",
    "unwarp_by_pose",
    "sample_poses",
    "wrap_angle",
]


def wrap_angle(angle: Tensor | float, period: float = 360.0) -> Tensor:
    """Wrap angles (degrees) into ``(-period / 2, period / 2]``."""
    angle = torch.as_tensor(angle)
    half = period / 2.0
    wrapped = torch.remainder(angle + half, period) - half  # [-half, half)
    return torch.where(wrapped <= -half, wrapped + period, wrapped)


@dataclass
class Pose:
    """A batch of similarity poses in the project's convention (see module docstring).

    Attributes:
        tx, ty: translation in pixels, shape ``(B,)``.
        angle: rotation in degrees, counter-clockwise as displayed, shape ``(B,)``.
        scale: isotropic scale factor, shape ``(B,)``.
        confidence: optional peak strength of the correlation that produced the pose, in
            ``[0, 1]`` (1: perfect match), shape ``(B,)``.
    """

    tx: Tensor
    ty: Tensor
    angle: Tensor
    scale: Tensor
    confidence: Tensor | None = field(default=None)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            try:
                value = torch.as_tensor(value)
            except (TypeError, ValueError, RuntimeError):
                raise TypeError(f"Pose.{f.name} must be numbers (a tensor, array or list), got {value!r}") from None
            if value.ndim == 0:
                value = value.reshape(1)
            if value.ndim != 1:
                raise ValueError(f"Pose.{f.name} must be a scalar or shape (B,), got {tuple(value.shape)}")
            setattr(self, f.name, value)
        sizes = {len(getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None}
        if len(sizes) != 1:
            raise ValueError(f"Pose fields have different batch sizes: {sorted(sizes)}")

    def __len__(self) -> int:
        return len(self.tx)

    def __getitem__(self, index: int | slice | Tensor) -> Pose:
        def pick(t: Tensor | None) -> Tensor | None:
            return None if t is None else t[index].reshape(-1)

        return Pose(pick(self.tx), pick(self.ty), pick(self.angle), pick(self.scale), pick(self.confidence))

    @classmethod
    def from_tensor(cls, params: Tensor, confidence: Tensor | None = None) -> Pose:
        """Build from a ``(B, 4)`` tensor of ``(tx, ty, angle, scale)``."""
        if params.ndim == 1:
            params = params[None]
        if params.ndim != 2 or params.shape[-1] != 4:
            raise ValueError(f"expected a (B, 4) tensor of (tx, ty, angle, scale), got {tuple(params.shape)}")
        return cls(params[:, 0], params[:, 1], params[:, 2], params[:, 3], confidence)

    @classmethod
    def cat(cls, poses: Sequence[Pose]) -> Pose:
        """Concatenate batches of poses (confidence kept only if every batch has one)."""
        if not poses:
            raise ValueError("Pose.cat needs at least one pose")
        confidences = [p.confidence for p in poses]
        confidence = None if any(c is None for c in confidences) else torch.cat(confidences)
        params = (torch.cat([getattr(p, name) for p in poses]) for name in ("tx", "ty", "angle", "scale"))
        return cls(*params, confidence)

    def as_tensor(self) -> Tensor:
        """Stack into a ``(B, 4)`` tensor of ``(tx, ty, angle, scale)``."""
        return torch.stack([self.tx, self.ty, self.angle, self.scale], dim=-1)

    def to(self, *args: Any, **kwargs: Any) -> Pose:
        def move(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(*args, **kwargs)

        return Pose(move(self.tx), move(self.ty), move(self.angle), move(self.scale), move(self.confidence))

    def detach(self) -> Pose:
        def det(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.detach()

        return Pose(det(self.tx), det(self.ty), det(self.angle), det(self.scale), det(self.confidence))

    def tolist(self) -> list[dict[str, float]]:
        """One ``{"tx", "ty", "angle", "scale"[, "confidence"]}`` dict of floats per pair."""
        names = [f.name for f in fields(self) if getattr(self, f.name) is not None]
        columns = {n: getattr(self, n).detach().cpu().double().tolist() for n in names}
        return [{n: columns[n][i] for n in names} for i in range(len(self))]

    def to_dict(self) -> dict[str, float]:
        """The single pose of a batch of one as a dict of floats."""
        if len(self) != 1:
            raise ValueError(f"to_dict() needs a batch of one pose, this one has {len(self)}; use tolist()")
        return self.tolist()[0]

    def to_json(self) -> str:
        """JSON object for a batch of one, JSON list of objects otherwise."""
        return json.dumps(self.to_dict() if len(self) == 1 else self.tolist())

    @classmethod
    def from_dict(cls, d: Mapping[str, float]) -> Pose:
        """One pose from ``{"tx", "ty", "angle"[, "scale"][, "confidence"]}`` (what
        :meth:`to_dict` and ``predict`` write); ``ValueError`` naming a missing or non-numeric key."""
        missing = [key for key in ("tx", "ty", "angle") if key not in d]
        if missing:
            raise ValueError(f"a pose needs the keys tx, ty, angle[, scale, confidence]; missing {missing}")

        def number(key: str, default: float | None = None) -> Tensor | None:
            value = d.get(key, default)
            if value is None:
                return None
            try:
                return torch.tensor([float(value)], dtype=torch.float64)
            except (TypeError, ValueError):
                raise ValueError(f"pose {key} must be a number, got {value!r}") from None

        return cls(number("tx"), number("ty"), number("angle"), number("scale", 1.0), number("confidence"))

    def __repr__(self) -> str:
        rows = ", ".join("(" + ", ".join(f"{k}={v:.4g}" for k, v in row.items()) + ")" for row in self.tolist()[:4])
        more = f", ... {len(self)} in all" if len(self) > 4 else ""
        return f"Pose[{rows}{more}]"


def pose_to_matrix(tx: Tensor, ty: Tensor, angle: Tensor, scale: Tensor, size: tuple[int, int]) -> Tensor:
    """The ``(B, 2, 3)`` affine matrices (template -> source pixels) of a batch of poses.

    Identical to ``cv2.getRotationMatrix2D((W / 2, H / 2), angle, scale)`` plus the
    translation. Differentiable in all four parameters.

    Args:
        tx, ty: ``(B,)`` translation in pixels.
        angle: ``(B,)`` degrees, counter-clockwise as displayed.
        scale: ``(B,)`` scale factor.
        size: ``(H, W)`` of the images.
    """
    height, width = size
    cx, cy = width / 2.0, height / 2.0
    theta = torch.deg2rad(angle)
    a = scale * torch.cos(theta)
    b = scale * torch.sin(theta)
    row0 = torch.stack([a, b, (1 - a) * cx - b * cy + tx], dim=-1)
    row1 = torch.stack([-b, a, b * cx + (1 - a) * cy + ty], dim=-1)
    return torch.stack([row0, row1], dim=-2)


def matrix_to_pose(matrix: Tensor, size: tuple[int, int]) -> Pose:
    """Inverse of :func:`pose_to_matrix` for ``(B, 2, 3)`` similarity matrices."""
    height, width = size
    a, b = matrix[:, 0, 0], matrix[:, 0, 1]
    scale = torch.sqrt(a * a + b * b)
    angle = torch.rad2deg(torch.atan2(b, a))
    cx, cy = width / 2.0, height / 2.0
    tx = matrix[:, 0, 2] - ((1 - a) * cx - b * cy)
    ty = matrix[:, 1, 2] - (b * cx + (1 - a) * cy)
    return Pose(tx, ty, wrap_angle(angle), scale)


def _warp_affine(image: Tensor, pose: Pose, inverse: bool, mode: str, padding_mode: str) -> Tensor:
    """kornia ``warp_affine`` of ``(B, C, H, W)`` images by the matrix of ``pose`` (or its inverse)."""
    batch, _, height, width = check_image(image).shape
    if len(pose) != batch:
        raise ValueError(f"{len(pose)} poses for {batch} images: need one pose per image")
    values = pose.as_tensor()  # (B, 4): tx, ty, angle, scale
    finite = torch.isfinite(values).all(dim=1)
    if not bool(finite.all()):  # kornia would warp to an image of NaN without a word
        first = int((~finite).nonzero()[0])
        raise ValueError(
            f"cannot warp by a pose with NaN or infinite values: pose {first} of {batch} is "
            f"(tx, ty, angle, scale) = {tuple(values[first].tolist())}"
        )
    if inverse and not bool((pose.scale > 0).all()):
        raise ValueError(f"cannot un-warp by a pose whose scale is not a finite number > 0: {pose.scale.tolist()}")
    matrix = pose_to_matrix(
        *(t.to(image.device, image.dtype) for t in (pose.tx, pose.ty, pose.angle, pose.scale)),
        size=(height, width),
    )
    if inverse:
        matrix = kornia.geometry.transform.invert_affine_transform(matrix)
    return kornia.geometry.transform.warp_affine(
        image, matrix, (height, width), mode=mode, padding_mode=padding_mode, align_corners=True
    )


def warp_by_pose(
    image: Tensor,
    pose: Pose,
    mode: str = "bilinear",
    padding_mode: str = "zeros",
) -> Tensor:
    """Warp ``(B, C, H, W)`` images by ``pose`` exactly as ``cv2.warpAffine`` would (kornia).

    With ``pose`` the ground truth, ``warp_by_pose(template, pose)`` is the source.
    Differentiable with respect to the image and the pose.
    """
    return _warp_affine(image, pose, False, mode, padding_mode)


def unwarp_by_pose(
    source: Tensor,
    pose: Pose,
    mode: str = "bilinear",
    padding_mode: str = "zeros",
) -> Tensor:
    """Bring ``(B, C, H, W)`` sources onto their templates: the inverse of :func:`warp_by_pose`.

    ``unwarp_by_pose(warp_by_pose(template, pose), pose)`` is ``template`` wherever the source
    saw it (``padding_mode`` elsewhere). Differentiable with respect to the image and the pose.
    """
    return _warp_affine(source, pose, True, mode, padding_mode)


def sample_poses(
    n: int,
    generator: torch.Generator | None = None,
    translation: float | tuple[float, float] = 50.0,
    rotation: tuple[float, float] = (-180.0, 180.0),
    scale: tuple[float, float] = (0.8, 1.2),
    dtype: torch.dtype = torch.float32,
) -> Pose:
    """Draw ``n`` poses uniformly: ``tx, ty`` in ``±translation`` pixels (or a ``(low, high)``
    range), angle in ``[rotation[0], rotation[1])`` degrees, scale in ``[scale[0], scale[1]]``."""
    check_int("sample_poses n", n, low=0)
    t_lo, t_hi = (-translation, translation) if isinstance(translation, (int, float)) else translation
    if not (t_lo <= t_hi and rotation[0] <= rotation[1] and 0 < scale[0] <= scale[1]):
        raise ValueError(f"invalid pose ranges: translation={translation}, rotation={rotation}, scale={scale}")
    u = torch.rand(n, 4, generator=generator, dtype=torch.float64)
    tx = t_lo + (t_hi - t_lo) * u[:, 0]
    ty = t_lo + (t_hi - t_lo) * u[:, 1]
    angle = rotation[0] + (rotation[1] - rotation[0]) * u[:, 2]
    log_lo, log_hi = math.log(scale[0]), math.log(scale[1])
    # Uniform in scale as the paper states, not in log-scale.
    sc = (
        scale[0] + (scale[1] - scale[0]) * u[:, 3]
        if log_hi > log_lo
        else torch.full((n,), scale[0], dtype=torch.float64)
    )
    return Pose(tx.to(dtype), ty.to(dtype), wrap_angle(angle).to(dtype), sc.to(dtype))
