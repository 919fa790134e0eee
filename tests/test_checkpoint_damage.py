"""Damaged or foreign checkpoint files: one clear line saying what is wrong, never weights
loaded from damaged bytes, never code run from a file."""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import pytest
import torch

from dpcn.training.module import CheckpointError, load_matcher

from .conftest import write_checkpoint

PREFIX = "(corrupt or not a torch file): "


def _largest_member(path: Path) -> zipfile.ZipInfo:
    """The archive's biggest tensor storage: a weight, so damage to it changes the model."""
    with zipfile.ZipFile(path) as archive:
        storages = [info for info in archive.infolist() if "/data/" in info.filename]
    return max(storages, key=lambda info: info.file_size)


def _damage_member(path: Path, info: zipfile.ZipInfo) -> None:
    """Overwrite bytes in the middle of a stored member's data, leaving the zip structure intact."""
    data = bytearray(path.read_bytes())
    name_length = int.from_bytes(data[info.header_offset + 26 : info.header_offset + 28], "little")
    extra_length = int.from_bytes(data[info.header_offset + 28 : info.header_offset + 30], "little")
    start = info.header_offset + 30 + name_length + extra_length + info.file_size // 2
    data[start : start + 64] = bytes(255 - b for b in data[start : start + 64])
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> bytes:
    return write_checkpoint(tmp_path_factory.mktemp("ckpt") / "good.ckpt").read_bytes()


def _damaged_copy(good: bytes, folder: Path) -> tuple[Path, zipfile.ZipInfo]:
    """The good checkpoint with bytes of its biggest weight flipped, and that member."""
    path = folder / "damaged.ckpt"
    path.write_bytes(good)
    member = _largest_member(path)
    _damage_member(path, member)
    return path, member


def test_damage_inside_a_weight_is_refused_not_loaded(good, tmp_path):
    path, member = _damaged_copy(good, tmp_path)
    # torch itself loads the file and hands back different weights: the check is what stops it
    intact = torch.load(io.BytesIO(good), weights_only=False)["state_dict"]
    loaded = torch.load(path, weights_only=False)["state_dict"]
    assert any(not torch.equal(intact[k], loaded[k]) for k in intact)
    with pytest.raises(CheckpointError) as error:
        load_matcher(path)
    message = str(error.value)
    assert f"{PREFIX}archive member {member.filename!r} fails its CRC check" in message
    assert "\n" not in message


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (lambda good: b"", "the file is empty (0 bytes)"),
        (lambda good: b"hello world", "not a torch file: it begins with b'hello wo'"),
        (lambda good: good[: len(good) // 2], "the file ends too early: a torch archive of"),
    ],
)
def test_unreadable_files_say_why(good, tmp_path, content, reason):
    path = tmp_path / "bad.ckpt"
    path.write_bytes(content(good))
    with pytest.raises(CheckpointError) as error:
        load_matcher(path)
    message = str(error.value)
    assert message.startswith(f"cannot read checkpoint {path} {PREFIX}{reason}")
    assert "\n" not in message and "miniz" not in message and "Errno" not in message


def test_a_truncated_legacy_file_names_the_format(tmp_path):
    buffer = io.BytesIO()
    torch.save({"state_dict": {}}, buffer, _use_new_zipfile_serialization=False)
    path = tmp_path / "legacy.ckpt"
    path.write_bytes(buffer.getvalue()[:20])
    with pytest.raises(CheckpointError, match=r"a damaged legacy torch file \("):
        load_matcher(path)


def test_an_intact_checkpoint_still_loads(good, tmp_path):
    path = tmp_path / "good.ckpt"
    path.write_bytes(good)
    assert load_matcher(path).model is not None


class _MakesAFolder:
    """Pickles as a call of ``os.mkdir``: code that an unpickler would run on loading."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (os.mkdir, (str(self.path),))


def _foreign_copy(good: bytes, folder: Path) -> tuple[Path, Path]:
    """The good checkpoint with a pickled ``os.mkdir`` in its hyperparameters, and the folder
    that loading it would make."""
    marker = folder / "ran"
    checkpoint = torch.load(io.BytesIO(good), weights_only=True)
    checkpoint["hyper_parameters"]["payload"] = _MakesAFolder(marker)
    path = folder / "foreign.ckpt"
    torch.save(checkpoint, path)
    return path, marker


def test_a_checkpoint_that_would_run_code_is_refused_without_running_it(good, tmp_path):
    path, marker = _foreign_copy(good, tmp_path)
    with pytest.raises(CheckpointError) as error:
        load_matcher(path)
    assert not marker.exists()
    assert str(error.value).startswith(f"{path} holds Python objects that loading it would run (")
    assert "mkdir" in str(error.value) and "\n" not in str(error.value)


def test_a_module_made_in_python_from_omegaconf_and_numpy_values_loads_back(tmp_path):
    """Lightning stores the arguments as given; they are made plain first, so the checkpoint
    passes the tensors-and-plain-values reading above."""
    import lightning as L
    import numpy as np
    from omegaconf import OmegaConf

    from dpcn.training.module import DPCNModule

    net = {"base_channels": 2, "depth": 1, "image_size": [32, 32], "n_angles": 32, "n_radii": 32}
    module = DPCNModule(
        net=OmegaConf.create(net), temperature=np.float64(0.05), lr=np.float32(0.5), warmup_epochs=np.int64(2)
    )
    checkpoint = {
        "state_dict": module.state_dict(),
        "hyper_parameters": dict(module.hparams),
        "pytorch-lightning_version": L.__version__,
    }
    path = tmp_path / "python.ckpt"
    torch.save(checkpoint, path)
    loaded = load_matcher(path)
    assert loaded.hparams["net"] == net and type(loaded.hparams["net"]) is dict
    assert (loaded.hparams["temperature"], loaded.hparams["lr"], loaded.hparams["warmup_epochs"]) == (0.05, 0.5, 2)
    assert [type(loaded.hparams[k]) for k in ("temperature", "lr", "warmup_epochs")] == [float, float, int]
    for name, tensor in module.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor), name


# Lightning's own loader, the one the README's notebook snippet shows, gets the same checks.


def test_lightnings_loader_refuses_damage_inside_a_weight(good, tmp_path):
    from dpcn.training.module import DPCNModule

    path, member = _damaged_copy(good, tmp_path)
    with pytest.raises(CheckpointError, match="fails its CRC check") as error:
        DPCNModule.load_from_checkpoint(path)
    assert member.filename in str(error.value)


def test_lightnings_loader_refuses_code_without_running_it(good, tmp_path):
    from dpcn.training.module import DPCNModule

    path, marker = _foreign_copy(good, tmp_path)
    with pytest.raises(CheckpointError, match="holds Python objects that loading it would run"):
        DPCNModule.load_from_checkpoint(str(path))
    assert not marker.exists()


@pytest.mark.parametrize(("content", "reason"), [(b"", "the file is empty"), (None, "checkpoint not found")])
def test_lightnings_loader_names_a_missing_or_empty_file(tmp_path, content, reason):
    from dpcn.training.module import DPCNModule

    path = tmp_path / "model.ckpt"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(CheckpointError, match=reason):
        DPCNModule.load_from_checkpoint(path)


def test_lightnings_loader_still_loads_with_its_own_arguments(good, tmp_path):
    from dpcn.training.module import DPCNModule

    path = tmp_path / "good.ckpt"
    path.write_bytes(good)
    intact = torch.load(io.BytesIO(good), weights_only=True)
    module = DPCNModule.load_from_checkpoint(path, map_location="cpu", lr=0.123)
    assert module.hparams["lr"] == 0.123  # Lightning's keyword overrides still apply
    for name, tensor in intact["state_dict"].items():
        assert torch.equal(module.state_dict()[name], tensor), name
    # a stream is handed to Lightning as it is
    assert isinstance(DPCNModule.load_from_checkpoint(io.BytesIO(good)), DPCNModule)


def test_lightnings_loader_says_when_a_checkpoint_does_not_fit_this_version(good, tmp_path):
    from dpcn.training.module import DPCNModule

    checkpoint = torch.load(io.BytesIO(good), weights_only=True)
    net = checkpoint["hyper_parameters"]["net"]
    net["base_channels"] = 2 * net["base_channels"]  # settings that build other weights than the file's
    path = tmp_path / "other.ckpt"
    torch.save(checkpoint, path)
    with pytest.raises(CheckpointError, match=r"does not fit this version of dpcn: .*size mismatch"):
        DPCNModule.load_from_checkpoint(path)
