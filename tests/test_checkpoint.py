"""dpcn.load_model: a checkpoint's DPCN without Lightning, the same matcher load_matcher gives."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import dpcn
from dpcn.checkpoint import CheckpointError, load_model, set_inference_settings
from dpcn.training import load_matcher

from .conftest import cv2_warp, photo, write_checkpoint
from .test_checkpoint_damage import _damaged_copy, _foreign_copy

SMALL = ("image_size=64", "model.net.base_channels=4", "model.net.n_angles=64", "model.net.n_radii=64")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt", *SMALL, seed=3)


@pytest.fixture(scope="module")
def pairs():
    template = photo("camera", size=(64, 64))
    sources = [cv2_warp(template, 3.0, -2.0, angle, 1.05) for angle in (20.0, -135.0)]
    return template, sources


def test_load_model_is_load_matchers_model(checkpoint, pairs):
    model = load_model(checkpoint)
    reference = load_matcher(checkpoint).model
    assert isinstance(model, dpcn.models.DPCN) and not model.training
    assert model.state_dict().keys() == reference.state_dict().keys()
    for key, value in reference.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key
    for name in ("rotation_hypotheses", "hypothesis_ratio", "rotation_views", "inference_radii", "image_size"):
        assert getattr(model, name) == getattr(reference, name), name
    template, sources = pairs
    t = torch.from_numpy(template)[None, None].expand(2, -1, -1, -1)
    s = torch.from_numpy(np.stack(sources))[:, None]
    torch.testing.assert_close(model.match(t, s).as_tensor(), reference.match(t, s).as_tensor(), rtol=0, atol=0)


def test_model_match_reads_arrays_as_the_lightning_module_does(checkpoint, pairs):
    """DPCN.match takes what dpcn.register takes: arrays, or an array template against a batch."""
    model = load_model(checkpoint)
    template, sources = pairs
    t = torch.from_numpy(template)[None, None]
    s = torch.from_numpy(np.stack(sources))[:, None]
    one = model.match(t, s[1:]).as_tensor()
    torch.testing.assert_close(model.match(template, sources[1]).as_tensor(), one, rtol=0, atol=0)
    torch.testing.assert_close(load_matcher(checkpoint).match(template, sources[1]).as_tensor(), one, rtol=0, atol=0)
    batch = model.match(t, s).as_tensor()
    torch.testing.assert_close(model.match(template, s).as_tensor(), batch, rtol=0, atol=0)
    with pytest.raises(ValueError, match="same size"):
        model.match(template, template[:32])


def test_model_match_converts_images_to_the_models_channels(checkpoint, pairs):
    """Arrays and files reach a grey model as grey (colour converted as the data sets and
    cv2.COLOR_RGB2GRAY convert it) and a colour model as colour (grey repeated)."""
    import cv2

    grey_model = load_model(checkpoint)
    template, sources = pairs
    colour = np.stack([template, np.roll(template, 5, axis=0), template[::-1]], axis=2)
    colour_source = cv2_warp(colour, 3.0, -2.0, 20.0, 1.05)
    grey = [cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) for image in (colour, colour_source)]
    as_grey = grey_model.match(*grey)
    # equal up to the rounding of the two grey conversions (px, px, degrees, scale)
    from_colour = grey_model.match(colour, colour_source)
    torch.testing.assert_close(from_colour.as_tensor(), as_grey.as_tensor(), atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match="this model takes 1-channel images, got 3 channels"):  # tensors as given
        grey_model.match(torch.from_numpy(colour).permute(2, 0, 1)[None], torch.rand(1, 3, 64, 64))
    colour_model = load_model(write_checkpoint(checkpoint.parent / "colour.ckpt", *SMALL, "channels=3", seed=3))
    repeated = np.repeat(template[..., None], 3, axis=2)
    torch.testing.assert_close(
        colour_model.match(template, sources[0]).as_tensor(),
        colour_model.match(repeated, np.repeat(sources[0][..., None], 3, axis=2)).as_tensor(),
        rtol=0,
        atol=0,
    )


def test_load_model_replaces_inference_settings(checkpoint):
    model = load_model(checkpoint, rotation_hypotheses=3, hypothesis_ratio=0.5, rotation_views=4, inference_radii=24)
    assert (model.rotation_hypotheses, model.hypothesis_ratio, model.rotation_views) == (3, 0.5, 4)
    assert model.inference_radii == 24
    assert load_model(checkpoint, inference_radii="trained").inference_radii is None
    assert load_model(checkpoint, rotation_range=[0, 180]).rotation_range == (0.0, 180.0)
    assert load_model(checkpoint, scale_range=[0.8, 1.25]).scale_range == (0.8, 1.25)
    assert load_model(checkpoint).scale_range == (0.5, 2.0)  # tiny's, stored
    with pytest.raises(ValueError, match=r"scale_range must be \[low, high\] with 0 < low <= 1 <= high, got \[1.2, 2"):
        load_model(checkpoint, scale_range=[1.2, 2.0])
    with pytest.raises(ValueError, match="inference_radii must be an integer >= 2 or 'trained', got 'all'"):
        load_model(checkpoint, inference_radii="all")
    with pytest.raises(ValueError, match="rotation_views must be an integer from 1 to 8, got 9"):
        load_model(checkpoint, rotation_views=9)
    with pytest.raises(TypeError, match="unknown inference setting views"):
        set_inference_settings(model, views=2)


def test_load_model_refuses_bad_files_in_one_line(checkpoint, tmp_path):
    good = checkpoint.read_bytes()
    damaged, _ = _damaged_copy(good, tmp_path)
    with pytest.raises(CheckpointError, match="fails its CRC check"):
        load_model(damaged)
    foreign, marker = _foreign_copy(good, tmp_path)
    with pytest.raises(CheckpointError, match="holds Python objects that loading it would run"):
        load_model(foreign)
    assert not marker.exists()
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        load_model(tmp_path / "missing.ckpt")
    # a device this machine lacks is named as such, not called a corrupt file (torch's load fails on it)
    with pytest.raises(ValueError, match="map_location=hpu requested but this machine cannot use it") as error:
        load_model(checkpoint, map_location="hpu")
    assert not isinstance(error.value, CheckpointError)
    with pytest.raises(ValueError, match="map_location must be a device such as cpu, cuda or cuda:0, got 'gpu'"):
        load_matcher(checkpoint, map_location="gpu")
    with pytest.raises(CheckpointError, match="is a folder, not a checkpoint file"):
        load_model(tmp_path)
    other = torch.load(checkpoint, weights_only=True)
    other["hyper_parameters"]["net"]["base_channels"] = 8
    torch.save(other, tmp_path / "other.ckpt")
    # one line naming the first differences, not torch's list of every tensor
    fits = r"does not fit this version of dpcn: its weights are not its model's \(t_template.stem.0.weight is "
    for load, prefix in ((load_model, ""), (load_matcher, "model.")):
        with pytest.raises(CheckpointError, match=fits.replace("t_template", prefix + "t_template")) as error:
            load(tmp_path / "other.ckpt")
        assert "\n" not in str(error.value) and len(str(error.value)) < 400 and "more)" in str(error.value)
    assert dpcn.CheckpointError is CheckpointError and dpcn.training.CheckpointError is CheckpointError


def _imports_after(code: str) -> set[str]:
    """The top-level packages loaded after running ``code`` in a fresh interpreter."""
    probe = f"{code}\nimport sys\nprint(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return set(done.stdout.split())


def test_matching_from_a_checkpoint_needs_no_lightning_nor_hydra(checkpoint, tmp_path):
    import cv2

    template = str(tmp_path / "a.png")
    cv2.imwrite(template, (photo("camera", size=(64, 64)) * 255).astype(np.uint8))
    code = f"import dpcn\nprint(dpcn.load_model({str(checkpoint)!r}).match({template!r}, {template!r}))"
    loaded = _imports_after(code)
    assert "lightning" not in loaded and "hydra" not in loaded and "dpcn" in loaded
    # predict needs Hydra for its configuration, not Lightning (whose import took 2.5 s here)
    for extra in ([], [f"ckpt_path={checkpoint}"]):
        argv = ["predict", f"template={template}", f"source={template}", *extra]
        loaded = _imports_after(f"from dpcn.cli import main\nmain({argv!r})")
        assert "lightning" not in loaded and "hydra" in loaded, extra
