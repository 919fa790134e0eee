"""The classical baselines the benchmarks compare against, checked on OpenCV-made pairs."""

import math

import cv2
import numpy as np
import pytest

from dpcn.baselines import _pose_from_inverse, opencv_fourier_mellin

from .conftest import angle_error, cv2_warp, photo
from .test_estimator import CASES


@pytest.mark.parametrize("name,tx,ty,angle,scale", CASES)
def test_opencv_fourier_mellin_recovers_opencv_poses(name, tx, ty, angle, scale):
    """The estimator's cases (both half-turns, both scale ends, shifts up to 48 px), within the
    thresholds of benchmarks/bench_registration.py, but 1.5 % of scale: OpenCV's sub-pixel
    peak reads the log-radius shift up to 1 % high at the low end (0.808 for 0.8)."""
    template = photo(name)
    pose = opencv_fourier_mellin(template, cv2_warp(template, tx, ty, angle, scale))
    assert float(pose.tx[0]) == pytest.approx(tx, abs=1.0)
    assert float(pose.ty[0]) == pytest.approx(ty, abs=1.0)
    assert angle_error(pose.angle[0], angle) < 0.5
    assert float(pose.scale[0]) == pytest.approx(scale, rel=0.015)
    assert 0.0 < float(pose.confidence[0]) <= 1.0


def test_opencv_fourier_mellin_takes_colour_and_refuses_two_sizes():
    template = photo("coffee", colour=True)
    pose = opencv_fourier_mellin(template, cv2_warp(template, 6.0, -4.0, -60.0, 0.95))
    assert angle_error(pose.angle[0], -60.0) < 0.2 and float(pose.tx[0]) == pytest.approx(6.0, abs=0.25)
    with pytest.raises(ValueError, match=r"same size, got \(256, 256\) and \(128, 256\)"):
        opencv_fourier_mellin(photo("camera"), photo("camera", (128, 256)))


@pytest.mark.parametrize(
    "tx,ty,angle,scale", [(12.5, -30.0, 40.0, 1.2), (-7.0, 4.0, -170.0, 0.8), (0.0, 0.0, 90.0, 1.0)]
)
def test_a_sources_way_back_converts_to_the_pose(tx, ty, angle, scale):
    """imreg_dft reports how to map the source back (rotate and scale about the centre, then
    shift); the pose is what OpenCV's inverse of the pose's matrix says it is."""
    size = 256
    m = cv2.getRotationMatrix2D((size / 2, size / 2), angle, scale)
    m[:, 2] += (tx, ty)
    back = cv2.invertAffineTransform(m)
    angle_back = math.degrees(math.atan2(back[0, 1], back[0, 0]))
    scale_back = math.hypot(back[0, 0], back[0, 1])
    centre = np.array([size / 2, size / 2])
    shift = back[:, :2] @ centre + back[:, 2] - centre  # where the centre goes, less the centre
    got = _pose_from_inverse(angle_back, scale_back, (float(shift[0]), float(shift[1])))
    assert got[0] == pytest.approx(tx, abs=1e-9) and got[1] == pytest.approx(ty, abs=1e-9)
    assert angle_error(got[2], angle) < 1e-9 and got[3] == pytest.approx(scale, rel=1e-12)
