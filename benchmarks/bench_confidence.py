"""How well a matcher's confidence ranks its matches: accuracy of its most confident pairs.

A pose's confidence (``Pose.confidence``) is the height of the phase-2 correlation peak that
produced it. A robot that fuses matches (the measurement model of a particle filter, a pose
graph) needs to know whether a low confidence flags a wrong match. This evaluates a
checkpoint (or, without ``--checkpoint``, the classical estimator) on the fixed validation
pairs (held-out regions) and test pairs (held-out scene) of a data config, calls a pair
correct when x and y are within the data's translation threshold and the rotation within 1°,
and prints, for the most confident fractions of the pairs (``--keep``), the confidence at that
cut and the share of those pairs that is correct, then the AUC: the probability that a
correct pair has a higher confidence than a wrong one (ties count half; 0.5 is no ranking).

For a checkpoint it also reads stage 1's own doubt: the second-strongest rotation/scale peak
over the strongest (the ratio that ``DPCN.hypothesis_ratio`` gates on), and prints how many
pairs reach ``--ratio`` (the ambiguous pairs, for which a gated model checks further peaks),
the share of them and of the others that is correct, and the AUC of ``1 - ratio`` as a
confidence.

    python benchmarks/bench_confidence.py --data s2d --checkpoint CKPT [--keep 1,0.9,0.8,0.5] \
        [--ratio 0.7] [--stages validate,test] [-- rotation_views=4 ...]

Everything after ``--`` is a Hydra override of the evaluation config (as for
``python -m dpcn test``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch
from hydra.utils import instantiate

from dpcn.models import DPCN

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_coverage import evaluation_parser, evaluation_setup, matched_batches, parse_stages  # noqa: E402  (the same evaluation set-up)


def ranking_auc(correct: torch.Tensor, confidence: torch.Tensor) -> float:
    """P(confidence of a correct pair > that of a wrong one), ties counted half (the
    Mann-Whitney statistic); NaN without correct or without wrong pairs. ``(N,)`` each."""
    good, bad = confidence[correct].double(), confidence[~correct].double()
    if good.numel() == 0 or bad.numel() == 0:
        return math.nan
    above = (good[:, None] > bad[None, :]).double().mean()
    ties = (good[:, None] == bad[None, :]).double().mean()
    return float(above + 0.5 * ties)


def most_confident(
    correct: torch.Tensor, confidence: torch.Tensor, keep: list[float]
) -> list[tuple[float, int, float, float]]:
    """For each fraction in ``keep``: ``(fraction, pairs kept, lowest confidence kept, % of
    them correct)``, keeping the ``round(fraction * N)`` (at least 1) most confident pairs."""
    order = confidence.argsort(descending=True, stable=True)
    rows = []
    for fraction in keep:
        n = max(1, round(fraction * confidence.numel()))
        kept = order[:n]
        rows.append((fraction, n, float(confidence[kept].min()), 100.0 * float(correct[kept].double().mean())))
    return rows


def stage1_peak_ratio(model: DPCN, template: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
    """``(B,)`` the score of stage 1's second rotation/scale peak over its first's, with the
    model's inference settings (windows, views, radii); 0 where there is no second peak. What
    ``DPCN.hypothesis_ratio`` gates on: near 1, stage 1 cannot tell two poses apart. A stage-1
    pass of its own, beside ``match``'s: a model that checks one peak keeps no second one."""
    device = next(model.parameters()).device
    with torch.no_grad():
        rs, _ = model.rotation_scale(
            template.to(device),
            source.to(device),
            2,
            model.spectrum_window_grid,
            model.rotation_views,
            radii=model.inference_radii,
        )
    first, second = rs.candidate_score[:, 0], rs.candidate_score[:, 1]
    return torch.where(torch.isfinite(second), second / first, torch.zeros_like(first)).cpu()


def split_by_ratio(correct: torch.Tensor, ratio: torch.Tensor, threshold: float) -> tuple[int, float, float, float]:
    """``(ambiguous pairs, their share %, % of them correct, % of the others correct)``, a pair
    being ambiguous when its ``ratio`` reaches ``threshold`` (NaN for an empty group)."""
    ambiguous = ratio >= threshold

    def rate(group: torch.Tensor) -> float:
        return 100.0 * float(correct[group].double().mean()) if bool(group.any()) else math.nan

    return int(ambiguous.sum()), 100.0 * float(ambiguous.double().mean()), rate(ambiguous), rate(~ambiguous)


def _ratio(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"--ratio takes a number in (0, 1], e.g. 0.7; got {text!r}")
    return value


def _fractions(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or any(not 0.0 < v <= 1.0 for v in values):
        raise argparse.ArgumentTypeError(f"--keep takes fractions in (0, 1], e.g. 1,0.9,0.8,0.5; got {text!r}")
    return values


def main(argv: list[str] | None = None) -> None:
    parser = evaluation_parser(__doc__, "data config (l2d, l2sat, s2d, s2sat, sim_...)")
    parser.add_argument("--keep", type=_fractions, default=[1.0, 0.9, 0.8, 0.5], help="fractions kept")
    parser.add_argument("--ratio", type=_ratio, default=0.7, help="stage-1 second/first peak ratio: ambiguous")
    args = parser.parse_args(argv)
    stages = parse_stages(parser, args.stages)

    cfg, matcher, name = evaluation_setup(args.data, args.checkpoint, args.overrides, "bench_confidence")
    datamodule = instantiate(cfg.data)
    threshold = float(cfg.data.translation_threshold)
    print(f"{name} on {args.data}: correct = x and y within {threshold:g} px and rotation within 1 deg")
    print(f"{'pairs':<18} {'kept':>6} {'n':>5} {'confidence >=':>14} {'correct %':>10}")
    for stage in stages:
        label, batches = matched_batches(matcher, datamodule, stage)
        model = getattr(matcher, "model", None)
        errors, confidence, ratio = [], [], []
        for batch, pose, batch_errors in batches:
            errors.append(batch_errors)
            confidence.append(pose.confidence.cpu())
            if isinstance(model, DPCN):
                ratio.append(stage1_peak_ratio(model, batch["template"], batch["source"]))
        errors, confidence = torch.cat(errors), torch.cat(confidence)
        correct = (errors[:, 0] <= threshold) & (errors[:, 1] <= threshold) & (errors[:, 2] <= 1.0)
        for fraction, n, lowest, rate in most_confident(correct, confidence, args.keep):
            print(f"{label:<18} {fraction:>6.0%} {n:>5d} {lowest:>14.4f} {rate:>10.1f}")
        print(f"{label:<18} AUC {ranking_auc(correct, confidence):.3f}")
        if ratio:
            ratio = torch.cat(ratio)
            n, share, ambiguous, clear = split_by_ratio(correct, ratio, args.ratio)
            auc = ranking_auc(correct, 1 - ratio)
            print(
                f"{label:<18} stage 1: {n} ambiguous pairs (second peak >= {args.ratio:g} x first, {share:.1f} %) "
                f"{ambiguous:.1f} % correct, the others {clear:.1f} %; AUC of 1 - ratio {auc:.3f}"
            )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
