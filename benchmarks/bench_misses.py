"""Where a matcher's rotation misses lie; phase 2 of one checkpoint on phase 1 of another.

Phase 1 finds the angle modulo half a turn and phase 2's half-turn check settles which of the
two turns it is (the stronger translation peak). This evaluates a checkpoint (or, without
``--checkpoint``, the classical estimator) on the fixed validation pairs (held-out regions)
and test pairs (held-out scene) of a data config, and splits the pairs that miss the 1°
rotation threshold into half-turns (error at least 175°: the check chose the wrong turn),
near misses (1–5°) and wrong peaks (5–175°: phase 1 failed), and counts the pairs found
within 1° whose translation still misses (x or y beyond the data's threshold), beside the
paper's accuracies (%). For a checkpoint, ``turn|truth`` counts the pairs whose half-turn
check picks the wrong turn even when the source is un-warped by the true angle and scale:
half-turns that phase 2's features cannot settle, whatever phase 1 does (``of them h-t``:
how many of those the matcher did turn the wrong way).

``--phase2-from CKPT2`` replaces the checkpoint's phase-2 U-Nets (``t_template``,
``t_source``) by CKPT2's before evaluating: two phase-2 trainings compared on the same
phase 1, which run-to-run spread of whole trainings cannot show.

``--shared-with CKPT2`` also evaluates CKPT2 (e.g. another seed) on the same pairs and counts
the rotation misses the two share: misses that are mostly the same pairs point at those pairs
(the data), not at the draw of one training.

    python benchmarks/bench_misses.py --data s2d --checkpoint CKPT [--phase2-from CKPT2] \
        [--shared-with CKPT2] [--stages validate,test] [-- rotation_views=4 ...]

Everything after ``--`` is a Hydra override of the evaluation config (as for
``python -m dpcn test``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from hydra.utils import instantiate

from dpcn.estimator import unwarp_rotation_scale
from dpcn.metrics import summarize, thresholds_for
from dpcn.models.dpcn import PHASE_UNETS
from dpcn.training.module import CheckpointError, load_matcher

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_coverage import evaluation_parser, evaluation_setup, matched_batches, parse_stages  # noqa: E402  (the same evaluation set-up)

HALF_TURN = 175.0  # degrees: an error this large is the other turn, not a wrong peak
NEAR = 5.0


def miss_counts(errors: torch.Tensor, translation_threshold: float) -> dict[str, int]:
    """Counts over ``(N, 4)`` absolute errors ``(x, y, angle, scale)`` (pixels, degrees)."""
    rot = errors[:, 2]
    found = rot <= 1.0
    xy_miss = (errors[:, 0] > translation_threshold) | (errors[:, 1] > translation_threshold)
    return {
        "n": int(errors.shape[0]),
        "rot>1": int((~found).sum()),
        "half-turn": int((rot >= HALF_TURN).sum()),
        "1-5": int(((rot > 1.0) & (rot <= NEAR)).sum()),
        "5-175": int(((rot > NEAR) & (rot < HALF_TURN)).sum()),
        "xy miss|rot ok": int((found & xy_miss).sum()),
    }


def wrong_turn_at_truth(model, template: torch.Tensor, source: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool: the half-turned source's phase-2 peak is at least as strong as the
    upright one's when ``source`` is un-warped by the true angle and scale of ``pose``
    (``(B, 4)``: tx, ty, angle in degrees, scale), i.e. the half-turn check would fail
    even with a perfect phase 1."""
    angle, scale = pose[:, 2].to(source.dtype), pose[:, 3].to(source.dtype)
    with torch.no_grad():
        unwarped = unwarp_rotation_scale(source, angle, scale)
        (upright, turned), _, _ = model.translation_turns(template, unwarped, angle, scale, sigma=model.inference_sigma)
    return turned.confidence >= upright.confidence


def _swap_phase2(matcher, donor_path: str, target_path: str) -> None:
    donor = load_matcher(donor_path)
    for name in PHASE_UNETS["translation"]:
        try:
            getattr(matcher.model, name).load_state_dict(getattr(donor.model, name).state_dict())
        except RuntimeError as error:
            first = str(error).strip().splitlines()[0]
            raise SystemExit(f"bench_misses: phase 2 of {donor_path} does not fit {target_path}: {first}") from None


def main(argv: list[str] | None = None) -> None:
    parser = evaluation_parser(__doc__, "data config (l2d, l2sat, s2d, s2sat, sim_...)")
    parser.add_argument("--phase2-from", help="take the phase-2 U-Nets from this checkpoint")
    parser.add_argument("--shared-with", help="count the rotation misses shared with this checkpoint's")
    args = parser.parse_args(argv)
    stages = parse_stages(parser, args.stages)
    if args.phase2_from and not args.checkpoint:
        parser.error("--phase2-from needs --checkpoint (the classical estimator has no phase-2 U-Nets)")

    cfg, matcher, name = evaluation_setup(args.data, args.checkpoint, args.overrides, "bench_misses")
    if args.phase2_from:
        try:
            _swap_phase2(matcher, args.phase2_from, args.checkpoint)
        except CheckpointError as e:
            raise SystemExit(f"bench_misses: {e}") from None
        name += f", phase 2 of {Path(args.phase2_from).name}"
    other = None
    if args.shared_with:
        other = evaluation_setup(args.data, args.shared_with, args.overrides, "bench_misses")[1]
    datamodule = instantiate(cfg.data)
    threshold = float(cfg.data.translation_threshold)
    print(f"{name} on {args.data}: rotation misses (error > 1 deg) by size; translation misses (> {threshold:g} px)")
    columns = ["n", "rot>1", "half-turn", "1-5", "5-175", "xy miss|rot ok", "turn|truth", "of them h-t"]
    t = f"{threshold:g}"
    accuracies = [
        (f"x@{t}", f"acc_x@{t}"),
        (f"y@{t}", f"acc_y@{t}"),
        ("rot@1", "acc_rot@1"),
        ("s@0.2", "acc_scale@0.2"),
    ]
    header = " ".join(f"{c:>14}" for c in columns) + " " + " ".join(f"{c:>7}" for c, _ in accuracies)
    print(f"{'pairs':<18} {header}")
    for stage in stages:
        label, batches = matched_batches(matcher, datamodule, stage)
        errors, wrong_at_truth = [], []
        for batch, _, batch_errors in batches:
            errors.append(batch_errors)
            if args.checkpoint:
                model = matcher.model.eval()
                wrong_at_truth.append(wrong_turn_at_truth(model, batch["template"], batch["source"], batch["pose"]))
        errors = torch.cat(errors)
        counts, metrics = miss_counts(errors, threshold), summarize(errors, thresholds_for(threshold))
        if wrong_at_truth:
            wrong = torch.cat(wrong_at_truth).cpu()
            counts["turn|truth"] = int(wrong.sum())
            counts["of them h-t"] = int((wrong & (errors[:, 2] >= HALF_TURN)).sum())
        else:  # the classical estimator's turn check is not phase 2's
            counts["turn|truth"] = counts["of them h-t"] = "-"
        cells = (
            " ".join(f"{counts[c]:>14}" for c in columns) + " " + " ".join(f"{metrics[k]:>7.1f}" for _, k in accuracies)
        )
        print(f"{label:<18} {cells}")
        if other is not None:
            _, other_batches = matched_batches(other, datamodule, stage)
            other_missed = torch.cat([e for _, _, e in other_batches])[:, 2] > 1.0
            shared = int((other_missed & (errors[:, 2] > 1.0)).sum())
            other_name = Path(args.shared_with).name
            print(f"{'':<18} rotation misses shared with {other_name}: {shared} (it misses {int(other_missed.sum())})")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
