"""The checks of plain settings: values pass through, bad ones get an error naming them."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dpcn._validate import check_bool, check_device, check_int, check_number
from dpcn.data.datamodule import PairDataModule
from dpcn.estimator import PhaseCorrelationEstimator
from dpcn.models import DPCN
from dpcn.training.module import DPCNModule


def test_check_int_accepts_python_and_numpy_integers():
    assert check_int("n", 3) == 3
    assert check_int("n", np.int64(4), low=4) == 4 and type(check_int("n", np.int64(4))) is int


@pytest.mark.parametrize("value", ["3", 2.5, 2.0, True, None, [1], 0])
def test_check_int_rejects_non_integers_and_values_below_the_bound(value):
    with pytest.raises(ValueError, match=r"^depth must be an integer >= 1, got "):
        check_int("depth", value, low=1)


def test_check_bool_takes_only_booleans():
    assert check_bool("b", True) is True and check_bool("b", np.bool_(False)) is False
    for value in ("maybe", "true", 1, 0, None):  # a CLI typo is not a truthy value
        with pytest.raises(ValueError) as info:
            check_bool("model.net.highpass", value)
        assert str(info.value) == f"model.net.highpass must be true or false, got {value!r}"


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("bogus", "device must be a device such as cpu, cuda or cuda:0, got 'bogus'"),
        ("cuda:x", "device must be a device such as cpu, cuda or cuda:0, got 'cuda:x'"),
        (3.5, "device must be a device such as cpu, cuda or cuda:0, got 3.5"),
        ("meta", "device=meta: the meta device holds no values to compute with"),
        ("hpu", "device=hpu requested but this machine cannot use it ("),
        ("cuda:99", "device=cuda:99 requested but "),  # no CUDA here, or fewer devices
    ],
)
def test_check_device_names_a_device_this_machine_lacks(value, message):
    with pytest.raises(ValueError) as error:
        check_device("device", value)
    assert str(error.value).startswith(message) and "\n" not in str(error.value)


def test_check_device_passes_the_devices_this_machine_has():
    assert check_device("device", "cpu") == torch.device("cpu")
    assert check_device("map_location", torch.device("cpu")) == torch.device("cpu")
    if torch.cuda.is_available():
        assert check_device("device", "cuda:0") == torch.device("cuda:0")
    else:
        with pytest.raises(ValueError, match="device=cuda requested but CUDA is not available"):
            check_device("device", "cuda")


def test_check_number_ranges():
    assert check_number("x", 0, low=0.0) == 0.0
    assert check_number("x", np.float32(0.5), low=0.0, high=1.0) == 0.5
    assert check_number("x", 1, low=0.0, high=1.0, low_open=True) == 1.0
    for value, kwargs, message in [
        (0.0, dict(low=0.0, low_open=True), "x must be a finite number > 0, got 0.0"),
        (-1, dict(low=0.0), "x must be a finite number >= 0, got -1"),
        (1.5, dict(low=0.0, high=1.0), "x must be a finite number in [0, 1], got 1.5"),
        (0.0, dict(low=0.0, high=1.0, low_open=True), "x must be a finite number in (0, 1], got 0.0"),
        (2, dict(high=1.0), "x must be a finite number <= 1, got 2"),
        ("abc", {}, "x must be a finite number, got 'abc'"),
        (math.nan, {}, "x must be a finite number, got nan"),
        (math.inf, dict(low=0.0), "x must be a finite number >= 0, got inf"),
        (False, {}, "x must be a finite number, got False"),
    ]:
        with pytest.raises(ValueError) as info:
            check_number("x", value, **kwargs)
        assert str(info.value) == message


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(sigma="abc"), "model.net.sigma must be a finite number >= 0, got 'abc'"),
        (dict(temperature=0), "model.net.temperature must be a finite number > 0, got 0"),
        (dict(base_channels="8"), "model.net.base_channels must be an integer >= 1, got '8'"),
        (dict(n_angles=1), "model.net.n_angles must be an integer >= 2, got 1"),
        (dict(max_radius=1.5), "model.net.max_radius must be a finite number in (0, 1], got 1.5"),
        (dict(image_size=(256, "x")), "image_size must be an integer >= 8, got 'x'"),
        (dict(image_size=256), "image_size must be an (H, W) pair of integers, got 256"),
        (dict(scale_range=(0.5, "2")), "scale_range must be a finite number > 0, got '2'"),
        (dict(train_temperature=(0.1, -1.0)), "train_temperature must be a finite number > 0, got -1.0"),
        (dict(spectrum_window_step="abc"), "spectrum_window_step must be in (0, 0.5)"),
        (dict(highpass="maybe"), "model.net.highpass must be true or false, got 'maybe'"),
        (dict(log_spectrum=1), "model.net.log_spectrum must be true or false, got 1"),
        (dict(input_skip="no"), "model.net.input_skip must be true or false, got 'no'"),
    ],
)
def test_dpcn_settings_are_checked_by_name(kwargs, message):
    with pytest.raises(ValueError) as info:
        DPCN(**kwargs)
    assert message in str(info.value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(lr="abc"), "model.lr must be a finite number > 0, got 'abc'"),
        (dict(weight_decay=-1.0), "model.weight_decay must be a finite number >= 0, got -1.0"),
        (dict(teacher_forcing=1.5), "model.teacher_forcing must be a finite number in [0, 1], got 1.5"),
        (dict(warmup_epochs=0.5), "model.warmup_epochs must be an integer >= 0, got 0.5"),
        (dict(translation_fraction=0), "model.translation_fraction must be a finite number in (0, 1], got 0"),
        (dict(temperature=[0.1, "abc"]), "model.temperature must be a finite number > 0, got 'abc'"),
        (dict(learnable_temperature="yes"), "model.learnable_temperature must be true or false, got 'yes'"),
        (dict(warp_grad=1), "model.warp_grad must be true or false, got 1"),
    ],
)
def test_training_settings_are_checked_by_name(kwargs, message):
    net = dict(image_size=(32, 32), base_channels=2, depth=1, n_angles=16, n_radii=16)
    with pytest.raises(ValueError) as info:
        DPCNModule(net=net, **kwargs)
    assert str(info.value) == message


@pytest.mark.parametrize("name", ["highpass", "log_spectrum", "resolve_180"])
def test_estimator_switches_are_checked_by_name(name):
    with pytest.raises(ValueError, match=rf"^{name} must be true or false, got 'maybe'$"):
        PhaseCorrelationEstimator(**{name: "maybe"})


def test_data_module_settings_are_checked_by_name():
    with pytest.raises(ValueError, match=r"^data.batch_size must be an integer >= 1, got 'abc'$"):
        PairDataModule(dataset=dict, batch_size="abc")
    with pytest.raises(ValueError, match=r"^data.num_workers must be an integer >= 0, got -1$"):
        PairDataModule(dataset=dict, num_workers=-1)
