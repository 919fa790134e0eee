"""What the simulated heterogeneous pairs allow: Fourier-Mellin on ideal feature maps.

A diagnostic for the DPCN sim benchmark. Each test pair of ``sim_heterogeneous`` (seed 2, the
fixed test set) is re-rendered with its own scene and pose, but instead of the two styles'
pixels the images are feature maps a perfect extractor could produce, and the classical
estimator (the same spectrum / log-polar / correlation pipeline DPCN trains through) matches
them:

``pixels``
    the images themselves (the classical row of the README's Table 1).
``gradient``
    gradient magnitude of both images (a hand-crafted feature).
``all-boundaries``
    every region boundary of the label map, in both images: the geometry the two styles share.
``visible>D``
    template: the boundaries whose style-A contrast (difference of the two classes' grey
    levels) exceeds D; source: every boundary (style B emphasises all of them). Separate
    extractors cannot see which boundaries the other image shows, so this is what they can
    at best agree on when boundaries fainter than D are lost in the template's texture.

With ``--checkpoint`` it also asks which of a trained model's two stage-1 extractors loses
the pairs: stage 1 (rotation modulo 180 degrees) on the learned features of both images, and
on the learned features of one image against the ideal maps of the other (shrunk like the
model's stage-1 input, one copy per feature channel).

It swaps the private render functions of :mod:`dpcn.data.simulation` while it runs (the
scene, pose and crop geometry stay the module's own).

    python benchmarks/bench_sim_ceiling.py [--pairs 300] [--contrast 0.02 0.05 0.1] [--checkpoint CKPT]
"""

from __future__ import annotations

import argparse
import contextlib
import time

import cv2
import numpy as np
import torch

import dpcn.data.simulation as sim
from dpcn import PhaseCorrelationEstimator
from dpcn.metrics import pose_errors, summarize, thresholds_for
from dpcn.models import DPCN
from dpcn.pose import wrap_angle
from dpcn.training.module import CheckpointError, load_matcher

_KERNEL = np.ones((3, 3), np.uint8)
# printed column -> key of dpcn.metrics.summarize (the paper's sim thresholds, then the strict ones)
COLUMNS = {
    "x@5": "acc_x@5", "y@5": "acc_y@5", "rot@1": "acc_rot@1", "s@0.2": "acc_scale@0.2",
    "x@1": "acc_x@1", "y@1": "acc_y@1", "rot@0.5": "acc_rot@0.5", "s@0.02": "acc_scale@0.02",
}  # fmt: skip


def _boundaries(values: np.ndarray, threshold: float) -> np.ndarray:
    """(h, w, 1) float32: 1 where the per-pixel class value changes by more than threshold."""
    step = cv2.dilate(values, _KERNEL) - cv2.erode(values, _KERNEL)
    return cv2.GaussianBlur((step > threshold).astype(np.float32), (0, 0), 0.8)[..., None]


def _gradient(image: np.ndarray) -> np.ndarray:
    grey = image if image.ndim == 2 else image[..., 0]
    gy, gx = np.gradient(cv2.GaussianBlur(grey, (0, 0), 1.0))
    return np.hypot(gx, gy).astype(np.float32)[..., None]


@contextlib.contextmanager
def rendering(mode: str, contrast: float = 0.0):
    """Temporarily render the two styles as the feature maps of ``mode``."""
    render_a, render_b = sim._render_a, sim._render_b

    def template(style, labels, rect):
        if mode == "gradient":
            return _gradient(render_a(style, labels, rect))
        if mode == "all-boundaries":
            return _boundaries(labels.astype(np.float32), 0.5)
        return _boundaries(cv2.LUT(labels, sim._lut(style.colour)), contrast)  # visible

    def source(style, labels, rect, canvas):
        if mode == "gradient":
            return _gradient(render_b(style, labels, rect, canvas))
        return _boundaries(labels.astype(np.float32), 0.5)

    if mode != "pixels":
        sim._render_a, sim._render_b = template, source
    try:
        yield
    finally:
        sim._render_a, sim._render_b = render_a, render_b


def batches(mode: str, pairs: int, contrast: float = 0.0, batch: int = 10):
    """``(template, source, pose)`` batches of the test pairs rendered as ``mode``.

    Each batch is rendered inside its own :func:`rendering` block, so several of these
    generators can be consumed side by side.
    """
    data = sim.SimulatedPairs(kind="heterogeneous", length=pairs, seed=2, noise=0.0 if mode != "pixels" else 0.02)
    for start in range(0, pairs, batch):
        with rendering(mode, contrast):
            items = [data[i] for i in range(start, min(pairs, start + batch))]
        yield tuple(torch.stack([x[key] for x in items]) for key in ("template", "source", "pose"))


def evaluate(mode: str, pairs: int, contrast: float = 0.0) -> dict[str, float]:
    """Accuracies (%) of the classical estimator on the pairs rendered as ``mode``."""
    estimator = PhaseCorrelationEstimator()
    errors = [pose_errors(estimator(t, s).as_tensor(), gt) for t, s, gt in batches(mode, pairs, contrast)]
    metrics = summarize(torch.cat(errors), thresholds_for(5.0))
    return {column: metrics[key] for column, key in COLUMNS.items()}


@torch.no_grad()
def stage1_sides(model: DPCN, pairs: int, contrast: float) -> dict[str, float]:
    """Stage-1 rotation (mod 180 degrees) Acc@1 of learned vs ideal features, per side."""
    model.eval()

    def ideal(image: torch.Tensor, channels: int) -> torch.Tensor:
        return model.rotation_scale_input(image).repeat(1, channels, 1, 1)

    hits: dict[str, list[torch.Tensor]] = {}
    streams = zip(
        batches("pixels", pairs), batches("all-boundaries", pairs), batches("visible", pairs, contrast), strict=True
    )
    for (template, source, gt), (all_t, all_s, _), (visible_t, _, _) in streams:
        _, features = model.rotation_scale(template, source)
        learned_t, learned_s = features["rs_template"], features["rs_source"]
        c = learned_t.shape[1]
        combos = {
            "learned / learned": (learned_t, learned_s),
            "learned / all-boundaries": (learned_t, ideal(all_s, c)),
            "all-boundaries / learned": (ideal(all_t, c), learned_s),
            f"visible>{contrast:g} / learned": (ideal(visible_t, c), learned_s),
        }
        for name, (a, b) in combos.items():
            angle = model.rotation_scale_from_features(a, b).angle
            hits.setdefault(name, []).append(wrap_angle(angle - gt[:, 2], period=180.0).abs() <= 1.0)
    return {name: 100.0 * float(torch.cat(h).float().mean()) for name, h in hits.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=300)
    parser.add_argument("--contrast", type=float, nargs="*", default=[0.02, 0.05, 0.1])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--checkpoint", help="a trained DPCN checkpoint: which stage-1 extractor loses the pairs")
    parser.add_argument("--sides-contrast", type=float, default=0.05, help="template threshold of the per-side check")
    args = parser.parse_args()
    if args.pairs < 1 or args.threads < 1:
        parser.error("--pairs and --threads must be >= 1")
    if min([*args.contrast, args.sides_contrast]) < 0:
        parser.error("contrasts must be >= 0")
    torch.set_num_threads(args.threads)
    model = None
    if args.checkpoint:  # before the long part: a bad path fails at once
        try:
            model = load_matcher(args.checkpoint).model
        except CheckpointError as error:
            parser.error(str(error))

    runs = [("pixels", 0.0), ("gradient", 0.0), ("all-boundaries", 0.0)]
    runs += [(f"visible>{c:g}", c) for c in args.contrast]
    print(f"sim_heterogeneous test pairs (seed 2), first {args.pairs}; classical estimator; Acc in %")
    print(("{:<18}" + "{:>8}" * len(COLUMNS)).format("features", *COLUMNS))
    for name, contrast in runs:
        started = time.perf_counter()
        mode = "visible" if name.startswith("visible") else name
        acc = evaluate(mode, args.pairs, contrast)
        row = ("{:<18}" + "{:>8.1f}" * len(COLUMNS)).format(name, *acc.values())
        print(f"{row}   ({time.perf_counter() - started:.0f} s)", flush=True)
    if model is not None:
        print(f"\nstage 1 of {args.checkpoint}, rotation (mod 180 degrees) within 1 degree, %")
        print("template features / source features")
        for name, acc in stage1_sides(model, args.pairs, args.sides_contrast).items():
            print(f"  {name:<32}{acc:>6.1f}")


if __name__ == "__main__":
    main()
