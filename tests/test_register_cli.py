"""dpcn.register and `python -m dpcn predict`: inputs of every kind, and bad ones."""

import csv
import io
import json
import os
import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest
import torch

import dpcn
from dpcn.io import DpcnInputError, load_image, prepare_pair, read_image, to_image_tensor

from .conftest import CONF, angle_error, cv2_warp, photo

TRUTH = (11.0, -23.5, 141.0, 0.93)


@pytest.fixture(scope="module")
def pair():
    template = photo("astronaut")
    return template, cv2_warp(template, *TRUTH)


def check(pose, truth=TRUTH):
    assert float(pose.tx[0]) == pytest.approx(truth[0], abs=0.5)
    assert float(pose.ty[0]) == pytest.approx(truth[1], abs=0.5)
    assert angle_error(pose.angle[0], truth[2]) < 0.3
    assert float(pose.scale[0]) == pytest.approx(truth[3], rel=0.006)


def test_register_numpy_float_and_uint8(pair):
    template, source = pair
    check(dpcn.register(template, source))
    check(dpcn.register((template * 255).astype(np.uint8), (source * 255).astype(np.uint8)))


def test_register_colour_and_mixed_channels():
    template = photo("coffee", colour=True)
    source = cv2_warp(template, *TRUTH)
    check(dpcn.register(template, source))
    grey_source = cv2.cvtColor(source, cv2.COLOR_RGB2GRAY)
    check(dpcn.register(template, grey_source))


def test_register_torch_batch(pair):
    template, source = pair
    t = torch.from_numpy(np.stack([template, template]))[:, None]
    s = torch.from_numpy(np.stack([source, cv2_warp(template, 0.0, 0.0, -60.0, 1.1)]))[:, None]
    pose = dpcn.register(t, s)
    assert len(pose) == 2
    check(pose[0])
    check(pose[1], (0.0, 0.0, -60.0, 1.1))


def test_one_template_image_against_a_batch_of_sources(pair):
    template, source = pair
    sources = torch.from_numpy(np.stack([source, cv2_warp(template, 0.0, 0.0, -60.0, 1.1)]))[:, None].double()
    uint8 = (template * 255).astype(np.uint8)
    t, s = prepare_pair(uint8, sources)
    # converted to the sources' dtype, then expanded: still one image (DPCN runs its U-Nets once)
    assert t.shape == (2, 1, *template.shape) and t.dtype == torch.float64 and t.stride(0) == 0
    pose = dpcn.register(uint8, sources)
    check(pose[0])
    check(pose[1], (0.0, 0.0, -60.0, 1.1))


def test_register_paths(tmp_path, pair):
    template, source = pair
    cv2.imwrite(str(tmp_path / "t.png"), (template * 255).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "s.tif"), (source * 65535).astype(np.uint16))
    check(dpcn.register(str(tmp_path / "t.png"), str(tmp_path / "s.tif")))
    assert load_image(tmp_path / "s.tif").max() <= 1.0


def test_files_read_as_the_map_data_reads_them(tmp_path, pair):
    """``load_image`` (what ``predict`` and ``register(path, ...)`` read) follows the map-pair
    data sets' rules, so a crop matched at inference looks like a crop trained on: no data
    (alpha 0, NaN) reads as 0 whatever lies under it, and a float raster in metres is
    min-max normalised over its finite pixels."""
    template, _ = pair
    grey = (template * 255).astype(np.uint8)
    hidden = np.zeros(grey.shape, bool)
    hidden[:20] = True
    under = np.where(hidden, 255, grey).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "rgba.png"), np.dstack([under, under, under, np.where(hidden, 0, 255).astype(np.uint8)]))
    image, valid = read_image(tmp_path / "rgba.png")
    np.testing.assert_array_equal(valid, ~hidden)
    np.testing.assert_array_equal(image[..., 0], np.where(hidden, 0, grey))
    loaded = load_image(tmp_path / "rgba.png")
    assert loaded.shape == (*grey.shape, 3) and loaded[hidden].max() == 0.0
    np.testing.assert_allclose(loaded[~hidden][:, 1], grey[~hidden] / 255.0, atol=1e-6)
    # The same RGBA as an array: the alpha's zeros read as 0 too.
    array = np.dstack([under, under, under, np.where(hidden, 0, 255).astype(np.uint8)])
    np.testing.assert_allclose(to_image_tensor(array)[0].permute(1, 2, 0).numpy(), loaded, atol=1e-6)

    metres = (12.5 + 30.0 * template).astype(np.float32)
    metres[hidden] = np.nan
    assert cv2.imwrite(str(tmp_path / "dem.tif"), metres)
    loaded = load_image(tmp_path / "dem.tif")
    assert np.isfinite(loaded).all() and loaded.min() == 0.0 and loaded.max() == pytest.approx(1.0)
    assert loaded[hidden].max() == 0.0
    finite = metres[~hidden]
    np.testing.assert_allclose(loaded[~hidden], (finite - finite.min()) / (finite.max() - finite.min()), atol=1e-6)


@pytest.mark.parametrize(
    "template,source,message",
    [
        (np.zeros((64, 64)), np.zeros((64, 65)), "same size"),
        (np.zeros((1, 1)), np.zeros((1, 1)), "at least 8x8"),
        (np.zeros((0, 64)), np.zeros((0, 64)), "empty"),
        (np.full((32, 32), np.nan), np.zeros((32, 32)), "NaN"),
        (np.zeros((32, 32)), np.full((32, 32), np.inf), "NaN or infinite"),
        (np.zeros((32, 32, 5)), np.zeros((32, 32, 5)), r"\(H, W, C\)"),
        (np.zeros((32, 32), dtype=np.complex64), np.zeros((32, 32)), "unsupported dtype"),
        ("no/such/file.png", np.zeros((32, 32)), "not found"),
        ([[1, 2], [3, 4]], np.zeros((32, 32)), "expected a numpy array"),
        (torch.zeros(2, 1, 32, 32), torch.zeros(3, 1, 32, 32), "batch"),
        (torch.zeros(1, 1, 1, 32, 32), torch.zeros(1, 1, 32, 32), r"\(B, C, H, W\)"),
    ],
)
def test_register_bad_inputs(template, source, message):
    with pytest.raises(DpcnInputError, match=message):
        dpcn.register(template, source)


def test_corrupt_image_file(tmp_path):
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    with pytest.raises(DpcnInputError, match="cannot read"):
        load_image(bad)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(DpcnInputError, match=r"cannot read image file \(unsupported or corrupt\): .*empty.png"):
        load_image(tmp_path / "empty.png")
    with pytest.raises(DpcnInputError, match="not a file: "):
        dpcn.register(tmp_path, tmp_path)


def test_integer_and_bool_tensors_read_as_their_full_range(pair):
    template, source = pair
    as_float = dpcn.register(template, source).as_tensor()
    t8, s8 = (torch.from_numpy(np.round(x * 255).astype(np.uint8)) for x in (template, source))
    as_uint8 = dpcn.register(t8, s8).as_tensor()
    torch.testing.assert_close(as_uint8, dpcn.register(t8.float() / 255, s8.float() / 255).as_tensor())
    torch.testing.assert_close(as_uint8, as_float, atol=0.05, rtol=0.01)  # 8-bit rounding of the images
    masks = torch.from_numpy(template > 0.5), torch.from_numpy(source > 0.5)
    torch.testing.assert_close(
        dpcn.register(*masks).as_tensor(), dpcn.register(*(m.float() for m in masks)).as_tensor()
    )
    with pytest.raises(DpcnInputError, match="complex tensors are not images"):
        dpcn.register(torch.zeros(32, 32, dtype=torch.complex64), torch.zeros(32, 32))


@pytest.mark.parametrize("dtype", [np.int16, np.int32, np.int64])
def test_signed_and_wide_integer_images_read_as_values(pair, dtype):
    # `.astype(int)` of an 8-bit image: its 0-255 values, not a sliver of the int64 range,
    # which would round every pixel to one float32 and match nothing
    template, source = (np.round(x * 255).astype(dtype) for x in pair)
    check(dpcn.register(template, source))
    check(dpcn.register(torch.from_numpy(template), torch.from_numpy(source)))
    as_values = to_image_tensor(template)
    expected = (template - template.min()) / float(template.max() - template.min())
    torch.testing.assert_close(as_values[0, 0], torch.from_numpy(expected.astype(np.float32)))
    batch = torch.from_numpy(np.stack([template, template // 2]))[:, None]  # each image its own range
    torch.testing.assert_close(to_image_tensor(batch)[1], to_image_tensor(batch)[0], atol=0.01, rtol=0)
    ones = np.ones((16, 16), dtype=dtype)  # already within [0, 1]: kept
    assert to_image_tensor(ones).unique().tolist() == [1.0]


def test_register_on_a_device_this_machine_lacks(pair):
    with pytest.raises(ValueError, match="device=cuda:99 requested but"):  # not torch's assertion
        dpcn.register(*pair, device="cuda:99")


def test_constant_pairs_get_confidence_zero_and_a_warning(pair):
    template, source = (torch.from_numpy(x)[None, None] for x in pair)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a pair with structure gives no warning
        alone = dpcn.register(template, source)
    t, s = template.repeat(3, 1, 1, 1), source.repeat(3, 1, 1, 1)
    t[1], s[2] = 0.0, 0.25
    with pytest.warns(UserWarning, match=r"2 of 3 pair\(s\) have a constant template or source") as caught:
        pose = dpcn.register(t, s)
    assert caught[0].filename == __file__
    assert pose.confidence[1:].tolist() == [0.0, 0.0]
    check(pose[0])
    assert float(pose.confidence[0]) == float(alone.confidence[0]) > 0.5


def test_cli_predict_of_a_blank_image_says_so(tmp_path, pair):
    cv2.imwrite(str(tmp_path / "t.png"), np.zeros((64, 64), np.uint8))
    cv2.imwrite(str(tmp_path / "s.png"), (pair[1][:64, :64] * 255).astype(np.uint8))
    out = run_cli("predict", "template=t.png", "source=s.png", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["confidence"] == 0.0
    assert "1 of 1 pair(s) have a constant template or source" in out.stderr


def run_cli(*args, cwd):
    env = {k: v for k, v in os.environ.items() if k != "DPCN_DEBUG"}
    return subprocess.run([sys.executable, "-m", "dpcn", *args], capture_output=True, text=True, cwd=cwd, env=env)


def test_cli_predict_prints_json(tmp_path, pair):
    template, source = pair
    cv2.imwrite(str(tmp_path / "t.png"), (template * 255).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "s.png"), (source * 255).astype(np.uint8))
    out = run_cli("predict", "template=t.png", "source=s.png", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert set(result) == {"tx", "ty", "angle", "scale", "confidence"}
    check(dpcn.Pose.from_dict(result))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.png", "t.png"]  # a query leaves no run directory


def test_cli_predict_writes_one_pose_to_out(tmp_path, pair):
    template, source = pair
    cv2.imwrite(str(tmp_path / "t.png"), (template * 255).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "s.png"), (source * 255).astype(np.uint8))
    out = run_cli("predict", "template=t.png", "source=s.png", "out=pose.json", cwd=tmp_path)
    assert out.returncode == 0 and out.stdout == "", out.stderr  # out= was ignored before: the JSON went to stdout
    assert "pose written to pose.json" in out.stderr
    check(dpcn.Pose.from_dict(json.loads((tmp_path / "pose.json").read_text())))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pose.json", "s.png", "t.png"]  # no partial file left
    missing = run_cli("predict", "template=t.png", "source=s.png", "out=nowhere/pose.json", cwd=tmp_path)
    assert missing.returncode == 2 and "out=nowhere/pose.json: folder nowhere does not exist" in missing.stderr


@pytest.mark.parametrize(
    "args,message",
    [
        (["source=s.png"], "needs template=PATH and source=PATH"),
        (["template=t.png", "source=missing.png"], "not found: missing.png"),
        (["template=t.png", "source=small.png"], "same size"),
        (["template=t.png", "source=s.png", "registration.temperature=-1"], "temperature must be a finite number > 0"),
        (["template=t.png", "source=s.png", "registration.window=abc"], "window must be an integer >= 0, got 'abc'"),
        (["template=t.png", "source=s.png", "device=cuda:7"], "CUDA is not available"),
        (["template=t.png", "source=s.png", "device=bogus"], "device must be a device such as cpu, cuda or cuda:0"),
        (["template=t.png", "source=s.png", "device=hpu"], "device=hpu requested but this machine cannot use it"),
        # a checkpoint's inference settings do not reach the classical estimator: not silently ignored
        (["template=t.png", "source=s.png", "rotation_range=[0,180]"], "set registration.rotation_range= instead"),
        (["template=t.png", "source=s.png", "rotation_views=4"], "rotation_views= applies to a checkpoint"),
        (["template=t.png", "source=s.png", "inference_sigma=3"], "set registration.sigma= instead"),
        (["template=t.png", "source=s.png", "scale_range=[0.8,1.25]"], "set registration.scale_range= instead"),
    ],
)
def test_cli_predict_errors_are_one_line(tmp_path, pair, args, message):
    if "device=cuda:7" in args and torch.cuda.is_available():
        pytest.skip("a CUDA machine has a device to offer")
    template, source = pair
    cv2.imwrite(str(tmp_path / "t.png"), (template * 255).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "s.png"), (source * 255).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "small.png"), (template[:64] * 255).astype(np.uint8))
    out = run_cli("predict", *args, cwd=tmp_path)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], out.stderr
    assert "Traceback" not in out.stderr


PAIR_TRUTHS = {  # name: (photo, size, pose); "wide" has another size, so it is a batch of its own
    "astro": ("astronaut", (256, 256), TRUTH),
    "cam": ("camera", (256, 256), (-5.0, 8.0, -30.0, 1.1)),
    "wide": ("coffee", (192, 256), (4.0, -3.0, 75.0, 0.95)),
    "moon": ("moon", (256, 256), (0.0, 12.0, 170.0, 1.05)),
}


def write_pairs(root, header="name,note", missing=()):
    """Pre-cut pairs in the CSV layout, the pose left out of the CSV (unknown to predict)."""
    for folder in ("template", "source"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    lines = [header]
    for name, (image, size, pose) in PAIR_TRUTHS.items():
        template = photo(image, size)
        cv2.imwrite(str(root / "template" / f"{name}.png"), (template * 255).astype(np.uint8))
        if name not in missing:
            cv2.imwrite(str(root / "source" / f"{name}.png"), (cv2_warp(template, *pose) * 255).astype(np.uint8))
        lines.append(f"{name},x")
    (root / "pairs.csv").write_text("\n".join(lines) + "\n")
    return root / "pairs.csv"


def test_cli_predict_pairs_writes_every_pose_as_csv(tmp_path):
    """`predict pairs=CSV` matches every pair the CSV names, batched, in the CSV's order, with
    the poses a single-pair `predict` gives; `out=FILE` writes the same rows."""
    pairs = write_pairs(tmp_path)
    out = run_cli("predict", f"pairs={pairs}", "predict_batch_size=2", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    rows = list(csv.DictReader(io.StringIO(out.stdout)))
    assert [r["name"] for r in rows] == list(PAIR_TRUTHS)
    assert list(rows[0]) == ["name", "tx", "ty", "angle", "scale", "confidence"]
    for row in rows:
        check(dpcn.Pose.from_dict({k: float(v) for k, v in row.items() if k != "name"}), PAIR_TRUTHS[row["name"]][2])
    single = run_cli("predict", "template=template/cam.png", "source=source/cam.png", cwd=tmp_path)
    alone = json.loads(single.stdout)
    for key in ("tx", "ty", "angle", "scale", "confidence"):
        assert float(rows[1][key]) == pytest.approx(alone[key], rel=1e-4, abs=1e-4), key
    written = run_cli("predict", f"pairs={pairs}", "out=poses.csv", cwd=tmp_path)
    assert written.returncode == 0 and written.stdout == "", written.stderr
    assert (tmp_path / "poses.csv").read_text() == out.stdout
    assert "poses of 4 pairs written to poses.csv" in written.stderr


@pytest.mark.parametrize(
    "args,setup,message",
    [
        (["template=t.png"], None, "template=PATH and source=PATH, or pairs=CSV, not both"),
        (["predict_batch_size=0"], None, "predict_batch_size must be an integer >= 1, got 0"),
        (["out=no/such/dir/poses.csv"], None, "folder no/such/dir does not exist"),
        ([], "missing", "source image for 'cam' not found"),
        ([], "header", "missing column(s) ['name']"),
        ([], "sizes", "pair 'cam': template and source must have the same size"),
        ([], "tiny", "pair 'cam': template is 4x4 pixels; at least 8x8 is needed"),
    ],
)
def test_cli_predict_pairs_errors_are_one_line(tmp_path, args, setup, message):
    pairs = write_pairs(tmp_path, header="id,note" if setup == "header" else "name,note",
                        missing=("cam",) if setup == "missing" else ())  # fmt: skip
    if setup == "sizes":
        cv2.imwrite(str(tmp_path / "source" / "cam.png"), np.zeros((64, 64), np.uint8))
    if setup == "tiny":  # too small to match
        for folder in ("template", "source"):
            cv2.imwrite(str(tmp_path / folder / "cam.png"), np.full((4, 4), 9, np.uint8))
    out = run_cli("predict", f"pairs={pairs}", "out=poses.csv", *args, cwd=tmp_path)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], out.stderr
    assert not (tmp_path / "poses.csv").exists() and not list(tmp_path.glob(".poses*"))  # nothing half-written


def test_cli_unknown_key_and_command(tmp_path):
    out = run_cli("predict", "tempalte=t.png", cwd=tmp_path)
    assert out.returncode != 0 and "tempalte" in out.stderr and "Traceback" not in out.stderr
    out = run_cli("frobnicate", cwd=tmp_path)
    assert out.returncode == 2 and "unknown command 'frobnicate'" in out.stderr
    out = run_cli("--help", cwd=tmp_path)
    assert out.returncode == 0 and "predict" in out.stdout
    for args in (("fit", "--help"), ("test", "data=l2d", "-h")):  # was Hydra's dump of the whole config
        sub = run_cli(*args, cwd=tmp_path)
        assert sub.returncode == 0 and sub.stdout == out.stdout and "Powered by Hydra" not in sub.stdout


def test_cli_help_lists_every_config_of_each_group(tmp_path):
    """The usage's group options come from conf/, so a new data, model or experiment config is
    listed (the default first) and none that is gone."""
    out = run_cli("--help", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    listed = {}
    for token in out.stdout.replace("[", " ").replace("]", " ").split():
        group, _, options = token.partition("=")
        if group in ("data", "model", "loss", "trainer", "experiment") and "|" in options:
            listed.setdefault(group, options.split("|"))  # fit's line comes first
    for group in ("data", "model", "loss", "trainer", "experiment"):
        expected = {p.stem for p in (CONF / group).glob("*.yaml")} - {"classical"}
        assert sorted(listed[group]) == sorted(expected), group
    assert listed["data"][0] == "sim_heterogeneous" and listed["model"][0] == "tiny"
    assert "paper_table1" in listed["experiment"] and "tiny_full_s2d" in listed["model"]
