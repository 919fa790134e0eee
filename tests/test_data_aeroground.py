"""Procedural scenes (dpcn.data.scene) and the map-pair readers (dpcn.data.aeroground)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dpcn.data.aeroground import PAIRS, CsvPairs, DataError, MapPairs
from dpcn.data.scene import generate_scene, make_dataset, write_scene

# ----------------------------------------------------------------------------- helpers


def _texture(seed: int, h: int, w: int, blur: float = 2.0) -> np.ndarray:
    """Smooth random uint8 texture in [10, 245] (never 0, so empty borders show)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), blur)
    img = (img - img.min()) / (img.max() - img.min())
    return np.round(10 + 235 * img).astype(np.uint8)


def _imwrite(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image), path


def _matrix(pose, size):
    tx, ty, angle, scale = (float(v) for v in pose)
    h, w = size
    m = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
    m[0, 2] += tx
    m[1, 2] += ty
    return m


def _interior(m, size, erode=3):
    """Source pixels whose preimage lies well inside the template."""
    h, w = size
    ones = np.ones((h, w), np.float32)
    inside = cv2.warpAffine(ones, m, (w, h), flags=cv2.INTER_NEAREST) > 0
    return cv2.erode(inside.astype(np.uint8), np.ones((2 * erode + 1,) * 2, np.uint8)) > 0


def _ncc_best_shift(a, b, valid, r):
    h, w = a.shape
    scores = {}
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            v = valid[r : h - r, r : w - r]
            x = a[r : h - r, r : w - r][v]
            y = b[r + dy : h - r + dy, r + dx : w - r + dx][v]
            scores[(dx, dy)] = np.corrcoef(x, y)[0, 1]
    return max(scores, key=scores.get)


# ----------------------------------------------------------------------------- scene


@pytest.fixture(scope="module")
def scene():
    return generate_scene(5, (384, 512))


def test_generate_scene_shapes_and_determinism(scene):
    expected = {
        "lidar": ((384, 512), np.uint8),
        "stereo": ((384, 512), np.uint8),
        "drone": ((384, 512, 3), np.uint8),
        "satellite": ((384, 512, 3), np.uint8),
        "lidar_mask": ((384, 512), np.uint8),
        "stereo_mask": ((384, 512), np.uint8),
    }
    assert set(scene) == set(expected)
    for key, (shape, dtype) in expected.items():
        assert scene[key].shape == shape and scene[key].dtype == dtype, key
    again = generate_scene(5, (384, 512))
    for key in expected:
        np.testing.assert_array_equal(scene[key], again[key], err_msg=key)
    other = generate_scene(6, (384, 512))
    assert not np.array_equal(scene["drone"], other["drone"])
    for m in ("lidar", "stereo"):
        mask = scene[f"{m}_mask"]
        assert set(np.unique(mask)) <= {0, 255}
        assert 0.1 < (mask > 0).mean() <= 1.0
        assert (scene[m][mask == 0] == 0).all(), f"{m} has data outside its mask"
    # The LiDAR map is sparse/speckled inside its mask, the stereo one is dense.
    lidar_fill = (scene["lidar"][scene["lidar_mask"] > 0] > 0).mean()
    assert 0.3 < lidar_fill < 0.95
    assert (scene["stereo"][scene["stereo_mask"] > 0] > 0).all()


def test_modalities_differ_but_are_coregistered(scene):
    drone_grey = cv2.cvtColor(scene["drone"], cv2.COLOR_RGB2GRAY).astype(np.float32)
    sat_grey = cv2.cvtColor(scene["satellite"], cv2.COLOR_RGB2GRAY).astype(np.float32)
    lidar = scene["lidar"].astype(np.float32)
    lm = scene["lidar_mask"] > 0
    # Genuinely different appearance.
    assert abs(np.corrcoef(lidar[lm], drone_grey[lm])[0, 1]) < 0.6
    sm = scene["stereo_mask"] > 0
    assert abs(np.corrcoef(scene["stereo"][sm].astype(float), drone_grey[sm])[0, 1]) < 0.6
    assert np.abs(drone_grey - sat_grey).mean() > 10
    # The satellite is blurrier (lower resolution) than the drone image.
    lap = [cv2.Laplacian(g, cv2.CV_32F).var() for g in (drone_grey, sat_grey)]
    assert lap[1] < 0.3 * lap[0]

    # Co-registered: lane marks (bright in LiDAR and drone) line up best at zero shift.
    bright_l = cv2.GaussianBlur((lidar > 200).astype(np.float32), (0, 0), 1.0)
    bright_d = cv2.GaussianBlur((drone_grey > 200).astype(np.float32), (0, 0), 1.0)
    assert _ncc_best_shift(bright_l, bright_d, lm, 6) == (0, 0)

    def grad(g):
        g = cv2.GaussianBlur(g, (0, 0), 1.5)
        return cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))

    assert _ncc_best_shift(grad(sat_grey), grad(drone_grey), np.ones_like(lm), 6) == (0, 0)

    # Stereo high regions (> 3 m: trees, walls) sit on the drone's tree canopies, and much
    # less so when the stereo map is displaced by 40 px.
    d = scene["drone"].astype(np.float32)
    canopy = (d[..., 1] > 1.9 * d[..., 0]) & (d[..., 1] > 1.9 * d[..., 2])
    high = scene["stereo"] > 20 + 3 * (235 / 25)
    valid = cv2.erode(scene["stereo_mask"], np.ones((5, 5), np.uint8)) > 0

    def enrichment(hi, ok):
        return canopy[ok & hi].mean() / max(canopy[ok & ~hi].mean(), 1e-3)

    aligned = enrichment(high, valid)
    shifted = enrichment(np.roll(high, 40, axis=1), np.roll(valid, 40, axis=1))
    assert aligned > 5 and aligned > 2 * shifted


def test_make_dataset_layout_and_default_reading(tmp_path):
    root = make_dataset(tmp_path / "ds", n_scenes=1, seed=3)
    assert (root / "README.txt").is_file()
    assert "regions.json" in (root / "README.txt").read_text()
    folder = root / "scene_a"
    for name in (
        "lidar.png",
        "stereo.png",
        "drone.png",
        "satellite.png",
        "lidar_mask.png",
        "stereo_mask.png",
        "regions.json",
    ):
        assert (folder / name).is_file(), name
    regions = json.loads((folder / "regions.json").read_text())
    assert {"train", "val"} <= set(regions)
    (x0, _, x1, _), (v0, _, v1, _) = regions["train"][0], regions["val"][0]
    assert x0 == 0 and v0 - x1 == 630 and v1 == 2560  # the gap keeps train and val crops apart
    assert cv2.imread(str(folder / "drone.png")).shape == (1280, 2560, 3)
    # Default settings work on both splits of the default-size stand-in, for every pair.
    for split in ("train", "val"):
        for pair in PAIRS:
            ds = MapPairs(root, pair, split, length=3, channels=3)
            item = ds[2]
            assert item["template"].shape == item["source"].shape == (3, 256, 256)
            assert item["template_mask"].shape == (1, 256, 256)
            assert item["pose"].shape == (4,) and item["pose"].dtype == torch.float32
            for k in ("template", "source", "template_mask"):
                t = item[k]
                assert t.dtype == torch.float32 and 0 <= t.min() and t.max() <= 1, k


def test_write_scene_round_trip_and_names(tmp_path):
    small = generate_scene(1, (96, 128))
    folder = write_scene(tmp_path, "x", small, {"train": [[0, 0, 64, 96]]})
    np.testing.assert_array_equal(cv2.imread(str(folder / "lidar.png"), 0), small["lidar"])
    rgb = cv2.cvtColor(cv2.imread(str(folder / "drone.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(rgb, small["drone"])
    assert json.loads((folder / "regions.json").read_text()) == {"train": [[0, 0, 64, 96]]}
    root = make_dataset(tmp_path / "three", n_scenes=3, size=(96, 128), gap=0)
    with pytest.raises(ValueError, match="split gap"):
        make_dataset(tmp_path / "narrow", size=(96, 128))
    assert sorted(p.name for p in root.iterdir() if p.is_dir()) == [
        "scene_a",
        "scene_b",
        "scene_c",
    ]


# ----------------------------------------------------------------------------- MapPairs


@pytest.fixture()
def same_modality_root(tmp_path):
    """One scene whose lidar and drone rasters are the same grey image."""
    tex = _texture(0, 460, 540)
    _imwrite(tmp_path / "s1" / "lidar.png", tex)
    _imwrite(tmp_path / "s1" / "drone.png", tex)
    return tmp_path


@pytest.mark.parametrize(
    "rotation, scale",
    [
        ((179.0, 180.0), (0.8, 0.8)),
        ((-180.0, -179.0), (1.2, 1.2)),
        ((88.0, 92.0), (1.0, 1.0)),
        ((-180.0, 180.0), (0.8, 1.2)),
    ],
)
def test_exact_geometry(same_modality_root, rotation, scale):
    size = (112, 144)  # (H, W), not square on purpose
    ds = MapPairs(
        same_modality_root,
        "l2d",
        length=4,
        size=size,
        translation=20.0,
        rotation=rotation,
        scale=scale,
        seed=1,
    )
    for i in range(len(ds)):
        item = ds[i]
        tx, ty, angle, sc = item["pose"].tolist()
        assert abs(tx) <= 20 and abs(ty) <= 20
        assert scale[0] - 1e-6 <= sc <= scale[1] + 1e-6
        if rotation[0] > 170:
            assert angle >= 179 - 1e-4
        elif rotation[1] < -170:
            assert angle <= -179 + 1e-4 or angle >= 180 - 1e-4
        template = item["template"][0].numpy()
        source = item["source"][0].numpy()
        assert template.shape == source.shape == size
        assert source.min() > 0, "source has an artificial empty border"
        m = _matrix(item["pose"], size)
        inside = _interior(m, size)
        assert inside.mean() > 0.3
        warped = cv2.warpAffine(template, m, (size[1], size[0]), flags=cv2.INTER_LINEAR)
        assert np.abs(warped - source)[inside].mean() < 0.02
        # The check can fail: 10 degrees off is far off.
        wrong = cv2.warpAffine(template, _matrix([tx, ty, angle + 10, sc], size), size[::-1])
        assert np.abs(wrong - source)[inside].mean() > 0.05


def test_split_regions_respected(tmp_path):
    h, w = 500, 900
    yy, xx = np.mgrid[0:h, 0:w]
    coords = np.stack([np.zeros_like(xx), yy * 32, xx * 32], axis=-1).astype(np.uint16)  # BGR
    folder = tmp_path / "grid"
    _imwrite(folder / "lidar.png", coords)
    _imwrite(folder / "satellite.png", _texture(1, h, w))
    regions = {
        "train": [[0, 0, 450, 500]],
        "val": [[450, 0, 900, 250]],
        "test": [[450, 250, 900, 500], [600, 0, 700, 100]],
    }
    (folder / "regions.json").write_text(json.dumps(regions))
    for split, rects in regions.items():
        ds = MapPairs(
            tmp_path,
            "l2sat",
            split,
            length=40,
            size=64,
            translation=10.0,
            scale=(0.9, 1.1),
            channels=3,
            seed=2,
        )
        xs = []
        for i in range(len(ds)):
            rgb = ds[i]["template"][:, 32, 32].double() * 65535 / 32
            cx, cy = round(float(rgb[0])), round(float(rgb[1]))
            assert any(x0 <= cx < x1 and y0 <= cy < y1 for x0, y0, x1, y1 in rects), (split, cx, cy)
            assert 32 <= cx <= w - 32 and 32 <= cy <= h - 32
            xs.append(cx)
        assert max(xs) - min(xs) > 100  # spread over the region, not stuck


def test_determinism_and_epochs(same_modality_root):
    def make(seed=0):
        return MapPairs(same_modality_root, "l2d", length=6, size=64, seed=seed)

    a, b = make(), make()
    first = [a[i] for i in range(6)]
    for i in reversed(range(6)):
        for k in first[i]:
            assert torch.equal(first[i][k], b[i][k])
    a.set_epoch(1)
    assert not torch.equal(a[0]["pose"], first[0]["pose"])
    a.set_epoch(0)
    assert torch.equal(a[0]["template"], first[0]["template"])
    assert not torch.equal(make(seed=1)[0]["pose"], first[0]["pose"])
    assert len(a) == 6
    with pytest.raises(IndexError):
        a[6]


def test_channels_and_rgb_order(tmp_path):
    red = np.zeros((300, 300, 3), np.uint8)
    red[..., 2] = 200  # BGR: red
    _imwrite(tmp_path / "s" / "stereo.png", _texture(2, 300, 300))
    _imwrite(tmp_path / "s" / "drone.png", red)
    kw = dict(length=1, size=32, translation=5.0, rotation=(0.0, 0.0), scale=(1.0, 1.0))
    item = MapPairs(tmp_path, "s2d", channels=3, **kw)[0]
    src = item["source"]
    assert src.shape == (3, 32, 32)
    assert torch.allclose(src[0], torch.full_like(src[0], 200 / 255), atol=1e-3)
    assert src[1:].abs().max() < 1e-6
    t = item["template"]
    assert torch.equal(t[0], t[1]) and torch.equal(t[1], t[2])
    grey = MapPairs(tmp_path, "s2d", channels=1, **kw)[0]
    assert grey["source"].shape == (1, 32, 32)
    assert abs(float(grey["source"].mean()) - 0.299 * 200 / 255) < 0.01


def test_low_valid_fraction_warns_once_and_sampling_meets_min_valid(tmp_path):
    tex = _texture(3, 400, 600)
    mask = np.zeros((400, 600), np.uint8)
    mask[:20, :20] = 255
    _imwrite(tmp_path / "scene_q" / "lidar.png", tex)
    _imwrite(tmp_path / "scene_q" / "satellite.png", tex)
    _imwrite(tmp_path / "scene_q" / "lidar_mask.png", mask)
    ds = MapPairs(tmp_path, "l2sat", length=5, size=64, translation=10.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        items = [ds[i] for i in range(5)]
    msgs = [str(w.message) for w in caught]
    assert len(msgs) == 1 and "scene_q" in msgs[0] and "min_valid" in msgs[0], msgs
    # None qualifies: the most observed crop that the pose's footprint allows.
    fractions = [float(it["template_mask"].mean()) for it in items]
    assert max(fractions) < 0.3 and max(fractions) > 0.0

    # Left half valid: every crop satisfies min_valid.
    mask[:] = 0
    mask[:, :300] = 255
    _imwrite(tmp_path / "scene_q" / "lidar_mask.png", mask)
    ds = MapPairs(tmp_path, "l2sat", length=10, size=64, translation=10.0, min_valid=0.95, seed=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fractions = [float(ds[i]["template_mask"].mean()) for i in range(10)]
    assert min(fractions) >= 0.95

    # An alpha channel works as the mask too.
    rgba = np.dstack([tex, tex, tex, mask])
    _imwrite(tmp_path / "alpha" / "lidar.png", rgba)
    _imwrite(tmp_path / "alpha" / "drone.png", tex)
    ds = MapPairs(tmp_path, "l2d", scenes=["alpha"], length=10, size=64, translation=10.0, min_valid=0.0, seed=5)
    fr = [float(ds[i]["template_mask"].mean()) for i in range(10)]
    assert min(fr) < 1.0 and max(fr) > 0.0

    # One small observed patch: about 0.2 % of the offsets qualify (random redraws would
    # almost never find one); the sampler finds them, and spreads over them.
    mask[:] = 0
    mask[150:230, 250:330] = 255
    _imwrite(tmp_path / "scene_q" / "lidar_mask.png", mask)
    ds = MapPairs(tmp_path, "l2sat", scenes=["scene_q"], length=20, size=64, translation=10.0, min_valid=0.9, seed=6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        items = [ds[i] for i in range(20)]
    assert min(float(it["template_mask"].mean()) for it in items) >= 0.9
    assert len({it["template"].numpy().tobytes() for it in items}) > 10


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("marking", ["alpha", "mask_file", "nan"])
def test_no_data_reads_as_zero_whatever_the_raster_holds_there(tmp_path, marking):
    """Unobserved template pixels reach the model as 0, the built-in maps' coding, whether an
    alpha channel, a mask file or NaN marks them and whatever values lie under them; the
    source's own no-data too. Two scenes that differ only there give the same pairs."""
    h, w = 200, 240
    tex = _texture(1, h, w)
    observed = np.zeros((h, w), bool)
    observed[:, :120] = True  # the left half: the crops near the middle straddle its edge
    junk = _texture(2, h, w) // 2 + 128  # bright values under the no-data
    clean = np.where(observed, tex, 0).astype(np.uint8)
    source = _texture(3, h, w)
    src_alpha = np.full((h, w), 255, np.uint8)
    src_alpha[95:105] = 0  # the source's own no-data, a band through the middle: an alpha channel
    _imwrite(tmp_path / "clean" / "sc" / "lidar.png", clean)
    _imwrite(tmp_path / "clean" / "sc" / "lidar_mask.png", observed.astype(np.uint8) * 255)
    _imwrite(tmp_path / "clean" / "sc" / "drone.png", np.where(src_alpha > 0, source, 0).astype(np.uint8))
    messy = tmp_path / "messy" / "sc"
    under = np.where(observed, tex, junk).astype(np.uint8)
    if marking == "alpha":
        _imwrite(messy / "lidar.png", np.dstack([under, under, under, observed.astype(np.uint8) * 255]))
    elif marking == "mask_file":
        _imwrite(messy / "lidar.png", under)
        _imwrite(messy / "lidar_mask.png", observed.astype(np.uint8) * 255)
    else:  # a float raster: NaN is no data; values already in [0, 1] keep their scale
        _imwrite(messy / "lidar.tif", np.where(observed, tex / 255.0, np.nan).astype(np.float32))
    _imwrite(messy / "drone.png", np.dstack([source, source, source, src_alpha]))
    kw = dict(length=6, size=64, translation=10.0, min_valid=0.0, seed=9)
    a, b = MapPairs(tmp_path / "clean", "l2d", **kw), MapPairs(tmp_path / "messy", "l2d", **kw)
    coverage = []
    for i in range(6):
        x, y = a[i], b[i]
        torch.testing.assert_close(y["template_mask"], x["template_mask"])
        torch.testing.assert_close(y["template"], x["template"], atol=1e-6, rtol=0)
        torch.testing.assert_close(y["source"], x["source"], atol=1e-6, rtol=0)
        coverage.append(float(x["template_mask"].mean()))
    assert min(coverage) < 0.9  # the comparison covered crops that reach the no-data
    assert (y["template"][:, y["template_mask"][0] == 0] == 0).all()


def _scene(root: Path, name="sc", size=(200, 240), mods=("lidar", "satellite")):
    folder = root / name
    for mod in mods:
        _imwrite(folder / f"{mod}.png", _texture(0, *size))
    return folder


def test_map_pairs_errors(tmp_path):
    kw = dict(size=64, translation=5.0, rotation=(-10.0, 10.0), scale=(1.0, 1.0))
    with pytest.raises(DataError, match="does not exist"):
        MapPairs(tmp_path / "missing", **kw)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no scene folders"):
        MapPairs(tmp_path / "empty", **kw)
    with pytest.raises(DataError, match=r"unknown pair 'x2y'.*l2d.*l2sat.*s2d.*s2sat"):
        MapPairs(tmp_path, "x2y", **kw)

    r = tmp_path / "r1"
    _scene(r, "alpha", mods=("lidar",))
    with pytest.raises(DataError, match=r"'alpha'.*satellite.*satellite\.png.*satellite\.tif"):
        MapPairs(r, "l2sat", **kw)

    r = tmp_path / "r2"
    _imwrite(r / "sc" / "lidar.png", _texture(0, 100, 120))
    _imwrite(r / "sc" / "satellite.png", _texture(0, 100, 130))
    with pytest.raises(DataError, match=r"lidar\.png is 120x100.*satellite\.png is 130x100"):
        MapPairs(r, **kw)

    r = tmp_path / "r3"
    folder = _scene(r)
    (folder / "regions.json").write_text(json.dumps({"train": [[0, 0, 500, 100]]}))
    with pytest.raises(DataError, match=r"regions\.json.*outside"):
        MapPairs(r, **kw)
    (folder / "regions.json").write_text(json.dumps({"train": [[0, 0, 20, 20]]}))
    with pytest.raises(DataError, match=r"'sc'.*too small"):
        MapPairs(r, **kw)
    (folder / "regions.json").write_text(json.dumps({"train": [[0, 0, 240, 200]]}))
    with pytest.raises(DataError, match="too small"):  # whole raster, but crop + footprint
        MapPairs(r, size=160, rotation=(-180.0, 180.0))
    with pytest.raises(DataError, match=r"split 'val'.*train"):
        MapPairs(r, split="val", **kw)
    (folder / "regions.json").write_text("{not json")
    with pytest.raises(DataError, match="cannot parse"):
        MapPairs(r, **kw)
    (folder / "regions.json").unlink()
    assert len(MapPairs(r, split="test", length=2, **kw)) == 2  # no file: one region
    with pytest.raises(DataError, match="unknown scene"):
        MapPairs(r, scenes=["nope"], **kw)
    with pytest.raises(DataError, match=r"unknown scene\(s\) \['nope'\] in exclude_scenes \(data.test_scenes"):
        MapPairs(r, exclude_scenes=["nope"], **kw)
    with pytest.raises(DataError, match="no scene left for split 'test'.*excluded"):
        MapPairs(r, split="test", exclude_scenes=["sc"], **kw)

    r = tmp_path / "r4"
    folder = _scene(r)
    (folder / "satellite.png").write_bytes(b"this is not a png")
    with pytest.raises(DataError, match=r"satellite\.png"):
        MapPairs(r, **kw)

    r = tmp_path / "r5"
    folder = _scene(r)
    _imwrite(folder / "lidar_mask.png", np.zeros((10, 10), np.uint8))
    with pytest.raises(DataError, match=r"lidar_mask\.png"):
        MapPairs(r, **kw)


# ----------------------------------------------------------------------------- CsvPairs


def _write_csv_pairs(root: Path, poses, size=(96, 96), header="name, rotation, shift_x, shift_y, scale"):
    h, w = size
    rows = [header]
    for i, (tx, ty, angle, sc) in enumerate(poses):
        tex = _texture(10 + i, h, w, blur=3.0)
        src = cv2.warpAffine(tex, _matrix([tx, ty, angle, sc], size), (w, h))
        _imwrite(root / "template" / f"p{i}.png", tex)
        _imwrite(root / "source" / f"p{i}.png", src)
        values = [f"p{i}", angle, tx, ty] + ([sc] if "scale" in header else [])
        rows.append(", ".join(str(v) for v in values))
    (root / "pairs.csv").write_text("\n".join(rows) + "\n")
    return root / "pairs.csv"


def test_csv_pairs_round_trip(tmp_path):
    poses = [(3.5, -7.0, 170.0, 1.1), (-12.0, 4.25, -45.0, 0.85), (0.0, 0.0, 179.5, 1.0)]
    csv_path = _write_csv_pairs(tmp_path, poses)
    ds = CsvPairs(csv_path)
    assert len(ds) == 3
    for i, pose in enumerate(poses):
        item = ds[i]
        np.testing.assert_allclose(item["pose"].numpy(), pose, atol=1e-5)
        tex = cv2.imread(str(tmp_path / "template" / f"p{i}.png"), 0) / 255.0
        np.testing.assert_allclose(item["template"][0].numpy(), tex, atol=1e-6)
        assert item["template_mask"].shape == (1, 96, 96) and item["template_mask"].min() == 1
        m = _matrix(item["pose"], (96, 96))
        warped = cv2.warpAffine(item["template"][0].numpy(), m, (96, 96))
        inside = _interior(m, (96, 96))
        assert np.abs(warped - item["source"][0].numpy())[inside].mean() < 0.01

    # Resized on reading: the rescaled pose stays exact for the resized images.
    small = CsvPairs(csv_path, size=48, channels=3)
    for i in range(3):
        item = small[i]
        assert item["template"].shape == item["source"].shape == (3, 48, 48)
        tx, ty, angle, sc = item["pose"].tolist()
        assert (angle, sc) == pytest.approx(poses[i][2:], abs=1e-5)
        assert (tx, ty) == pytest.approx((poses[i][0] / 2, poses[i][1] / 2), abs=0.6)
        m = _matrix(item["pose"], (48, 48))
        warped = cv2.warpAffine(item["template"][0].numpy(), m, (48, 48))
        inside = _interior(m, (48, 48), erode=2)
        assert np.abs(warped - item["source"][0].numpy())[inside].mean() < 0.02

    # Without a scale column, scale is 1; explicit folders override the defaults.
    other = tmp_path / "noscale"
    csv2 = _write_csv_pairs(other, [(1.0, 2.0, 30.0, 1.0)], header="name,rotation,shift_x,shift_y")
    moved = tmp_path / "moved"
    (other / "template").rename(moved)
    item = CsvPairs(csv2, template_dir=moved)[0]
    np.testing.assert_allclose(item["pose"].numpy(), [1.0, 2.0, 30.0, 1.0], atol=1e-6)


def test_csv_pairs_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        CsvPairs(tmp_path / "none.csv")
    csv_path = _write_csv_pairs(tmp_path, [(1.0, 2.0, 3.0, 1.0), (0.0, 0.0, 10.0, 1.0)])
    good = csv_path.read_text().splitlines()

    csv_path.write_text("name, rotation, shift_x\np0, 1, 2\n")
    with pytest.raises(DataError, match=r"pairs\.csv.*missing column.*shift_y"):
        CsvPairs(csv_path)

    csv_path.write_text("\n".join([good[0], good[1], "p1, abc, 0, 0, 1"]) + "\n")
    with pytest.raises(DataError, match=r"row 2 .*rotation = 'abc' is not a number"):
        CsvPairs(csv_path)

    csv_path.write_text("\n".join([good[0], good[1], good[2], "ghost, 0, 0, 0, 1"]) + "\n")
    with pytest.raises(DataError, match=r"row 3 .*'ghost' not found"):
        CsvPairs(csv_path)

    csv_path.write_text("\n".join([good[0], "p0, 1, 2"]) + "\n")
    with pytest.raises(DataError, match="row 1"):
        CsvPairs(csv_path)

    csv_path.write_text(good[0] + "\n")
    with pytest.raises(DataError, match="no data rows"):
        CsvPairs(csv_path)

    csv_path.write_text("\n".join(good) + "\n")
    (tmp_path / "source" / "p1.png").write_bytes(b"garbage")
    ds = CsvPairs(csv_path)
    ds[0]
    with pytest.raises(DataError, match=r"p1\.png"):
        ds[1]
