"""Inference speed of DPCN (tiny and paper presets) and of the classical estimator.

256x256 single-channel pairs, end to end (all four U-Nets, both phases, the half-turn check),
no ground truth. Reports the latency of one pair (batch 1) and the throughput of batches, as
the median of several timed rounds after a warm-up. Each round times every model once, in
turn, so a slow spell of a shared machine falls on all of them alike and the ratios between
rows hold even when the absolute numbers drift. Weights are random unless --ckpt is given:
the cost does not depend on them, except that of a gated hypothesis check (`tiny`'s default:
a second stage-1 peak for the pairs whose second peak reaches 0.7 of the first), which depends
on the pairs and weights. Noise pairs are all ambiguous, so the default rows are its worst case;
--ckpt with --pairs times real pairs (the 1-pair column: their mean, matched one at a time).

    python benchmarks/bench_inference.py [--device cpu|cuda] [--threads 2] [--batch 32] [--ckpt last.ckpt]
        [--window-grids 1,3] [--hypotheses 1,3] [--views 1,2,8]   # also time other stage-1 inference settings
        [--hypothesis-ratios 0,0.7] [--pairs heterogeneous]      # gated hypotheses: their cost depends on the pairs
        [--radii 128,256]                                         # DPCN.inference_radii
        [--unet-dtype bfloat16]                                   # DPCN.unet_dtype
        [--compile [BACKEND]]                                     # torch.compile the U-Nets (default inductor)
        [--rotation-range 0,180]                                  # also with DPCN.rotation_range (one phase-2 pass)
        [--half-turn-passes winner,every]                         # DPCN.half_turn_pass
        [--one-template]                                          # also one template against the batch's sources
        [--chunks 2,4,8]                                          # DPCN.match's chunk_size (CPU default 4)

With --one-template every model also matches the batch's first template against all its sources in
one call (a robot's map against aerial crops at many particle poses: DPCN runs the template's
U-Nets once), timed in the same rounds as the batch of distinct pairs.

With --compile each DPCN's four U-Nets go through ``torch.compile`` (``nn.Module.compile``;
the rest of the pipeline stays eager). The warm-up call of each timed call compiles it; a
batch of a shape not seen before (a gated hypothesis check's share of the batch) compiles
again within the timed rounds, so read such rows with --hypotheses 1 or --pairs left out.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import torch
from omegaconf import OmegaConf

from dpcn import PhaseCorrelationEstimator
from dpcn.data.simulation import SIM_KINDS, SimulatedPairs
from dpcn.models import DPCN
from dpcn.models.dpcn import PHASE_UNETS, UNET_DTYPES

CONF = Path(__file__).resolve().parents[1] / "conf" / "model"
TIMED_SETTINGS = (  # the preset's architecture and its cost-bearing inference settings
    "feature_channels",
    "base_channels",
    "depth",
    "norm",
    "input_skip",
    "upsample",
    "rotation_scale_downsample",
    "rotation_scale_pooling",
    "rotation_scale_base_channels",
    "rotation_scale_depth",
    "rotation_scale_template_channels",
    "n_angles",
    "n_radii",
    "highpass",
    "log_spectrum",
    "rotation_hypotheses",
    "hypothesis_ratio",
    "spectrum_window_grid",
    "spectrum_window_step",
    "rotation_views",
    "inference_radii",
    "template_relief",
    "half_turn_pass",
)


def preset(name: str) -> dict:
    """The architecture and inference settings of ``conf/model/<name>.yaml`` (so the benchmark
    times what ``fit`` trains and ``test`` runs)."""
    net = OmegaConf.load(CONF / f"{name}.yaml").net
    return {key: net[key] for key in TIMED_SETTINGS if key in net}


def timed_in_turn(
    calls: dict[str, Callable[[], object]], device: str, rounds: int, warmup: int = 3
) -> dict[str, float]:
    """Median seconds of each call over ``rounds`` rounds, each of which runs every call once
    in turn, after ``warmup`` untimed runs of each."""
    for call in calls.values():
        for _ in range(warmup):
            call()
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)  # GPU work is asynchronous
    times: dict[str, list[float]] = {label: [] for label in calls}
    for _ in range(rounds):
        for label, call in calls.items():
            sync()
            start = time.perf_counter()
            call()
            sync()
            times[label].append(time.perf_counter() - start)
    return {label: statistics.median(values) for label, values in times.items()}


def one_at_a_time(run: Callable[[int, int], None], n: int) -> Callable[[], None]:
    """A call that runs ``run(start, stop)`` on pairs ``0 .. n - 1`` one at a time."""

    def stream() -> None:
        for index in range(n):
            run(index, index + 1)

    return stream


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def float_pair(text: str) -> tuple[float, float]:
    """``"0,180"`` -> ``(0.0, 180.0)`` (an argparse type)."""
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH, got {text!r}") from None
    return low, high


def float_list(text: str) -> list[float]:
    """argparse type: comma-separated numbers (each setting's own check comes later)."""
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def int_list(text: str) -> list[int]:
    """argparse type: comma-separated integers (each setting's own check comes later)."""
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def positive_int_list(text: str) -> list[int]:
    """argparse type: comma-separated integers >= 1."""
    return [positive_int(v) for v in text.split(",")]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=positive_int, default=2)
    parser.add_argument("--batch", type=positive_int, default=32)
    parser.add_argument("--size", type=positive_int, default=256)
    parser.add_argument("--rounds", type=positive_int, default=10)
    parser.add_argument("--presets", default="tiny,paper")
    parser.add_argument("--ckpt", default=None, help="time this checkpoint instead of randomly initialised presets")
    parser.add_argument(
        "--hypotheses", type=int_list, default=None, help="comma-separated rotation_hypotheses values to time"
    )
    parser.add_argument(
        "--hypothesis-ratios", type=float_list, default=None, help="comma-separated hypothesis_ratio values to time"
    )
    parser.add_argument(
        "--pairs",
        choices=SIM_KINDS,
        default=None,
        help="time the first --batch simulated test pairs of this kind instead of noise: the cost of "
        "hypothesis_ratio depends on the pairs (and, with --ckpt, on trained weights); the 1-pair column "
        "is then the mean over those pairs, matched one at a time",
    )
    parser.add_argument(
        "--window-grids", type=int_list, default=None, help="comma-separated spectrum_window_grid values to time"
    )
    parser.add_argument("--views", type=int_list, default=None, help="comma-separated rotation_views values to time")
    parser.add_argument("--radii", type=int_list, default=None, help="comma-separated inference_radii values to time")
    parser.add_argument(
        "--rotation-range",
        type=float_pair,
        default=None,
        help="LOW,HIGH degrees: also time each DPCN with this rotation_range (<= 180 wide: one phase-2 pass)",
    )
    parser.add_argument(
        "--half-turn-passes",
        type=lambda text: text.split(","),
        default=None,
        help="comma-separated half_turn_pass values to time (winner: the turned source's U-Net pass only for a "
        "turned winner; every: for every candidate)",
    )
    parser.add_argument(
        "--one-template",
        action="store_true",
        help="also time one template against the --batch sources in one call (its U-Nets run once)",
    )
    parser.add_argument(
        "--chunks",
        type=positive_int_list,
        default=None,
        help="comma-separated chunk_size values of DPCN.match to time (pairs per forward pass; default: 4 on CPUs)",
    )
    parser.add_argument("--bf16", action="store_true", help="autocast the U-Nets to bfloat16 (GPU)")
    parser.add_argument("--unet-dtype", choices=UNET_DTYPES, default=None, help="DPCN.unet_dtype of the timed models")
    parser.add_argument(
        "--compile",
        nargs="?",
        const="inductor",
        default=None,
        metavar="BACKEND",
        help="torch.compile the four U-Nets of each DPCN with this backend (default: inductor)",
    )
    args = parser.parse_args(argv)
    unknown = [name for name in args.presets.split(",") if not (CONF / f"{name}.yaml").is_file()]
    if unknown and not args.ckpt:
        known = ", ".join(sorted(p.stem for p in CONF.glob("*.yaml") if p.stem != "classical"))
        parser.error(f"--presets: no model config {', '.join(unknown)} (conf/model has {known})")
    if args.compile is not None and args.compile not in torch.compiler.list_backends(exclude_tags=()):
        parser.error(f"--compile: {args.compile!r} is not a torch.compile backend (torch.compiler.list_backends())")
    torch.set_num_threads(args.threads)
    device = args.device
    name = torch.cuda.get_device_name() if device.startswith("cuda") else f"CPU, {args.threads} threads"
    print(f"{args.size}x{args.size} pairs, device {device} ({name}), torch {torch.__version__}")

    models: dict[str, torch.nn.Module] = {}
    if args.ckpt:
        from dpcn.training import CheckpointError, load_matcher

        try:
            models[f"DPCN {args.ckpt}"] = load_matcher(args.ckpt).model
        except CheckpointError as error:
            parser.error(str(error))
    else:
        for name in args.presets.split(","):
            models[f"DPCN {name}"] = DPCN(image_size=(args.size, args.size), **preset(name))
    for option, values, short in (
        ("spectrum_window_grid", args.window_grids, "grid"),
        ("rotation_hypotheses", args.hypotheses, "K"),
        ("hypothesis_ratio", args.hypothesis_ratios, "ratio"),
        ("rotation_views", args.views, "views"),
        ("inference_radii", args.radii, "radii"),
        ("rotation_range", args.rotation_range and [None, args.rotation_range], "range"),
        ("half_turn_pass", args.half_turn_passes, "half-turn pass"),
    ):
        if values:  # one copy per value, same weights
            for label, model in list(models.items()):
                del models[label]
                for value in values:
                    models[f"{label}, {short}={value}"] = variant = copy.deepcopy(model)
                    try:
                        setattr(variant, option, value)  # DPCN's setters validate
                    except ValueError as error:
                        parser.error(str(error))
    if args.unet_dtype:
        for label in list(models):
            models[label].unet_dtype = args.unet_dtype
            models[f"{label}, {args.unet_dtype} U-Nets"] = models.pop(label)
    if args.compile:
        for label in list(models):
            for unet in (n for names in PHASE_UNETS.values() for n in names):
                getattr(models[label], unet).compile(backend=args.compile)
            models[f"{label}, compiled ({args.compile})"] = models.pop(label)
    chunk_sizes: dict[str, int] = {}  # label -> DPCN.match's chunk_size (absent: its default)
    for label in list(models) if args.chunks else []:
        model = models.pop(label)
        for chunk in args.chunks:  # the same model under each chunk size
            models[f"{label}, chunk={chunk}"] = model
            chunk_sizes[f"{label}, chunk={chunk}"] = chunk
    models["classical (no U-Nets)"] = PhaseCorrelationEstimator()

    if args.pairs:  # the test split of the sim data configs (seed 2)
        data = SimulatedPairs(args.pairs, length=args.batch, size=args.size, seed=2)
        items = [data[i] for i in range(args.batch)]
        pairs = torch.stack([torch.stack([item[side] for item in items]) for side in ("template", "source")])
    else:
        pairs = torch.rand(2, args.batch, 1, args.size, args.size, generator=torch.Generator().manual_seed(0))
    pairs = pairs.to(device)
    for model in models.values():
        try:
            model.check_inputs(pairs[0, :1], pairs[1, :1])  # e.g. a checkpoint built for another --size
        except ValueError as error:
            parser.error(str(error))

    def run(
        model: torch.nn.Module, start: int, stop: int, one_template: bool = False, chunk: int | None = None
    ) -> None:
        # DPCN.match: what users call (batches chunked on CPUs); the classical estimator has
        # no chunking.
        infer = getattr(model, "match", model)
        templates = pairs[0, start : start + 1] if one_template else pairs[0, start:stop]
        chunking = {} if chunk is None else {"chunk_size": chunk}
        with torch.inference_mode(), torch.autocast(device.split(":")[0], torch.bfloat16, enabled=args.bf16):
            infer(templates, pairs[1, start:stop], **chunking)

    models = {label: model.to(device).eval() for label, model in models.items()}
    if args.pairs:  # each pair's cost depends on the pair (the gate): the mean over a stream of them
        one = timed_in_turn(
            {
                label: one_at_a_time(partial(run, model, chunk=chunk_sizes.get(label)), args.batch)
                for label, model in models.items()
            },
            device,
            args.rounds,
        )
        one = {label: seconds / args.batch for label, seconds in one.items()}
    else:
        one = timed_in_turn(
            {label: partial(run, model, 0, 1, chunk=chunk_sizes.get(label)) for label, model in models.items()},
            device,
            args.rounds,
        )
    batched = {
        label: partial(run, model, 0, args.batch, chunk=chunk_sizes.get(label)) for label, model in models.items()
    }
    if args.one_template:
        for label, model in models.items():
            batched[f"{label}, one template"] = partial(run, model, 0, args.batch, True, chunk_sizes.get(label))
    many = timed_in_turn(batched, device, max(3, args.rounds // 3))
    width = max(34, *(len(label) for label in models))
    shared = f" {'one template (ms/source)':>25s}" if args.one_template else ""
    print(
        f"{'model':{width}s} {'params':>9s} {'1 pair (ms)':>12s} {f'batch {args.batch} (ms/pair)':>20s} {'pairs/s':>9s}"
        + shared
    )
    for label, model in models.items():
        params = sum(p.numel() for p in model.parameters())
        per_pair = many[label] / args.batch
        row = f"{label:{width}s} {params:9d} {1000 * one[label]:12.1f} {1000 * per_pair:20.2f} {1 / per_pair:9.0f}"
        if args.one_template:
            row += f" {1000 * many[f'{label}, one template'] / args.batch:25.2f}"
        print(row)


if __name__ == "__main__":
    main()
