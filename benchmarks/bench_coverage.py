"""Map-pair accuracy by how much of the template crop the ground robot observed.

A ground robot's map covers only what its sensors saw (the ``*_mask`` rasters), so a
template crop can be mostly no-data; the data configs keep crops at least ``data.dataset.min_valid``
observed (0.5). This evaluates a trained checkpoint (or, without ``--checkpoint``, the
classical estimator) on the fixed validation pairs (held-out regions) and test pairs
(held-out scene) of a map data config and prints the paper's accuracies per bin of the
template's observed fraction, so that a held-out scene whose robot saw less can be told
apart from one the model does not generalise to.

    python benchmarks/bench_coverage.py --data s2d --checkpoint CKPT [--bins 0.3 0.45 0.6] \
        [--stages validate,test] [-- data.builtin_scenes=32 rotation_views=4 ...]

Everything after ``--`` is a Hydra override of the evaluation config (as for
``python -m dpcn test``); ``rotation_views=``, ``spectrum_window_grid=`` and
``rotation_hypotheses=`` replace the checkpoint's inference settings.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from hydra.utils import instantiate
from omegaconf.errors import OmegaConfBaseException

from dpcn.cli import inference_settings, one_line
from dpcn.data.aeroground import PAIRS
from dpcn.metrics import pose_errors, summarize, thresholds_for
from dpcn.pose import Pose
from dpcn.training.module import CheckpointError, load_matcher

CONF = Path(__file__).resolve().parents[1] / "conf"
STAGES = {"validate": ("val", "held-out regions"), "test": ("test", "held-out scene")}
OTHER_LABELS = {"validate": "validation pairs", "test": "test pairs"}  # data that is not a map pair


def evaluation_parser(doc: str, data_help: str) -> argparse.ArgumentParser:
    """The evaluation benchmarks' shared arguments: ``--data``, ``--checkpoint``, ``--stages``
    and the Hydra overrides after ``--``; each script adds its own options."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--data", default="s2d", help=data_help)
    parser.add_argument("--checkpoint", help="DPCN checkpoint (default: the classical estimator)")
    parser.add_argument("--stages", default="validate,test")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (after --)")
    return parser


def parse_stages(parser: argparse.ArgumentParser, text: str) -> list[str]:
    """``--stages``' comma-separated keys of :data:`STAGES` (a usage error otherwise)."""
    stages = [s.strip() for s in text.split(",") if s.strip()]
    if not stages or any(s not in STAGES for s in stages):
        parser.error(f"--stages takes validate and/or test, got {text!r}")
    return stages


def evaluation_setup(data: str, checkpoint: str | None, overrides: list[str], prog: str):
    """``(config, matcher, name)`` for evaluating a checkpoint (its inference settings replaced
    by the top-level overrides) or, without one, the classical estimator, on a data config.
    A bad data config or override and a missing or unreadable checkpoint exit with one line
    prefixed by ``prog``."""
    try:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            cfg = compose("config", overrides=[f"data={data}", *overrides])
            if not checkpoint:
                classical = compose("config", overrides=[f"data={data}", "model=classical", *overrides])
                return cfg, instantiate(classical.model, _convert_="all"), "classical"
        matcher = load_matcher(checkpoint, **inference_settings(cfg))
    except (HydraException, OmegaConfBaseException, CheckpointError) as e:
        raise SystemExit(f"{prog}: {one_line(e)}") from None
    return cfg, matcher, f"DPCN ({Path(checkpoint).name})"


def matched_batches(matcher, datamodule, stage: str) -> tuple[str, Iterator[tuple[dict, Pose, torch.Tensor]]]:
    """The label of ``stage`` (a key of :data:`STAGES`) and, batch by batch over its fixed
    pairs, ``(batch, pose, errors)``: the matcher's pose and its ``(B, 4)`` absolute errors
    (``dpcn.metrics.pose_errors``). The benchmarks' shared evaluation loop."""
    split, label = STAGES[stage]
    if getattr(datamodule, "name", None) not in PAIRS:  # regions and scenes are the map pairs' splits
        label = OTHER_LABELS[stage]
    datamodule.setup(stage)
    loader = datamodule.val_dataloader() if split == "val" else datamodule.test_dataloader()

    def batches() -> Iterator[tuple[dict, Pose, torch.Tensor]]:
        for batch in loader:
            with torch.no_grad():  # per call: a generator must not leave autograd off between yields
                try:
                    pose = matcher.match(batch["template"], batch["source"])
                except ValueError as e:  # pairs the matcher refuses, e.g. a checkpoint built for another size
                    raise SystemExit(f"{label}: {one_line(e)}") from None
            yield batch, pose, pose_errors(pose.as_tensor().cpu(), batch["pose"])

    return label, batches()


def _errors_and_coverage(batches) -> tuple[torch.Tensor, torch.Tensor]:
    errors, coverage = [], []
    for batch, _, batch_errors in batches:
        if "template_mask" not in batch:
            raise SystemExit("bench_coverage: this data config has no no-data masks (pick a map pair: l2d, ...)")
        errors.append(batch_errors)
        coverage.append(batch["template_mask"].flatten(1).mean(dim=1).double())
    return torch.cat(errors), torch.cat(coverage)


def main(argv: list[str] | None = None) -> None:
    parser = evaluation_parser(__doc__, "map data config (l2d, l2sat, s2d, s2sat)")
    parser.add_argument("--bins", type=float, nargs="+", default=[0.3, 0.45, 0.6], help="bin edges (fraction)")
    args = parser.parse_args(argv)
    stages = parse_stages(parser, args.stages)
    edges = sorted(set([0.0, *args.bins, 1.0 + 1e-9]))
    if any(not 0.0 <= e <= 1.0 + 1e-9 for e in edges):
        parser.error(f"--bins are fractions in [0, 1], got {args.bins}")

    cfg, matcher, name = evaluation_setup(args.data, args.checkpoint, args.overrides, "bench_coverage")
    datamodule = instantiate(cfg.data)
    limit = float(cfg.data.translation_threshold)
    thresholds = thresholds_for(limit)
    t = f"{limit:g}"
    columns = [(f"x@{t}", f"acc_x@{t}"), (f"y@{t}", f"acc_y@{t}"), ("rot@1", "acc_rot@1"), ("s@0.2", "acc_scale@0.2")]
    print(f"{name} on {args.data}, accuracy (%) by observed fraction of the template crop")
    print(f"{'pairs':<30} {'n':>4} " + " ".join(f"{c:>7}" for c, _ in columns))
    for stage in stages:
        label, batches = matched_batches(matcher, datamodule, stage)
        errors, coverage = _errors_and_coverage(batches)
        rows = [(f"{label}, all", torch.ones_like(coverage, dtype=torch.bool))]
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            rows.append(
                (f"{label}, [{lo:.2f}, {min(hi, 1.0):.2f}{']' if hi > 1 else ')'}", (coverage >= lo) & (coverage < hi))
            )
        for title, selected in rows:
            n = int(selected.sum())
            if n == 0:
                continue
            metrics = summarize(errors[selected], thresholds)
            print(f"{title:<30} {n:>4} " + " ".join(f"{metrics[key]:>7.1f}" for _, key in columns))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
