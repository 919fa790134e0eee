import json
import math

import cv2
import numpy as np
import pytest
import torch

from dpcn.pose import (
    Pose,
    matrix_to_pose,
    pose_to_matrix,
    sample_poses,
    unwarp_by_pose,
    warp_by_pose,
    wrap_angle,
)

from .conftest import cv2_warp, photo


@pytest.mark.parametrize("size", [(256, 256), (120, 200), (97, 131)])
def test_pose_to_matrix_matches_opencv(size):
    h, w = size
    poses = [(0.0, 0.0, 0.0, 1.0), (12.5, -7.25, 33.0, 1.1), (-40.0, 3.0, -179.5, 0.8), (5.0, 5.0, 180.0, 1.2)]
    for tx, ty, angle, scale in poses:
        expected = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
        expected[0, 2] += tx
        expected[1, 2] += ty
        got = pose_to_matrix(*(torch.tensor([v], dtype=torch.float64) for v in (tx, ty, angle, scale)), size=size)
        np.testing.assert_allclose(got[0].numpy(), expected, atol=1e-9)


def test_matrix_to_pose_round_trip():
    pose = Pose(
        torch.tensor([3.0, -20.0]), torch.tensor([1.5, 44.0]), torch.tensor([-120.0, 179.0]), torch.tensor([0.9, 1.15])
    )
    back = matrix_to_pose(pose_to_matrix(pose.tx, pose.ty, pose.angle, pose.scale, (64, 80)), (64, 80))
    torch.testing.assert_close(back.as_tensor(), pose.as_tensor(), atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize("size", [(256, 256), (101, 150)])
def test_warp_by_pose_matches_cv2_warp_affine(size):
    template = photo("astronaut", size)
    pose = (9.3, -14.1, 57.0, 1.13)
    expected = cv2_warp(template, *pose)
    got = warp_by_pose(torch.from_numpy(template)[None, None], Pose.from_tensor(torch.tensor(pose)))
    interior = (slice(4, -4), slice(4, -4))
    assert np.abs(got[0, 0].numpy() - expected)[interior].max() < 1e-3


def test_unwarp_by_pose_inverts_an_opencv_warp():
    template = photo("astronaut", (128, 128))
    pose = (9.3, -14.1, 123.0, 0.87)
    source = torch.from_numpy(cv2_warp(template, *pose))[None, None]
    pose_ = Pose.from_tensor(torch.tensor(pose))
    back = unwarp_by_pose(source, pose_)[0, 0].numpy()
    # wherever the source saw the template (a disc well inside both frames), it is the template
    yy, xx = np.mgrid[:128, :128]
    inside = (yy - 63.5 + 14.1) ** 2 + (xx - 63.5 - 9.3) ** 2 < 40**2
    inside &= (yy - 63.5) ** 2 + (xx - 63.5) ** 2 < 55**2
    assert inside.sum() > 2000 and np.abs(back - template)[inside].mean() < 0.02
    # outside what the source saw: the padding
    unseen = unwarp_by_pose(torch.from_numpy(cv2_warp(np.ones_like(template), *pose))[None, None], pose_)[0, 0] == 0
    assert unseen.sum() > 500 and (back[unseen.numpy()] == 0).all()
    # exactly the inverse of warp_by_pose, and differentiable in the pose
    poses = Pose.from_tensor(torch.tensor([[5.0, -3.0, -40.0, 1.1], [0.0, 8.0, 170.0, 0.9]], dtype=torch.float64))
    axis = torch.arange(48.0, dtype=torch.float64)
    yy, xx = torch.meshgrid(axis, axis, indexing="ij")
    image = (torch.sin(xx / 6.0) * torch.cos(yy / 7.0)).expand(2, 1, 48, 48)  # smooth: interpolation nearly exact
    round_trip = unwarp_by_pose(warp_by_pose(image, poses), poses)
    assert (round_trip - image)[..., 18:30, 18:30].abs().max() < 0.03  # two bilinear passes; a wrong inverse: ~1
    angle = poses.angle.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a: unwarp_by_pose(image, Pose(poses.tx, poses.ty, a, poses.scale)), (angle,))


def test_warp_and_unwarp_reject_bad_input():
    pose = Pose.from_tensor(torch.tensor([[1.0, 0.0, 10.0, 1.0]]))
    with pytest.raises(ValueError, match=r"image must have shape \(B, C, H, W\), got \(8, 8\)"):
        warp_by_pose(torch.rand(8, 8), pose)
    with pytest.raises(ValueError, match="1 poses for 2 images"):
        unwarp_by_pose(torch.rand(2, 1, 8, 8), pose)
    with pytest.raises(ValueError, match="image contains NaN"):
        warp_by_pose(torch.full((1, 1, 8, 8), float("nan")), pose)
    flat = Pose.from_tensor(torch.tensor([[1.0, 0.0, 10.0, 0.0]]))
    with pytest.raises(ValueError, match="scale is not a finite number > 0"):
        unwarp_by_pose(torch.rand(1, 1, 8, 8), flat)
    lost = Pose.from_tensor(torch.tensor([[1.0, 0.0, 10.0, 1.0], [float("nan"), 0.0, 10.0, 1.0]]))
    for warp in (warp_by_pose, unwarp_by_pose):  # not an image of NaN
        with pytest.raises(ValueError, match=r"NaN or infinite values: pose 1 of 2 is .*\(nan, 0.0, 10.0, 1.0\)"):
            warp(torch.rand(2, 1, 8, 8), lost)


def test_wrap_angle_range():
    angles = torch.tensor([-540.0, -180.0, -179.0, 0.0, 180.0, 181.0, 359.0, 720.0])
    wrapped = wrap_angle(angles)
    assert torch.all(wrapped > -180) and torch.all(wrapped <= 180)
    torch.testing.assert_close(wrapped, torch.tensor([180.0, 180.0, -179.0, 0.0, 180.0, -179.0, -1.0, 0.0]))
    torch.testing.assert_close(wrap_angle(torch.tensor([95.0, -90.0]), period=180.0), torch.tensor([-85.0, 90.0]))


def test_pose_container_api():
    pose = Pose.from_tensor(
        torch.tensor([[1.0, 2.0, 30.0, 1.1], [4.0, 5.0, -60.0, 0.9]]), confidence=torch.tensor([0.5, 0.2])
    )
    assert len(pose) == 2
    rows = pose.tolist()
    assert rows[1] == pytest.approx({"tx": 4.0, "ty": 5.0, "angle": -60.0, "scale": 0.9, "confidence": 0.2})
    single = pose[0]
    assert single.to_dict()["angle"] == pytest.approx(30.0)
    assert json.loads(single.to_json())["tx"] == pytest.approx(1.0)
    assert len(json.loads(pose.to_json())) == 2
    assert Pose.from_dict(single.to_dict()).to_dict() == pytest.approx(single.to_dict())
    defaults = Pose.from_dict({"tx": 1, "ty": 2, "angle": 3}).to_dict()
    assert defaults == {"tx": 1.0, "ty": 2.0, "angle": 3.0, "scale": 1.0}
    with pytest.raises(ValueError, match=r"missing \['ty', 'angle'\]"):  # not a KeyError
        Pose.from_dict({"tx": 1.0})
    with pytest.raises(ValueError, match="pose scale must be a number, got 'big'"):
        Pose.from_dict({"tx": 1.0, "ty": 2.0, "angle": 3.0, "scale": "big"})
    with pytest.raises(ValueError, match="batch of one"):
        pose.to_dict()
    with pytest.raises(ValueError, match="different batch sizes"):
        Pose(torch.zeros(2), torch.zeros(3), torch.zeros(2), torch.ones(2))
    with pytest.raises(TypeError, match="Pose.tx must be numbers .* got 'a'"):  # not torch's "new(): invalid data type"
        Pose("a", 1.0, 2.0, 1.0)
    assert Pose([0, 1], np.zeros(2), (0.0, 5.0), [1, 1]).angle.tolist() == [0.0, 5.0]
    with pytest.raises(ValueError, match=r"\(B, 4\)"):
        Pose.from_tensor(torch.zeros(2, 3))


def test_pose_cat():
    a = Pose.from_tensor(torch.tensor([[1.0, 2.0, 30.0, 1.1]]), confidence=torch.tensor([0.5]))
    b = Pose.from_tensor(torch.tensor([[3.0, 4.0, -60.0, 0.9], [5.0, 6.0, 90.0, 1.0]]), torch.tensor([0.2, 0.9]))
    both = Pose.cat([a, b])
    torch.testing.assert_close(both.as_tensor(), torch.cat([a.as_tensor(), b.as_tensor()]))
    torch.testing.assert_close(both.confidence, torch.tensor([0.5, 0.2, 0.9]))
    assert Pose.cat([a, Pose.from_tensor(b.as_tensor())]).confidence is None
    with pytest.raises(ValueError, match="at least one"):
        Pose.cat([])


def test_sample_poses_ranges_and_seed():
    g = torch.Generator().manual_seed(1)
    poses = sample_poses(2000, g, translation=50.0, rotation=(-180.0, 180.0), scale=(0.8, 1.2))
    assert poses.tx.abs().max() <= 50 and poses.ty.abs().max() <= 50
    assert poses.scale.min() >= 0.8 and poses.scale.max() <= 1.2
    assert poses.angle.min() > -180 and poses.angle.max() <= 180
    assert poses.angle.min() < -170 and poses.angle.max() > 170  # covers the full turn
    again = sample_poses(2000, torch.Generator().manual_seed(1))
    torch.testing.assert_close(poses.as_tensor(), again.as_tensor())
    with pytest.raises(ValueError, match="invalid pose ranges"):
        sample_poses(3, scale=(1.2, 0.8))
    with pytest.raises(ValueError, match="sample_poses n must be an integer >= 0, got -1"):  # not torch's
        sample_poses(-1)
    assert len(sample_poses(0)) == 0


def test_pose_matrix_is_differentiable():
    params = torch.tensor([1.0, 2.0, 30.0, 1.1], dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda p: pose_to_matrix(p[0:1], p[1:2], p[2:3], p[3:4], (32, 48)), (params,))
    assert math.isfinite(float(pose_to_matrix(*params.detach()[:, None], (8, 8)).sum()))
