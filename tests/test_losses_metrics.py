"""Losses (against the classical estimator's own surfaces) and the paper's metrics."""

import math
import re

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from torch.autograd import gradcheck

from dpcn.estimator import estimate_rotation_scale, estimate_translation, unwarp_rotation_scale
from dpcn.metrics import (
    CURVE_THRESHOLDS,
    accuracy_curve,
    format_table,
    pose_errors,
    summarize,
    thresholds_for,
    write_csv,
    write_curve_csv,
)
from dpcn.ops.logpolar import log_radius_step
from dpcn.training.losses import (
    DPCNLoss,
    expectation_l1,
    gaussian_target,
    half_turn_nll,
    one_peak_kl,
    rotation_scale_target,
    translation_target,
)

from .conftest import compose_config, cv2_warp, photo

TRUTH = (13.0, -21.0, 37.0, 1.12)


@pytest.fixture(scope="module")
def pair():
    template = photo("astronaut")
    source = cv2_warp(template, *TRUTH)
    return torch.from_numpy(template)[None, None], torch.from_numpy(source)[None, None]


def test_targets_sit_on_the_classical_peaks(pair):
    """The supervision targets must be where phase correlation itself puts the true pose."""
    t, s = pair
    tx, ty, angle, scale = (torch.tensor([v]) for v in TRUTH)
    rs = estimate_rotation_scale(t, s)
    centre = rotation_scale_target(angle, scale, 256, 256, log_radius_step(256, 0.03, 0.95))
    peak = divmod(int(rs.surface[0].argmax()), 256)
    assert abs(peak[0] - float(centre[0, 0])) <= 1 and abs(peak[1] - float(centre[0, 1])) <= 1
    # translation surface of a source un-warped by a slightly wrong rotation/scale
    un_angle, un_scale = angle + 0.3, scale * 1.002
    tr = estimate_translation(t, unwarp_rotation_scale(s, un_angle, un_scale), un_angle, un_scale, resolve_180=False)
    centre = translation_target(tx, ty, un_angle, un_scale, (256, 256))
    peak = divmod(int(tr.surface[0].argmax()), 256)
    assert abs(peak[0] - float(centre[0, 0])) <= 1 and abs(peak[1] - float(centre[0, 1])) <= 1


def test_gaussian_target_normalised_and_circular():
    target = gaussian_target((16, 20), torch.tensor([[0.2, 10.0], [8.0, 3.5]]), sigma=1.5, circular=(True, False))
    torch.testing.assert_close(target.sum(dim=(1, 2)), torch.ones(2))
    assert target[0, 15, 10] > target[0, 3, 10]  # wraps around the row axis
    assert int(target[1].argmax()) // 20 == 8


def test_kl_is_zero_at_the_target_and_l1_at_the_centre():
    centre = torch.tensor([[5.3, 7.6]], dtype=torch.float64)
    target = gaussian_target((16, 16), centre, 1.5, (True, True))
    surface = 0.02 * torch.log(target)
    assert float(one_peak_kl(surface, centre, 0.02, 1.5, (True, True))) == pytest.approx(0.0, abs=1e-9)
    rows, cols = expectation_l1(surface, centre, 0.02, (True, True))
    assert float(rows) < 0.02 and float(cols) < 0.02
    far = torch.zeros(1, 16, 16, dtype=torch.float64)
    far[0, 12, 1] = 1.0
    assert float(one_peak_kl(far, centre, 0.02, 1.5, (True, True))) > 10


def test_loss_weights_and_errors():
    loss = DPCNLoss(l1_weight=0.0, kl_weight=1.0, kl_translation=3.0)
    assert loss.weights["l1_rotation"] == 0 and loss.weights["kl_translation"] == 3.0
    with pytest.raises(ValueError, match="not all zero"):
        DPCNLoss(l1_weight=0.0, kl_weight=0.0)
    with pytest.raises(ValueError, match="sigma"):
        DPCNLoss(sigma=0.0)
    with pytest.raises(ValueError, match=r"loss\.l1_rotation must be a finite number >= 0, got 'abc'"):
        DPCNLoss(l1_rotation="abc")
    with pytest.raises(ValueError, match=r"loss\.kl_rotation_scale must be a finite number >= 0"):
        DPCNLoss(kl_rotation_scale=float("inf"))
    # a shared weight is named as set, not as the per-term weight it fills in
    with pytest.raises(ValueError, match=r"loss\.kl_weight must be a finite number >= 0, got 'x'"):
        DPCNLoss(kl_weight="x")
    with pytest.raises(ValueError, match=r"loss\.l1_weight must be a finite number >= 0, got nan"):
        DPCNLoss(l1_weight=float("nan"))
    with pytest.raises(ValueError, match=r"loss\.l1_scale must be a finite number >= 0, got -1"):
        DPCNLoss(l1_scale=-1)
    surface = torch.randn(2, 8, 8, dtype=torch.float64)
    centre = torch.tensor([[1.0, 2.0], [5.5, 6.5]], dtype=torch.float64)
    out = DPCNLoss()(surface, centre, surface, centre, torch.tensor([0.1, 0.1], dtype=torch.float64))
    assert set(out.terms) == {"l1_rotation", "l1_scale", "l1_translation", "kl_rotation_scale", "kl_translation"}


def test_gradcheck_losses():
    surface = torch.randn(1, 6, 7, dtype=torch.float64, requires_grad=True)
    temperature = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    centre = torch.tensor([[2.3, 4.1]], dtype=torch.float64)
    assert gradcheck(lambda x, t: one_peak_kl(x, centre, t, 1.0, (True, False)), (surface, temperature))
    assert gradcheck(lambda x, t: torch.stack(expectation_l1(x, centre, t, (True, False))), (surface, temperature))


def test_pose_errors_wrap_the_angle():
    pred = torch.tensor([[1.0, -2.0, 179.0, 1.1], [0.0, 0.0, -170.0, 0.9]])
    truth = torch.tensor([[0.0, 0.0, -179.0, 1.0], [3.0, 4.0, 175.0, 1.0]])
    err = pose_errors(pred, truth)
    torch.testing.assert_close(err.float(), torch.tensor([[1.0, 2.0, 2.0, 0.1], [3.0, 4.0, 15.0, 0.1]]))


def test_summarize_matches_hand_counts(tmp_path):
    errors = torch.tensor([[0.5, 0.5, 0.2, 0.01], [3.0, 6.0, 0.8, 0.05], [10.0, 0.0, 2.0, 0.3]], dtype=torch.float64)
    m = summarize(errors, thresholds_for(5.0))
    assert m["acc_x@5"] == pytest.approx(200 / 3) and m["acc_x@1"] == pytest.approx(100 / 3)
    assert m["acc_y@5"] == pytest.approx(200 / 3)
    assert m["acc_rot@1"] == pytest.approx(200 / 3) and m["acc_rot@0.5"] == pytest.approx(100 / 3)
    assert m["acc_scale@0.2"] == pytest.approx(200 / 3) and m["acc_scale@0.02"] == pytest.approx(100 / 3)
    assert m["mse_x"] == pytest.approx((0.25 + 9 + 100) / 3)
    table = format_table([("dpcn", m)])
    assert "acc_rot@0.5" in table and "dpcn" in table
    path = write_csv(tmp_path / "m.csv", [("dpcn", m)])
    header, row = path.read_text().strip().splitlines()
    assert header.startswith("name,acc_x@5") and row.startswith("dpcn,")
    assert math.isclose(float(row.split(",")[1]), 200 / 3)
    assert np.isclose(summarize(errors, thresholds_for(10.0))["acc_x@10"], 100.0)


def test_accuracy_curve_counts_the_pairs_within_each_threshold(tmp_path):
    rng = np.random.default_rng(0)
    errors = np.abs(rng.normal(0.0, [6.0, 6.0, 0.8, 0.08], size=(200, 4)))
    errors[0] = [5.0, 0.0, 1.0, 0.2]  # on the thresholds: within, as in the tables
    curve = accuracy_curve(torch.from_numpy(errors))
    assert [(name, t) for name, t, _ in curve] == [
        (name, t) for name in CURVE_THRESHOLDS for t in CURVE_THRESHOLDS[name]
    ]
    assert len(CURVE_THRESHOLDS["x"]) == 20 and CURVE_THRESHOLDS["x"][-1] == 19.0  # the paper's Acc at 0-19 px
    for name, limit, acc in curve:
        column = errors[:, ["x", "y", "rot", "scale"].index(name)]
        assert acc == pytest.approx(100.0 * np.count_nonzero(column <= limit) / 200)
    # Every table threshold lies on the curves, with the table's number.
    table = summarize(
        torch.from_numpy(errors), {**thresholds_for(5.0), "aero": {"x": 10, "y": 10, "rot": 1, "scale": 0.2}}
    )
    on_curve = {f"acc_{name}@{limit:g}": acc for name, limit, acc in curve}
    for key, value in table.items():
        if key.startswith("acc_"):
            assert on_curve[key] == pytest.approx(value), key
    path = write_curve_csv(tmp_path / "curves" / "accuracy_test.csv", curve)
    rows = path.read_text().strip().splitlines()
    assert rows[0] == "component,threshold,acc" and len(rows) == 1 + len(curve)
    assert rows[1 + 5].startswith("x,5,") and float(rows[1 + 5].split(",")[2]) == pytest.approx(
        on_curve["acc_x@5"], abs=1e-4
    )
    mine = accuracy_curve(torch.from_numpy(errors), {"rot": [0.25, 3.0]})
    assert [t for _, t, _ in mine] == [0.25, 3.0]
    with pytest.raises(ValueError, match=r"errors must be \(N, 4\) with N >= 1, got \(3, 3\)"):
        accuracy_curve(torch.zeros(3, 3))
    with pytest.raises(ValueError, match=r"errors must be \(N, 4\) with N >= 1, got \(0, 4\)"):
        accuracy_curve(torch.zeros(0, 4))
    with pytest.raises(ValueError, match=r"unknown components \['angle'\]"):
        accuracy_curve(torch.zeros(2, 4), {"angle": [1.0]})
    for limits, shown in [
        ([1.0, float("nan")], "[1.0, nan]"),
        ([-1], "[-1]"),
        (["a"], "['a']"),
        (3, "3"),
        ("12", "'12'"),
    ]:
        with pytest.raises(
            ValueError, match=f"thresholds of rot must be a list of finite numbers >= 0, got {re.escape(shown)}$"
        ):
            accuracy_curve(torch.zeros(2, 4), {"rot": limits})
    # numpy errors too; a failed (NaN) estimate is outside every threshold
    failed = np.array([[0.5, 0.5, 0.1, 0.01], [np.nan, np.nan, np.nan, np.nan]])
    assert [acc for _, _, acc in accuracy_curve(failed, {"x": [1.0, 1e9], "scale": [0.02]})] == [50.0, 50.0, 50.0]


@pytest.mark.parametrize(
    ("choice", "expected"),
    [
        ("default", dict(l1_rotation=0.1, l1_scale=1.0, l1_translation=1.0, kl_rotation_scale=1.0, kl_translation=3.0)),
        ("l1", dict(l1_rotation=0.1, l1_scale=1.0, l1_translation=1.0, kl_rotation_scale=0.0, kl_translation=3.0)),
        ("kl", dict(l1_rotation=0.1, l1_scale=0.0, l1_translation=0.0, kl_rotation_scale=1.0, kl_translation=3.0)),
        ("paper", dict(l1_rotation=0.1, l1_scale=1.0, l1_translation=1.0, kl_rotation_scale=1.0, kl_translation=3.0)),
    ],
)
def test_loss_configs_take_per_term_overrides(choice, expected):
    """Every loss config composes from the real conf/ with per-term weight overrides (no ``+``)."""
    cfg = compose_config(f"loss={choice}", "loss.l1_rotation=0.1", "loss.kl_translation=3")
    loss = DPCNLoss(**instantiate(cfg.loss))
    # the extra alignment term: on in the default loss, off in the paper's losses
    assert loss.weights == pytest.approx(
        {**expected, "kl_align": 1.0 if choice == "default" else 0.0, "kl_half_turn": 0.0}
    )
    assert loss.hard_pair_gamma == 0.0
    tuned = compose_config(f"loss={choice}", "loss.hard_pair_gamma=-0.5")
    assert DPCNLoss(**instantiate(tuned.loss)).hard_pair_gamma == -0.5


def test_alignment_term_is_off_by_default_and_needs_its_surface():
    surface = torch.randn(2, 8, 8, dtype=torch.float64)
    centre = torch.tensor([[1.0, 2.0], [5.5, 6.5]], dtype=torch.float64)
    temperatures = torch.tensor([0.1, 0.1], dtype=torch.float64)
    assert DPCNLoss().weights["kl_align"] == 0.0
    loss = DPCNLoss(kl_align=0.5)
    with pytest.raises(ValueError, match="kl_align > 0 needs the phase-1 alignment surface"):
        loss(surface, centre, surface, centre, temperatures)
    out = loss(surface, centre, surface, centre, temperatures, surface, centre)
    expected = one_peak_kl(surface, centre, 0.1, 1.5, (True, True)).mean()
    torch.testing.assert_close(out.terms["kl_align"], expected)
    without = DPCNLoss()(surface, centre, surface, centre, temperatures)
    torch.testing.assert_close(out.total, without.total + 0.5 * expected)
    with pytest.raises(ValueError, match=r"loss\.kl_align must be a finite number >= 0"):
        DPCNLoss(kl_align=-1.0)


def test_half_turn_term_is_the_one_peak_kl_over_both_surfaces_minus_the_upright_one():
    """Independent reference: one softmax over the two surfaces side by side, the Gaussian
    target on the upright half only."""
    torch.manual_seed(0)
    upright, turned = torch.randn(2, 3, 8, 8, dtype=torch.float64).unbind(0)
    centre = torch.tensor([[1.0, 2.0], [5.5, 6.5], [4.0, 0.5]], dtype=torch.float64)
    t = 0.3
    target = gaussian_target((8, 8), centre, 1.5, (True, True))
    joint_target = torch.cat([target, torch.zeros_like(target)], dim=-1).flatten(1)
    log_p = torch.log_softmax((torch.cat([upright, turned], dim=-1) / t).flatten(1), dim=1)
    joint_kl = (joint_target * (torch.log(joint_target.clamp_min(1e-30)) - log_p)).sum(dim=1)
    upright_kl = one_peak_kl(upright, centre, t, 1.5, (True, True))
    torch.testing.assert_close(half_turn_nll(upright, turned, t), joint_kl - upright_kl)
    # A turned surface far below the upright one costs nothing; far above, its height gap.
    assert half_turn_nll(upright, upright - 100.0, 1.0).max() < 1e-30
    torch.testing.assert_close(half_turn_nll(upright, upright + 50.0, 1.0), torch.full((3,), 50.0, dtype=torch.float64))


def test_gradcheck_half_turn_term():
    torch.manual_seed(0)
    upright, turned = torch.rand(2, 2, 6, 6, dtype=torch.float64).unbind(0)
    temperature = torch.tensor(0.2, dtype=torch.float64)
    inputs = (upright.requires_grad_(), turned.requires_grad_(), temperature.requires_grad_())
    assert gradcheck(half_turn_nll, inputs)


def test_half_turn_term_is_off_by_default_and_needs_its_surface():
    surface = torch.randn(2, 8, 8, dtype=torch.float64)
    centre = torch.tensor([[1.0, 2.0], [5.5, 6.5]], dtype=torch.float64)
    temperatures = torch.tensor([0.1, 0.2], dtype=torch.float64)
    assert DPCNLoss().weights["kl_half_turn"] == 0.0
    loss = DPCNLoss(kl_half_turn=0.5)
    with pytest.raises(ValueError, match="kl_half_turn > 0 needs phase 2's surface for the half-turned source"):
        loss(surface, centre, surface, centre, temperatures)
    turned = surface.flip(-1)
    out = loss(surface, centre, surface, centre, temperatures, None, None, turned)
    expected = half_turn_nll(surface, turned, 0.2).mean()  # phase 2's temperature
    torch.testing.assert_close(out.terms["kl_half_turn"], expected)
    without = DPCNLoss()(surface, centre, surface, centre, temperatures)
    torch.testing.assert_close(out.total, without.total + 0.5 * expected)
    with pytest.raises(ValueError, match=r"loss\.kl_half_turn must be a finite number >= 0"):
        DPCNLoss(kl_half_turn=-1.0)


def test_hard_pair_weighting_weights_phase_1_by_its_one_peak_kl():
    """Independent reference: per-pair phase-1 terms weighted by ``kl ** gamma / mean(kl ** gamma)``
    (``kl`` floored at 0.01);
    phase 2 keeps the plain mean; the weights carry no gradient; gamma 0 is the plain loss."""
    torch.manual_seed(1)
    rs = torch.randn(3, 8, 10, dtype=torch.float64)
    centre = torch.tensor([[2.0, 3.0], [5.5, 6.5], [4.0, 0.5]], dtype=torch.float64)
    # an easy pair: its softmax is the one-peak target itself (KL 0)
    rs[0] = 0.5 * torch.log(gaussian_target((8, 10), centre[:1], 1.5, (True, False))[0])
    t_surface = torch.randn(3, 8, 8, dtype=torch.float64)
    temperatures = torch.tensor([0.5, 0.3], dtype=torch.float64)
    kl = one_peak_kl(rs, centre, 0.5, 1.5, (True, False))
    rot, sc = expectation_l1(rs, centre, 0.5, (True, False))
    plain = DPCNLoss(kl_align=1.0)(rs, centre, t_surface, centre, temperatures, t_surface, centre)
    assert DPCNLoss().hard_pair_gamma == 0.0
    for gamma in (1.0, 2.0, -0.5):
        weight = kl.clamp_min(0.01) ** gamma / (kl.clamp_min(0.01) ** gamma).mean()
        out = DPCNLoss(kl_align=1.0, hard_pair_gamma=gamma)(
            rs, centre, t_surface, centre, temperatures, t_surface, centre
        )
        align = one_peak_kl(t_surface, centre, 0.3, 1.5, (True, True))
        torch.testing.assert_close(out.terms["kl_rotation_scale"], (weight * kl).mean())
        torch.testing.assert_close(out.terms["l1_rotation"], (weight * rot).mean())
        torch.testing.assert_close(out.terms["l1_scale"], (weight * sc).mean())
        torch.testing.assert_close(out.terms["kl_align"], (weight * align).mean())
        torch.testing.assert_close(out.terms["kl_translation"], plain.terms["kl_translation"])
        torch.testing.assert_close(out.terms["l1_translation"], plain.terms["l1_translation"])
        # gamma > 0: the easy pair (smallest KL) counts for less than in the plain mean; < 0: for more
        easiest = weight.argmin() if gamma > 0 else weight.argmax()
        assert easiest == 0
        heavier = out.terms["kl_rotation_scale"] > plain.terms["kl_rotation_scale"]
        assert heavier == (gamma > 0)
    # the weights are constants of the backward pass: the gradient is the weighted one
    surface = rs.clone().requires_grad_()
    DPCNLoss(l1_weight=0.0, kl_translation=0.0, hard_pair_gamma=1.0)(
        surface, centre, t_surface, centre, temperatures
    ).total.backward()
    reference = rs.clone().requires_grad_()
    weight = kl.clamp_min(0.01) / kl.clamp_min(0.01).mean()
    (weight * one_peak_kl(reference, centre, 0.5, 1.5, (True, False))).mean().backward()
    torch.testing.assert_close(surface.grad, reference.grad)
    for bad in (-3.0, 5.0, float("nan"), "x"):
        with pytest.raises(ValueError, match=r"loss\.hard_pair_gamma must be a finite number in \[-2, 4\]"):
            DPCNLoss(hard_pair_gamma=bad)
