"""``dpcn.register``: classical (non-learned) registration of two images in one call."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from .estimator import PhaseCorrelationEstimator
from .io import flag_featureless, prepare_pair
from .pose import Pose

__all__ = ["register"]


def register(
    template: np.ndarray | Tensor | str,
    source: np.ndarray | Tensor | str,
    device: torch.device | str | None = None,
    **options: Any,
) -> Pose:
    """Estimate the similarity pose that maps ``template`` onto ``source``.

    Args:
        template, source: numpy ``(H, W)`` / ``(H, W, 3)`` arrays, torch ``(H, W)`` /
            ``(C, H, W)`` / ``(B, C, H, W)`` tensors (batched), or image file paths. Integer
            images are scaled to ``[0, 1]`` (:func:`dpcn.io.to_image_tensor`). Sizes must match.
        device: where to compute (default: the source tensor's device, CPU for numpy).
        **options: :class:`~dpcn.estimator.PhaseCorrelationEstimator` settings.

    Returns:
        :class:`~dpcn.pose.Pose` with ``(B,)`` fields and a ``confidence`` in ``[0, 1]``:
        ``source ~= cv2.warpAffine(template, M(pose), (W, H))`` (see :mod:`dpcn.pose`). A pair
        whose template or source is constant has confidence 0, with a warning
        (:func:`dpcn.io.flag_featureless`).

    Example:
        >>> pose = dpcn.register(template_array, source_array)
        >>> pose.to_dict()  # {'tx': ..., 'ty': ..., 'angle': ..., 'scale': ..., 'confidence': ...}
    """
    t, s = prepare_pair(template, source, device)
    estimator = PhaseCorrelationEstimator(**options)
    with torch.no_grad():
        return flag_featureless(estimator(t, s), t, s)
