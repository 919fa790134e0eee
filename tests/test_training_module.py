"""DPCNModule's training loss without a trainer: the phase-2 share of each batch."""

import warnings

import pytest
import torch

from dpcn.training.module import DPCNModule

from .conftest import cv2_warp, photo

NET = dict(base_channels=2, depth=1, image_size=(32, 32), n_angles=32, n_radii=32)


def batch(n: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Real-photograph pairs made with OpenCV, poses ``(tx, ty, angle, scale)``."""
    names = ("camera", "astronaut", "coffee", "chelsea")
    poses = [(2.0, -1.0, 10.0, 1.1), (-3.0, 2.0, -25.0, 0.9), (1.0, 1.0, 140.0, 1.0), (0.0, -2.0, 60.0, 1.05)]
    templates, sources = [], []
    for name, pose in zip(names[:n], poses[:n], strict=True):
        image = photo(name, (32, 32))
        templates.append(torch.from_numpy(image)[None])
        sources.append(torch.from_numpy(cv2_warp(image, *pose))[None])
    return torch.stack(templates), torch.stack(sources), torch.tensor(poses[:n], dtype=torch.float32)


def loss_and_phase2_batches(fraction: float) -> tuple[DPCNModule, torch.Tensor, list[int]]:
    torch.manual_seed(0)
    module = DPCNModule(net=NET, translation_fraction=fraction)
    seen: list[int] = []
    module.model.t_template.register_forward_hook(lambda _m, args, _out: seen.append(args[0].shape[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log() without a trainer
        loss = module._training_loss(*batch())
    return module, loss, seen


@pytest.mark.parametrize(("fraction", "pairs"), [(1.0, 4), (0.5, 2), (0.25, 1), (0.01, 1)])
def test_phase2_trains_on_the_first_share_of_the_batch(fraction, pairs):
    module, loss, seen = loss_and_phase2_batches(fraction)
    assert seen == [pairs]
    assert torch.isfinite(loss)
    loss.backward()
    for net in (module.model.rs_template, module.model.t_template, module.model.t_source):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


def test_phase1_gradients_do_not_depend_on_the_phase2_share():
    # Without warp_grad, phase 2's loss does not reach phase 1, which always sees the whole batch.
    phase1, phase2 = [], []
    for fraction in (1.0, 0.25):
        module, loss, _ = loss_and_phase2_batches(fraction)
        loss.backward()
        phase1.append(torch.cat([p.grad.flatten() for p in module.model.rs_template.parameters()]))
        phase2.append(torch.cat([p.grad.flatten() for p in module.model.t_template.parameters()]))
    torch.testing.assert_close(phase1[0], phase1[1])
    assert not torch.allclose(phase2[0], phase2[1])


@pytest.mark.parametrize("fraction", [0.0, -0.5, 1.5])
def test_bad_phase2_share_is_refused(fraction):
    with pytest.raises(ValueError, match="translation_fraction"):
        DPCNModule(net=NET, translation_fraction=fraction)
