"""dpcn: Deep Phase Correlation Network (CoRL 2020) and differentiable Fourier-Mellin registration.

Pose convention (everywhere in the package): a pose ``(tx, ty, angle, scale)`` means
``source = cv2.warpAffine(template, M, (W, H))`` with
``M = cv2.getRotationMatrix2D((W / 2, H / 2), angle, scale)`` plus ``(tx, ty)`` added to its
last column; ``angle`` in degrees, counter-clockwise as displayed, in ``(-180, 180]``.
"""

from .checkpoint import CheckpointError, load_model
from .estimator import PhaseCorrelationEstimator
from .io import DpcnInputError, load_image
from .pose import Pose, pose_to_matrix, sample_poses, unwarp_by_pose, warp_by_pose
from .registration import register

__version__ = "0.1.0"

__all__ = [
    "CheckpointError",
    "DpcnInputError",
    "PhaseCorrelationEstimator",
    "Pose",
    "load_image",
    "load_model",
    "pose_to_matrix",
    "register",
    "sample_poses",
    "unwarp_by_pose",
    "warp_by_pose",
    "__version__",
]
