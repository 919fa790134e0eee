"""Training losses of DPCN (paper eq. 12-13): L1 on the soft-argmax expectation and KL
divergence to a Gaussian one-peak target, per phase, mixed by weights.

Everything is measured in the bins of the correlation surface it supervises (log-polar rows
and columns, pixels), so the weights of the two phases are comparable.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .._validate import check_number
from ..ops.soft_argmax import soft_argmax2d

__all__ = [
    "gaussian_target",
    "one_peak_kl",
    "half_turn_nll",
    "expectation_l1",
    "DPCNLoss",
    "rotation_scale_target",
    "translation_target",
]


def _offsets(n: int, centre: Tensor, circular: bool) -> Tensor:
    d = torch.arange(n, device=centre.device, dtype=centre.dtype)[None] - centre[:, None]
    return torch.remainder(d + n / 2, n) - n / 2 if circular else d


def gaussian_target(
    shape: tuple[int, int], centre: Tensor, sigma: float, circular: tuple[bool, bool] = (False, False)
) -> Tensor:
    """``(B, H, W)`` normalised Gaussian bumps at sub-pixel ``centre`` ``(B, 2)`` (row, col)."""
    dy = _offsets(shape[0], centre[:, 0], circular[0])
    dx = _offsets(shape[1], centre[:, 1], circular[1])
    logits = -(dy[:, :, None] ** 2 + dx[:, None, :] ** 2) / (2 * sigma**2)
    return torch.softmax(logits.flatten(1), dim=1).view(-1, *shape)


def one_peak_kl(
    surface: Tensor, centre: Tensor, temperature: Tensor | float, sigma: float, circular: tuple[bool, bool]
) -> Tensor:
    """``KL(target || softmax(surface / temperature))`` per pair, ``(B,)``."""
    target = gaussian_target(surface.shape[-2:], centre, sigma, circular)
    log_p = torch.log_softmax((surface / temperature).flatten(1), dim=1)
    t = target.flatten(1)
    return (t * (torch.log(t.clamp_min(1e-30)) - log_p)).sum(dim=1)


def half_turn_nll(upright: Tensor, turned: Tensor, temperature: Tensor | float) -> Tensor:
    """``-log P(upright)`` per pair, ``(B,)``, under one softmax over both phase-2 surfaces.

    ``upright`` and ``turned`` are ``(B, H, W)`` correlation surfaces of the same template with
    the source un-warped by the right angle and by that angle plus half a turn. The one-peak KL
    over both surfaces together, with no target mass on ``turned``, is the one-peak KL of
    ``upright`` plus this term, ``log(1 + Z_turned / Z_upright)`` (``Z``: the sums of
    ``exp(surface / temperature)``). It trains the half-turn check that inference makes by
    comparing the two surfaces' peaks.
    """
    upright = torch.logsumexp((upright / temperature).flatten(1), dim=1)
    turned = torch.logsumexp((turned / temperature).flatten(1), dim=1)
    return F.softplus(turned - upright)


def expectation_l1(
    surface: Tensor, centre: Tensor, temperature: Tensor | float, circular: tuple[bool, bool]
) -> tuple[Tensor, Tensor]:
    """Per-axis ``|E[position] - centre|`` in bins (whole-surface soft-argmax), ``(B,)`` each."""
    peak = soft_argmax2d(surface, temperature, window=None, circular=circular)
    errors = []
    for axis, n in enumerate(surface.shape[-2:]):
        d = peak[:, axis] - centre[:, axis]
        if circular[axis]:
            d = torch.remainder(d + n / 2, n) - n / 2
        errors.append(d.abs())
    return errors[0], errors[1]


def rotation_scale_target(angle: Tensor, scale: Tensor, n_angles: int, n_radii: int, radius_step: float) -> Tensor:
    """``(B, 2)`` (row, col) of the true peak on the phase-1 log-polar correlation surface."""
    row = torch.remainder(n_angles // 2 - angle * (n_angles / 180.0), n_angles)
    col = n_radii // 2 - torch.log(scale) / radius_step
    return torch.stack([row, col], dim=1)


def translation_target(tx: Tensor, ty: Tensor, angle: Tensor, scale: Tensor, size: tuple[int, int]) -> Tensor:
    """``(B, 2)`` (row, col) of the true peak on the phase-2 surface, for a source un-warped by
    ``angle``/``scale``: the shift there is ``A^-1 t`` (``A`` the pose's linear part)."""
    theta = torch.deg2rad(angle)
    c, s = torch.cos(theta), torch.sin(theta)
    dx = (c * tx - s * ty) / scale
    dy = (s * tx + c * ty) / scale
    return torch.stack([size[0] // 2 + dy, size[1] // 2 + dx], dim=1)


@dataclass
class LossTerms:
    total: Tensor
    terms: dict[str, Tensor]


class DPCNLoss(nn.Module):
    """Weighted sum of the L1 and one-peak KL losses of both phases.

    Args:
        l1_weight, kl_weight: default weight of every L1 (expectation, in bins) term and of
            every one-peak KL term.
        l1_rotation, l1_scale, l1_translation, kl_rotation_scale, kl_translation: per-term
            weights overriding those defaults (``None``: the default).
        sigma: width (bins) of the Gaussian one-peak target.
        kl_align: weight of an extra one-peak KL term on phase 1's *features* (0: off, the
            paper's loss): the source's phase-1 features, un-warped by the true rotation and
            scale, phase-correlated with the template's in space; the target is the true
            shift. The paper's phase-1 loss reaches the features only through their
            magnitude spectra, which discard where structures are; this term asks the two
            extractors directly for maps that coincide where the images share geometry.
        kl_half_turn: weight of the one-peak KL of phase 2 taken over the upright and the
            half-turned source's surfaces together (0: off, the paper's loss; see
            :func:`half_turn_nll`, the extra over ``kl_translation``). Phase 1 knows the
            angle modulo half a turn and inference settles it by phase 2's stronger peak,
            which the paper's losses, on the upright surface only, never train.
        hard_pair_gamma: weight the phase-1 terms (rotation/scale L1 and KL, alignment) of
            each pair by its phase-1 one-peak KL to the power ``hard_pair_gamma``, detached
            and normalised to a mean of 1 over the batch, as focal losses weight hard
            examples (0: off, every pair alike, the paper's loss; negative values, down to
            -2, weight them down instead, as robust losses do; the KL is floored at 0.01).
    """

    def __init__(
        self,
        l1_weight: float = 1.0,
        kl_weight: float = 1.0,
        sigma: float = 1.5,
        l1_rotation: float | None = None,
        l1_scale: float | None = None,
        l1_translation: float | None = None,
        kl_rotation_scale: float | None = None,
        kl_translation: float | None = None,
        kl_align: float = 0.0,
        kl_half_turn: float = 0.0,
        hard_pair_gamma: float = 0.0,
    ) -> None:
        super().__init__()
        overrides = dict(
            l1_rotation=l1_rotation,
            l1_scale=l1_scale,
            l1_translation=l1_translation,
            kl_rotation_scale=kl_rotation_scale,
            kl_translation=kl_translation,
        )
        for key, value in (("l1_weight", l1_weight), ("kl_weight", kl_weight)):  # named as the user set them
            check_number(f"loss.{key}", value, low=0.0)
        self.weights = {
            key: (l1_weight if key.startswith("l1") else kl_weight) if value is None else value
            for key, value in overrides.items()
        }
        self.weights["kl_align"] = kl_align
        self.weights["kl_half_turn"] = kl_half_turn
        for key, value in self.weights.items():
            check_number(f"loss.{key}", value, low=0.0)
        check_number("loss.sigma", sigma, low=0.0, low_open=True)
        check_number("loss.hard_pair_gamma", hard_pair_gamma, low=-2.0, high=4.0)
        self.hard_pair_gamma = float(hard_pair_gamma)
        weights = tuple(self.weights.values())
        if not any(w > 0 for w in weights):
            raise ValueError(f"loss weights must be >= 0 and not all zero, got {weights}")
        self.sigma = sigma

    def forward(
        self,
        rs_surface: Tensor,
        rs_centre: Tensor,
        t_surface: Tensor,
        t_centre: Tensor,
        temperatures: Tensor,
        align_surface: Tensor | None = None,
        align_centre: Tensor | None = None,
        turned_surface: Tensor | None = None,
    ) -> LossTerms:
        """Surfaces ``(B, H, W)`` with their true peaks ``(B, 2)`` (row, col); ``temperatures``
        ``(2,)`` (phase 1, phase 2; the alignment and half-turn terms use phase 2's). The
        alignment surface is needed when ``kl_align > 0``, and ``turned_surface`` (phase 2's
        surface for the source turned by half a turn, like ``t_surface``) when
        ``kl_half_turn > 0``."""
        t_rs, t_tr = temperatures[0], temperatures[1]
        terms: dict[str, Tensor] = {}
        rs_kl = None  # per pair; the phase-1 KL term and the hard-pair weights share it
        if self.weights["kl_rotation_scale"] or self.hard_pair_gamma:
            rs_kl = one_peak_kl(rs_surface, rs_centre, t_rs, self.sigma, (True, False))
        phase1_mean = self._phase1_mean(rs_kl)
        if self.weights["l1_rotation"] or self.weights["l1_scale"]:
            rot, sc = expectation_l1(rs_surface, rs_centre, t_rs, (True, False))
            terms["l1_rotation"], terms["l1_scale"] = phase1_mean(rot), phase1_mean(sc)
        if self.weights["l1_translation"]:
            dy, dx = expectation_l1(t_surface, t_centre, t_tr, (True, True))
            terms["l1_translation"] = (dy + dx).mean()
        if self.weights["kl_rotation_scale"]:
            terms["kl_rotation_scale"] = phase1_mean(rs_kl)
        if self.weights["kl_translation"]:
            terms["kl_translation"] = one_peak_kl(t_surface, t_centre, t_tr, self.sigma, (True, True)).mean()
        if self.weights["kl_align"]:
            if align_surface is None or align_centre is None:
                raise ValueError("loss.kl_align > 0 needs the phase-1 alignment surface and its true peak")
            terms["kl_align"] = phase1_mean(one_peak_kl(align_surface, align_centre, t_tr, self.sigma, (True, True)))
        if self.weights["kl_half_turn"]:
            if turned_surface is None:
                raise ValueError("loss.kl_half_turn > 0 needs phase 2's surface for the half-turned source")
            terms["kl_half_turn"] = half_turn_nll(t_surface, turned_surface, t_tr).mean()
        total = sum(self.weights[k] * v for k, v in terms.items() if self.weights[k])
        if not isinstance(total, Tensor) or not math.isfinite(float(total.detach())):
            raise FloatingPointError(f"non-finite training loss: { {k: float(v) for k, v in terms.items()} }")
        return LossTerms(total, terms)

    def _phase1_mean(self, rs_kl: Tensor | None) -> Callable[[Tensor], Tensor]:
        """The batch mean of ``(B,)`` phase-1 per-pair terms, each pair weighted by its
        phase-1 one-peak KL ``rs_kl`` with ``hard_pair_gamma`` (a plain mean when it is 0)."""
        if not self.hard_pair_gamma:
            return torch.mean
        assert rs_kl is not None  # computed whenever hard_pair_gamma is set
        weight = rs_kl.detach().clamp_min(0.01) ** self.hard_pair_gamma
        weight = weight / weight.mean()

        def weighted_mean(values: Tensor) -> Tensor:
            return (values * weight.to(values.dtype)).mean()

        return weighted_mean
