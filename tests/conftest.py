"""Shared fixtures: real photographs (bundled with scikit-image) and OpenCV-made pairs."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

CONF = Path(__file__).resolve().parents[1] / "conf"
BENCHMARKS = CONF.parent / "benchmarks"

PHOTOS = ("camera", "astronaut", "coffee", "chelsea", "rocket", "brick", "gravel", "immunohistochemistry")


def photo(name: str, size: tuple[int, int] = (256, 256), colour: bool = False) -> np.ndarray:
    """Central crop of a scikit-image sample photograph, float32 in [0, 1]."""
    from skimage import data

    image = getattr(data, name)()
    if image.ndim == 3 and not colour:
        image = cv2.cvtColor(image[..., :3], cv2.COLOR_RGB2GRAY)
    elif image.ndim == 2 and colour:
        image = np.repeat(image[..., None], 3, axis=2)
    h, w = size
    top, left = (image.shape[0] - h) // 2, (image.shape[1] - w) // 2
    return np.ascontiguousarray(image[top : top + h, left : left + w]).astype(np.float32) / 255.0


def cv2_warp(template: np.ndarray, tx: float, ty: float, angle: float, scale: float) -> np.ndarray:
    """The project's pose convention, straight from OpenCV."""
    h, w = template.shape[:2]
    m = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
    m[0, 2] += tx
    m[1, 2] += ty
    return cv2.warpAffine(template, m, (w, h))


def angle_error(a: float | torch.Tensor, b: float | torch.Tensor) -> float:
    d = (float(a) - float(b) + 180.0) % 360.0 - 180.0
    return abs(d)


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


def compose_config(*overrides: str, return_hydra_config: bool = False):
    """The project's real ``conf/config.yaml`` composed with command-line style overrides."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=return_hydra_config)


def load_benchmark(name: str):
    """A script of ``benchmarks/`` imported as a module (they are not part of the package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def write_checkpoint(path: Path, *overrides: str, seed: int = 0) -> Path:
    """A checkpoint file as ``dpcn fit`` writes it, as far as ``load_matcher`` and
    ``DPCNModule.load_from_checkpoint`` read one: the weights of the model the real configs
    compose (with ``overrides``, initialised from ``seed``), its hyperparameters and Lightning's version."""
    import lightning as L
    from hydra.utils import instantiate

    torch.manual_seed(seed)
    module = instantiate(compose_config(*overrides).model, _convert_="all")
    checkpoint = {
        "state_dict": module.state_dict(),
        "hyper_parameters": dict(module.hparams),
        "pytorch-lightning_version": L.__version__,
    }
    torch.save(checkpoint, path)
    return path
