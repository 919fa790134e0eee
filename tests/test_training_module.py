"""DPCNModule's training loss without a trainer: the phase-2 share of each batch."""

import re
import warnings

import pytest
import torch

from dpcn.models import half_turn
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


@pytest.mark.parametrize("downsample", [1, 2])
def test_alignment_surface_peaks_at_the_true_shift(downsample):
    """With the images themselves as 'features', the alignment term's surface peaks where its
    target says (the source made by OpenCV, shifts halved at half resolution)."""
    module = DPCNModule(net=dict(NET, image_size=(64, 64), rotation_scale_downsample=downsample))
    names, poses = ("camera", "astronaut"), [(6.0, -4.0, 30.0, 1.1), (-8.0, 5.0, -150.0, 0.9)]
    images = [photo(name, (64, 64)) for name in names]
    template = torch.stack([torch.from_numpy(im)[None] for im in images])
    source = torch.stack([torch.from_numpy(cv2_warp(im, *p))[None] for im, p in zip(images, poses, strict=True)])
    shrink = module.model.rotation_scale_input
    features = {"rs_template": shrink(template), "rs_source": shrink(source)}
    surface, centre = module._alignment(features, torch.tensor(poses))
    size = 64 // downsample
    assert surface.shape == (2, size, size) and centre.shape == (2, 2)
    peaks = surface.flatten(1).argmax(dim=1)
    found = torch.stack([peaks // size, peaks % size], dim=1).float()
    assert (found - centre).abs().max() <= 1.0


def test_alignment_term_trains_both_phase1_extractors():
    torch.manual_seed(0)
    module = DPCNModule(net=NET, loss=dict(kl_align=1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log() without a trainer
        loss = module._training_loss(*batch())
    assert torch.isfinite(loss)
    # Only the new term: the paper's terms off, so any phase-1 gradient comes from it.
    torch.manual_seed(0)
    only = DPCNModule(net=NET, loss=dict(l1_weight=0.0, kl_weight=0.0, kl_align=1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        only._training_loss(*batch()).backward()
    for net in (only.model.rs_template, only.model.rs_source):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in only.model.t_source.parameters())


def test_half_turn_term_trains_phase2_on_the_turned_source():
    torch.manual_seed(0)
    only = DPCNModule(net=NET, loss=dict(l1_weight=0.0, kl_weight=0.0, kl_half_turn=1.0))
    seen: list[torch.Tensor] = []
    only.model.t_source.register_forward_hook(lambda module, args, out: seen.append(args[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log() without a trainer
        loss = only._training_loss(*batch())
    loss.backward()
    assert torch.isfinite(loss) and loss.item() > 0
    # One source pass holding the upright and the half-turned un-warps of the phase-2 pairs.
    (inputs,) = seen
    upright, turned = inputs.chunk(2)
    torch.testing.assert_close(turned, half_turn(upright))
    # Only the new term: gradients reach phase 2's extractors and its temperature, not phase 1.
    for net in (only.model.t_template, only.model.t_source):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in only.model.rs_template.parameters())
    # Off (the default): one source pass, upright only.
    seen.clear()
    off = DPCNModule(net=NET)
    off.model.t_source.register_forward_hook(lambda module, args, out: seen.append(args[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        off._training_loss(*batch())
    assert len(seen) == 1 and seen[0].shape == upright.shape


def test_gradcheck_alignment_surface():
    module = DPCNModule(net=dict(NET, image_size=(16, 16))).double()
    gt = torch.tensor([[1.5, -2.0, 35.0, 1.1]], dtype=torch.float64)
    torch.manual_seed(0)
    template = torch.rand(1, 2, 8, 8, dtype=torch.float64, requires_grad=True)
    source = torch.rand(1, 2, 8, 8, dtype=torch.float64, requires_grad=True)

    def surface(t: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        return module._alignment({"rs_template": t, "rs_source": s}, gt)[0]

    assert torch.autograd.gradcheck(surface, (template, source))


def test_nearest_training_window_follows_the_inference_grid():
    """``train_spectrum_window="nearest"`` moves phase 1's source window during training only
    when there is a grid to pick from; a bad value is refused by name."""
    template, source, gt = batch()
    gt[:, 0] = torch.tensor([9.0, -9.0, 2.0, 12.0])  # shifts of a quarter of the side and more

    def loss(window: str, grid: int) -> torch.Tensor:
        torch.manual_seed(0)
        module = DPCNModule(net=dict(NET, spectrum_window_grid=grid), train_spectrum_window=window)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # self.log() without a trainer
            value = module._training_loss(template, source, gt)
        value.backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.model.rs_source.parameters())
        return value.detach()

    torch.testing.assert_close(loss("nearest", 1), loss("centred", 1))
    assert torch.isfinite(loss("nearest", 3)) and not torch.allclose(loss("nearest", 3), loss("centred", 3))
    with pytest.raises(ValueError, match="model.train_spectrum_window must be one of centred, nearest, got 'best'"):
        DPCNModule(net=NET, train_spectrum_window="best")


@pytest.mark.parametrize(("frozen", "trained"), [("rotation_scale", "translation"), ("translation", "rotation_scale")])
def test_a_frozen_phase_gets_no_gradients_and_no_optimiser_slot(frozen, trained):
    from dpcn.training.module import FREEZABLE

    torch.manual_seed(0)
    module = DPCNModule(net=NET, freeze=[frozen], loss=dict(kl_align=1.0, kl_half_turn=1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log() without a trainer
        loss = module._training_loss(*batch())
    loss.backward()
    for name in FREEZABLE[frozen]:
        net = getattr(module.model, name)
        assert all(not p.requires_grad and p.grad is None for p in net.parameters())
    for name in FREEZABLE[trained]:
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in getattr(module.model, name).parameters())
    optimised = {id(p) for group in module.configure_optimizers().param_groups for p in group["params"]}
    frozen_params = [p for name in FREEZABLE[frozen] for p in getattr(module.model, name).parameters()]
    assert frozen_params and not optimised & {id(p) for p in frozen_params}
    assert optimised == {id(p) for p in module.parameters() if p.requires_grad}
    # train() keeps the frozen U-Nets in eval mode (BatchNorm statistics stay as loaded).
    module.train()
    assert all(not getattr(module.model, name).training for name in FREEZABLE[frozen])
    assert all(getattr(module.model, name).training for name in FREEZABLE[trained])


def test_frozen_batchnorm_statistics_do_not_move():
    torch.manual_seed(0)
    module = DPCNModule(net=dict(NET, norm="batch"), freeze="rotation_scale").train()
    before = {k: v.clone() for k, v in module.model.rs_template.state_dict().items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        module._training_loss(*batch())
    after = module.model.rs_template.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    # The trained phase's running statistics do move (they start at zero).
    assert module.model.t_template.state_dict()["stem.1.running_mean"].abs().sum() > 0


@pytest.mark.parametrize(
    ("freeze", "message"),
    [
        (["rotation"], "model.freeze takes a list of rotation_scale, translation; got ['rotation']"),
        (5, "model.freeze takes a list of rotation_scale, translation; got 5"),
        (["rotation_scale", "translation"], "model.freeze names both phases: nothing would be trained"),
    ],
)
def test_bad_freeze_is_refused(freeze, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        DPCNModule(net=NET, freeze=freeze)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t, s, p: {"template": t[:1], "source": s, "pose": p}, "pairs each template with one source; got 1"),
        (lambda t, s, p: {"template": t, "source": s, "pose": p[:, :3]}, r"pose must be \(4, 4\).*got \(4, 3\)"),
        (lambda t, s, p: {"template": t, "source": s, "pose": p[:2]}, r"pose must be \(4, 4\).*got \(2, 4\)"),
        (
            lambda t, s, p: {"template": t, "source": s, "pose": p.index_fill(0, torch.tensor([1]), float("nan"))},
            "finite",
        ),
        (lambda t, s, p: {"template": t, "source": s, "pose": p.long()}, "pose must be floating point.*int64"),
        (
            lambda t, s, p: {"template": t, "source": s, "pose": p.index_fill(0, torch.tensor([2]), float("inf"))},
            "row 2 is",
        ),
        (lambda t, s, p: {"image": t, "source": s, "pose": p}, r"keys template, source, pose; got \['image'"),
        (lambda t, s, p: (t, s, p), "a dict with the keys template, source, pose; got tuple"),
    ],
)
def test_bad_training_batches_are_named(change, message):
    # A user's own dataset may hand over batches of another form: one line, before any torch op.
    module = DPCNModule(net=NET)
    with pytest.raises(ValueError, match=message):
        module.training_step(change(*batch()), 0)


def test_evaluation_matches_one_template_against_a_batch_of_sources():
    # Evaluation, unlike training, may match one template against every source of a batch.
    # In float64: in float32 the template's batch of one and batch of four may round apart
    # (1.5e-5 degrees on some CPUs), which says nothing about the one-template path.
    torch.manual_seed(0)
    module = DPCNModule(net=NET).double()
    templates, sources, poses = (x.double() for x in batch())
    module._reset()
    errors = module._evaluate_batch({"template": templates[:1], "source": sources, "pose": poses})
    copies = module._evaluate_batch({"template": templates[:1].repeat(4, 1, 1, 1), "source": sources, "pose": poses})
    assert errors.shape[0] == 4 and len(module._records) == 2
    torch.testing.assert_close(errors, copies)
    with pytest.raises(ValueError, match=r"pose must be \(4, 4\)"):
        module._evaluate_batch({"template": templates[:1], "source": sources, "pose": poses[:1]})
