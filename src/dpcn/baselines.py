"""Classical baselines, one pair at a time (numpy/OpenCV), in the project's pose convention.

- :func:`opencv_fourier_mellin`: Fourier-Mellin registration built from OpenCV primitives
  (``cv2.warpPolar`` for the log-polar map, ``cv2.phaseCorrelate`` for both correlations),
  with the same half-turn resolution as :class:`dpcn.PhaseCorrelationEstimator`.
- :func:`imreg_dft_similarity`: ``imreg_dft.similarity`` (an optional dependency) with its
  result converted to this project's convention.

They exist to be compared against (benchmarks, evaluation tables), not to be fast or
differentiable.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .pose import Pose

__all__ = ["opencv_fourier_mellin", "imreg_dft_similarity"]


def _as_grey_float(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image[..., :3].astype(np.float32), cv2.COLOR_RGB2GRAY)
    return image.astype(np.float64)


def _pose_from_inverse(angle_inv: float, scale_inv: float, shift_xy: tuple[float, float]) -> tuple[float, ...]:
    """Our pose from "rotate by angle_inv / scale by scale_inv about the centre, then shift"
    that maps the *source* back onto the template."""
    angle, scale = -angle_inv, 1.0 / scale_inv
    theta = math.radians(angle)
    a, b = scale * math.cos(theta), scale * math.sin(theta)
    dx, dy = shift_xy
    return (-(a * dx + b * dy), -(-b * dx + a * dy), angle, scale)


def _wrap(angle: float) -> float:
    angle = (angle + 180.0) % 360.0 - 180.0
    return 180.0 if angle == -180.0 else angle


def opencv_fourier_mellin(template: np.ndarray, source: np.ndarray) -> Pose:
    """Fourier-Mellin registration with OpenCV: ``cv2.warpPolar`` + ``cv2.phaseCorrelate``.

    Args:
        template, source: ``(H, W)`` or ``(H, W, 3)`` arrays of the same size.

    Returns:
        A :class:`~dpcn.pose.Pose` of one pair (confidence = ``phaseCorrelate``'s response).
    """
    t, s = _as_grey_float(template), _as_grey_float(source)
    if t.shape != s.shape:
        raise ValueError(f"template and source must have the same size, got {t.shape} and {s.shape}")
    h, w = t.shape
    window = cv2.createHanningWindow((w, h), cv2.CV_64F)
    fy = np.fft.fftshift(np.fft.fftfreq(h))[:, None]
    fx = np.fft.fftshift(np.fft.fftfreq(w))[None, :]
    x = np.cos(np.pi * fy * 2 / 2) * np.cos(np.pi * fx * 2 / 2)
    highpass = (1.0 - x) * (2.0 - x)

    def spectrum(img: np.ndarray) -> np.ndarray:
        return np.abs(np.fft.fftshift(np.fft.fft2((img - img.mean()) * window))) * highpass

    radius = min(h, w) / 2.0
    # (columns: log-radius, rows: angle over 360 degrees). With only `radius` columns the
    # rotation-invariant part of the spectrum out-scores the true peak; twice that works.
    size = (int(2 * radius), 360)
    flags = cv2.WARP_POLAR_LOG | cv2.INTER_LINEAR
    # Drop the innermost radii (< 3 % of Nyquist): in a log-radius map they take up a quarter
    # of the columns and hold mostly the window's own, rotation-invariant, leakage.
    first = int(math.ceil(math.log(0.03 * radius) / math.log(radius) * size[0]))
    lp_t = np.ascontiguousarray(cv2.warpPolar(spectrum(t), size, (w / 2, h / 2), radius, flags)[:, first:])
    lp_s = np.ascontiguousarray(cv2.warpPolar(spectrum(s), size, (w / 2, h / 2), radius, flags)[:, first:])
    # phaseCorrelate's Hann window on the log-polar maps too: their log-radius axis is not
    # periodic (its ends hold the lowest and the highest frequencies), and unwindowed that
    # edge matches itself at no shift, reading many scales as 1.0 (51 % of bench_registration's
    # pairs found, against 94 %). The angle axis spans 360 degrees of a spectrum that repeats
    # every 180, so the window's middle still holds a whole period.
    window_lp = cv2.createHanningWindow((lp_t.shape[1], lp_t.shape[0]), cv2.CV_64F)
    (d_log, d_angle), _ = cv2.phaseCorrelate(lp_t, lp_s, window_lp)
    angle = -d_angle * 360.0 / size[1]
    scale = math.exp(-d_log * math.log(radius) / size[0])

    best = None
    for candidate in (angle, angle + 180.0):
        m = cv2.getRotationMatrix2D((w / 2, h / 2), -candidate, 1.0 / scale)
        unwarped = cv2.warpAffine(s, m, (w, h))
        (dx, dy), response = cv2.phaseCorrelate(t, unwarped, window)
        if best is None or response > best[0]:
            best = (response, candidate, dx, dy)
    response, angle, dx, dy = best
    theta = math.radians(angle)
    a, b = scale * math.cos(theta), scale * math.sin(theta)
    tx, ty = a * dx + b * dy, -b * dx + a * dy
    return Pose(
        *(np.array([v], dtype=np.float64) for v in (tx, ty, _wrap(angle), scale)),
        confidence=np.array([response]),
    )


def imreg_dft_similarity(template: np.ndarray, source: np.ndarray, **kwargs) -> Pose:
    """``imreg_dft.similarity(template, source)`` converted to the project's convention.

    ``imreg_dft`` reports the transform that maps the *source* back onto the template
    (angle, scale, and a ``(y, x)`` shift applied after rotating/scaling about the centre);
    this returns the inverse, i.e. the pose that maps the template onto the source. Its
    rotation centre follows from scipy.ndimage zoom/rotate on a padded canvas and is not
    exactly ``(W / 2, H / 2)``; the difference (a fraction of a pixel, growing with the angle)
    is left in, so it counts as imreg_dft's error.

    Raises:
        ModuleNotFoundError: if ``imreg_dft`` is not installed (``pip install imreg_dft``).
    """
    import imreg_dft

    result = imreg_dft.similarity(_as_grey_float(template), _as_grey_float(source), **kwargs)
    ty_inv, tx_inv = (float(v) for v in result["tvec"])
    tx, ty, angle, scale = _pose_from_inverse(float(result["angle"]), float(result["scale"]), (tx_inv, ty_inv))
    return Pose(
        *(np.array([v], dtype=np.float64) for v in (tx, ty, _wrap(angle), scale)),
        confidence=np.array([float(result.get("success", float("nan")))]),
    )
