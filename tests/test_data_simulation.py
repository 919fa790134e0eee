"""Tests of the simulated DPCN training pairs (dpcn.data.simulation)."""

from __future__ import annotations

import pickle

import cv2
import numpy as np
import pytest
import torch

from dpcn.data.simulation import SIM_KINDS, SimulatedPairs


def _matrix(pose: torch.Tensor, height: int, width: int, delta: float = 0.0) -> np.ndarray:
    """The project's pose convention (see dpcn.pose), built directly with OpenCV."""
    tx, ty, angle, scale = (float(v) for v in pose)
    m = cv2.getRotationMatrix2D((width / 2.0, height / 2.0), angle + delta, scale)
    m[0, 2] += tx
    m[1, 2] += ty
    return m


def _hwc(image: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(image.numpy().transpose(1, 2, 0))


def _warp_compare(item: dict[str, torch.Tensor], delta: float = 0.0, inverse: bool = False) -> tuple[float, float]:
    """Mean |warp(template, pose) - source| on the interior where the warp is defined, and the
    fraction of the image that is."""
    template, source = _hwc(item["template"]), _hwc(item["source"])
    h, w = template.shape[:2]
    m = _matrix(item["pose"], h, w, delta)
    flags = cv2.INTER_LINEAR | (cv2.WARP_INVERSE_MAP if inverse else 0)
    warped = cv2.warpAffine(template, m, (w, h), flags=flags).reshape(source.shape)
    inside = cv2.warpAffine(np.ones((h, w), np.float32), m, (w, h), flags=flags) > 0.999
    inside = cv2.erode(inside.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return float(np.abs(warped - source)[inside].mean()), float(inside.mean())


def _unwarp(item: dict[str, torch.Tensor]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grey template, source warped back into the template frame, and its valid interior."""
    template = item["template"].mean(0).numpy()
    source = item["source"].mean(0).numpy()
    h, w = template.shape
    m = _matrix(item["pose"], h, w)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    back = cv2.warpAffine(source, m, (w, h), flags=flags)
    valid = cv2.warpAffine(np.ones_like(source), m, (w, h), flags=flags) > 0.999
    valid = cv2.erode(valid.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    return template, back, valid


def _ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    a = a[mask] - a[mask].mean()
    b = b[mask] - b[mask].mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _gradient_magnitude(image: np.ndarray) -> np.ndarray:
    image = cv2.GaussianBlur(image, (0, 0), 1.5)
    return np.hypot(cv2.Sobel(image, cv2.CV_32F, 1, 0), cv2.Sobel(image, cv2.CV_32F, 0, 1))


# --------------------------------------------------------------------------- basics


def test_sim_kinds() -> None:
    assert SIM_KINDS == ("homogeneous", "heterogeneous", "dynamic")


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("kind", SIM_KINDS)
def test_item_shapes_dtypes_ranges(kind: str, channels: int) -> None:
    ds = SimulatedPairs(kind, length=5, size=(96, 128), channels=channels, seed=2)
    assert len(ds) == 5
    for index in (0, 4):
        item = ds[index]
        assert set(item) == {"template", "source", "pose"}
        for name in ("template", "source"):
            image = item[name]
            assert image.shape == (channels, 96, 128)
            assert image.dtype == torch.float32
            assert image.is_contiguous()
            assert float(image.min()) >= 0.0 and float(image.max()) <= 1.0
            assert float(image.std()) > 0.05  # not blank
        assert item["pose"].shape == (4,) and item["pose"].dtype == torch.float32
        assert torch.isfinite(item["pose"]).all()


def test_defaults() -> None:
    ds = SimulatedPairs()
    assert ds.kind == "heterogeneous" and len(ds) == 1000
    item = ds[999]
    assert item["template"].shape == item["source"].shape == (1, 256, 256)
    assert ds[-1]["pose"].equal(item["pose"])
    with pytest.raises(IndexError):
        ds[1000]
    with pytest.raises(IndexError):
        ds[-1001]


# --------------------------------------------------------------------------- determinism


def _assert_items_equal(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    for key in ("template", "source", "pose"):
        assert torch.equal(a[key], b[key]), key


def _assert_items_differ(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    for key in ("template", "source", "pose"):
        assert not torch.equal(a[key], b[key]), key


@pytest.mark.parametrize("kind", SIM_KINDS)
def test_deterministic(kind: str) -> None:
    args = dict(kind=kind, length=10, size=(64, 80), seed=5, channels=3)
    a, b = SimulatedPairs(**args), SimulatedPairs(**args)
    b_pickled = pickle.loads(pickle.dumps(b))  # what a DataLoader worker gets
    for index in (3, 0, 7):
        _assert_items_equal(a[index], b[index])
        _assert_items_equal(a[index], b_pickled[index])
        _assert_items_equal(a[index], a[index])


def test_index_epoch_seed_change_the_pairs() -> None:
    ds = SimulatedPairs("dynamic", length=4, size=64, seed=1)
    first = ds[0]
    _assert_items_differ(first, ds[1])
    ds.set_epoch(1)
    assert ds.epoch == 1
    _assert_items_differ(first, ds[0])
    ds.set_epoch(0)
    _assert_items_equal(first, ds[0])
    _assert_items_differ(first, SimulatedPairs("dynamic", length=4, size=64, seed=2)[0])


def test_kinds_share_pose_scene_and_template() -> None:
    items = {kind: SimulatedPairs(kind, length=3, size=(72, 96), seed=4, noise=0.0)[2] for kind in SIM_KINDS}
    homogeneous, heterogeneous = items["homogeneous"], items["heterogeneous"]
    assert torch.equal(homogeneous["pose"], heterogeneous["pose"])
    assert torch.allclose(homogeneous["template"], heterogeneous["template"], atol=1e-5)
    assert not torch.allclose(homogeneous["source"], heterogeneous["source"], atol=0.1)


# --------------------------------------------------------------------------- geometry


@pytest.mark.parametrize(
    ("rotation", "scale", "size", "channels"),
    [
        ((179.0, 180.0), (0.8, 0.8), 192, 1),
        ((-180.0, -179.0), (1.2, 1.2), 192, 1),
        ((-180.0, 180.0), (0.8, 1.2), (160, 224), 1),
        ((-180.0, 180.0), (0.8, 1.2), 128, 3),
    ],
)
def test_source_is_template_warped_by_pose(rotation, scale, size, channels) -> None:
    ds = SimulatedPairs(
        "homogeneous",
        length=3,
        size=size,
        seed=3,
        rotation=rotation,
        scale=scale,
        channels=channels,
        noise=0.0,
    )
    for index in range(3):
        item = ds[index]
        tx, ty, angle, sc = (float(v) for v in item["pose"])
        assert rotation[0] <= angle <= rotation[1] or abs(abs(angle) - 180.0) < 1.0
        assert scale[0] - 1e-6 <= sc <= scale[1] + 1e-6
        diff, valid = _warp_compare(item)
        assert valid > 0.25
        assert diff < 1e-3, (item["pose"], diff)
        # The check has teeth: the inverse convention, or an angle off by 1 degree, fail it.
        assert _warp_compare(item, inverse=True)[0] > 0.02
        assert _warp_compare(item, delta=1.0)[0] > 10 * diff + 2e-3


def test_source_has_no_empty_border() -> None:
    # Extreme poses: largest translation, smallest scale, 45 degrees (largest pre-image).
    ds = SimulatedPairs(
        "heterogeneous",
        length=4,
        size=(96, 128),
        translation=50.0,
        rotation=(45.0, 45.0),
        scale=(0.8, 0.8),
        seed=8,
        noise=0.0,
    )
    for index in range(4):
        source = ds[index]["source"][0].numpy()
        for edge in (source[0], source[-1], source[:, 0], source[:, -1]):
            assert float(edge.std()) > 0.0 and float(edge.max()) > 0.0


# --------------------------------------------------------------------------- appearance


def test_heterogeneous_changes_appearance_but_keeps_structure() -> None:
    ncc = {}
    structure = []
    mismatched = []
    for kind in ("homogeneous", "heterogeneous"):
        ds = SimulatedPairs(kind, length=8, size=160, seed=11)
        values = []
        for index in range(8):
            template, back, valid = _unwarp(ds[index])
            values.append(_ncc(template, back, valid))
            if kind == "heterogeneous":
                structure.append(_ncc(_gradient_magnitude(template), _gradient_magnitude(back), valid))
                other, _, _ = _unwarp(ds[(index + 1) % 8])
                mismatched.append(_ncc(_gradient_magnitude(other), _gradient_magnitude(back), valid))
        ncc[kind] = np.array(values)
    assert ncc["homogeneous"].min() > 0.9
    assert np.abs(ncc["heterogeneous"]).mean() < 0.5
    assert np.abs(ncc["heterogeneous"]).mean() < ncc["homogeneous"].mean() - 0.45
    # Non-monotonic: some heterogeneous pairs are even anti-correlated.
    assert ncc["heterogeneous"].min() < -0.1
    # The region boundaries (gradient magnitude) remain common to both images.
    assert np.mean(structure) > 0.25
    assert np.mean(structure) > np.mean(mismatched) + 0.2


def test_phase_correlation_fails_on_heterogeneous() -> None:
    success = {}
    for kind in ("homogeneous", "heterogeneous"):
        ds = SimulatedPairs(
            kind,
            length=16,
            size=128,
            seed=7,
            translation=20.0,
            rotation=(0.0, 0.0),
            scale=(1.0, 1.0),
        )
        hits = 0
        for index in range(16):
            item = ds[index]
            template = item["template"][0].numpy().astype(np.float64)
            source = item["source"][0].numpy().astype(np.float64)
            (dx, dy), _ = cv2.phaseCorrelate(template, source)
            hits += np.hypot(dx - float(item["pose"][0]), dy - float(item["pose"][1])) < 2.0
        success[kind] = hits / 16
    assert success["homogeneous"] >= 0.9
    assert success["heterogeneous"] <= 0.4


@pytest.mark.parametrize("channels", [1, 3])
def test_dynamic_obstacles_are_the_only_difference(channels: int) -> None:
    obstacles = 3
    args = dict(length=4, size=128, seed=9, channels=channels, obstacles=obstacles)
    dynamic = SimulatedPairs("dynamic", **args)
    heterogeneous = SimulatedPairs("heterogeneous", **args)
    in_both = 0
    template_total = 0
    for index in range(4):
        d, h = dynamic[index], heterogeneous[index]
        assert torch.equal(d["pose"], h["pose"])
        masks = {}
        for name in ("template", "source"):
            changed = (d[name] != h[name]).any(0).numpy()
            assert 0.0 < changed.mean() < 0.1  # a few small obstacles
            count, _ = cv2.connectedComponents(changed.astype(np.uint8), connectivity=8)
            assert 1 <= count - 1 <= obstacles  # at most `obstacles` blobs (some may merge)
            masks[name] = changed
        # Template obstacles are not in the source: where they land, the source is unchanged
        # (up to the chance overlap with the source's own obstacles).
        m = _matrix(d["pose"], 128, 128)
        landed = cv2.warpAffine(masks["template"].astype(np.float32), m, (128, 128)) > 0.5
        in_both += int((landed & masks["source"]).sum())
        template_total += int(landed.sum())
    assert template_total > 0
    assert in_both < 0.2 * template_total


def test_dynamic_without_obstacles_is_heterogeneous() -> None:
    args = dict(length=2, size=64, seed=3, obstacles=0)
    _assert_items_equal(SimulatedPairs("dynamic", **args)[1], SimulatedPairs("heterogeneous", **args)[1])


@pytest.mark.parametrize("kind", ["heterogeneous", "dynamic"])
@pytest.mark.parametrize("channels", [1, 3])
def test_appearance_change_cross_fades_to_the_homogeneous_source(kind: str, channels: int) -> None:
    args = dict(length=3, size=(80, 112), seed=5, channels=channels, noise=0.0, obstacles=0)
    full = SimulatedPairs(kind, **args)
    _assert_items_equal(SimulatedPairs(kind, appearance_change=1.0, **args)[2], full[2])  # the default
    none = SimulatedPairs(kind, appearance_change=0.0, **args)[2]
    homogeneous = SimulatedPairs("homogeneous", **args)[2]
    assert torch.equal(none["pose"], homogeneous["pose"])
    assert torch.allclose(none["template"], full[2]["template"])
    assert torch.allclose(none["source"], homogeneous["source"], atol=1e-5)
    assert not torch.allclose(none["source"], full[2]["source"], atol=0.1)
    half = SimulatedPairs(kind, appearance_change=0.25, **args)[2]
    assert torch.allclose(half["source"], 0.25 * full[2]["source"] + 0.75 * none["source"], atol=1e-5)


def test_noise_zero_and_noise_level() -> None:
    clean = SimulatedPairs("homogeneous", length=1, size=96, noise=0.0)[0]
    noisy = SimulatedPairs("homogeneous", length=1, size=96, noise=0.05)[0]
    residual = (noisy["template"] - clean["template"]).numpy()
    interior = (clean["template"].numpy() > 0.2) & (clean["template"].numpy() < 0.8)
    assert 0.04 < float(residual[interior].std()) < 0.06
    assert abs(float(residual[interior].mean())) < 0.01


# --------------------------------------------------------------------------- poses


def test_pose_ranges() -> None:
    ds = SimulatedPairs(
        "homogeneous",
        length=40,
        size=32,
        translation=10.0,
        rotation=(-30.0, 60.0),
        scale=(0.9, 1.1),
        seed=12,
    )
    poses = torch.stack([ds[i]["pose"] for i in range(40)]).double()
    tx, ty, angle, scale = poses.unbind(1)
    for t in (tx, ty):
        assert t.abs().max() <= 10.0 and t.max() - t.min() > 10.0
    assert angle.min() >= -30.0 and angle.max() < 60.0 and angle.max() - angle.min() > 45.0
    assert scale.min() >= 0.9 - 1e-6 and scale.max() <= 1.1 + 1e-6
    assert scale.max() - scale.min() > 0.1
    assert len(set(poses[:, 2].tolist())) == 40


def test_pose_angles_are_wrapped() -> None:
    ds = SimulatedPairs("homogeneous", length=30, size=16, translation=4.0, rotation=(170.0, 190.0), seed=1)
    angle = torch.stack([ds[i]["pose"][2] for i in range(30)])
    assert (angle > -180.0).all() and (angle <= 180.0).all()
    assert ((angle >= 170.0) | (angle <= -170.0)).all()
    assert (angle > 0).any() and (angle < 0).any()
    default = SimulatedPairs("homogeneous", length=30, size=16, translation=4.0, seed=1)
    angle = torch.stack([default[i]["pose"][2] for i in range(30)])
    assert (angle > -180.0).all() and (angle <= 180.0).all() and angle.std() > 60.0


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"kind": "rgb"}, "kind"),
        ({"kind": "Homogeneous"}, "kind"),
        ({"length": 0}, "length"),
        ({"length": 2.5}, "length"),
        ({"size": 15}, "size"),
        ({"size": (16, 15)}, "size"),
        ({"size": (32, 32, 3)}, "size"),
        ({"size": "big"}, "size"),
        ({"seed": -1}, "seed"),
        ({"translation": -1.0}, "translation"),
        ({"translation": float("nan")}, "translation"),
        ({"rotation": (10.0, -10.0)}, "rotation"),
        ({"rotation": (0.0,)}, "rotation"),
        ({"scale": (1.2, 0.8)}, "scale"),
        ({"scale": (0.0, 1.0)}, "scale"),
        ({"scale": (-1.0, 1.0)}, "scale"),
        ({"channels": 2}, "channels"),
        ({"channels": 4}, "channels"),
        ({"noise": -0.1}, "noise"),
        ({"obstacles": -1}, "obstacles"),
        ({"appearance_change": -0.1}, "appearance_change"),
        ({"appearance_change": 1.5}, "appearance_change"),
        ({"appearance_change": float("nan")}, "appearance_change"),
        ({"appearance_change": "strong"}, "appearance_change"),
        ({"appearance_change": True}, "appearance_change"),
    ],
)
def test_invalid_arguments(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        SimulatedPairs(**kwargs)


def test_unknown_kind_lists_the_valid_ones() -> None:
    with pytest.raises(ValueError) as info:
        SimulatedPairs("static")
    for kind in SIM_KINDS:
        assert kind in str(info.value)


@pytest.mark.parametrize("epoch", [-1, 1.5, None])
def test_invalid_epoch(epoch) -> None:
    ds = SimulatedPairs(length=1, size=16)
    with pytest.raises(ValueError, match="epoch"):
        ds.set_epoch(epoch)
