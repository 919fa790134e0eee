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
``visible>D|grain>G``
    as ``visible>D``, and the template also shows the boundaries between classes whose
    grain (style A's per-class texture amplitude) differs by more than G: regions of nearly
    one grey level that an extractor could still tell apart by how grainy they are.

With ``--checkpoint`` it also asks which of a trained model's two stage-1 extractors loses
the pairs: stage 1 (rotation modulo 180 degrees) on the learned features of both images, and
on the learned features of one image against the ideal maps of the other (shrunk like the
model's stage-1 input, one copy per feature channel). Then it looks at the pairs stage 1
misses with the model's own inference settings: is the true peak among the ``--peaks``
strongest of the log-polar surface (a wrong choice) or not at all (features that do not
correlate), how strong the peaks are, and how the accuracy depends on the scale, the
translation and the share of the template's boundaries that are visible (style-A contrast
above ``--sides-contrast``).

It swaps the private render functions of :mod:`dpcn.data.simulation` while it runs (the
scene, pose and crop geometry stay the module's own).

    python benchmarks/bench_sim_ceiling.py [--pairs 300] [--contrast 0.02 0.05 0.1] [--grain 0.02] \
        [--no-radius-window] [--checkpoint CKPT [--window-grid 3] [--peaks 5]]
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
def rendering(mode: str, contrast: float = 0.0, grain: float | None = None):
    """Temporarily render the two styles as the feature maps of ``mode`` (``grain``: the
    ``visible`` template also shows boundaries of a texture-amplitude step above it)."""
    render_a, render_b = sim._render_a, sim._render_b

    def template(style, labels, rect):
        if mode == "gradient":
            return _gradient(render_a(style, labels, rect))
        if mode == "all-boundaries":
            return _boundaries(labels.astype(np.float32), 0.5)
        visible = _boundaries(cv2.LUT(labels, sim._lut(style.colour)), contrast)
        if grain is None:
            return visible
        return np.maximum(visible, _boundaries(cv2.LUT(labels, sim._lut(style.texture_amp)), grain))

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


def batches(mode: str, pairs: int, contrast: float = 0.0, batch: int = 10, grain: float | None = None):
    """``(template, source, pose)`` batches of the test pairs rendered as ``mode``.

    Each batch is rendered inside its own :func:`rendering` block, so several of these
    generators can be consumed side by side.
    """
    data = sim.SimulatedPairs(kind="heterogeneous", length=pairs, seed=2, noise=0.0 if mode != "pixels" else 0.02)
    for start in range(0, pairs, batch):
        with rendering(mode, contrast, grain):
            items = [data[i] for i in range(start, min(pairs, start + batch))]
        yield tuple(torch.stack([x[key] for x in items]) for key in ("template", "source", "pose"))


def evaluate(
    mode: str, pairs: int, contrast: float = 0.0, grain: float | None = None, radius_window: bool = True
) -> dict[str, float]:
    """Accuracies (%) of the classical estimator on the pairs rendered as ``mode``."""
    estimator = PhaseCorrelationEstimator(radius_window=radius_window)
    streams = batches(mode, pairs, contrast, grain=grain)
    errors = [pose_errors(estimator(t, s).as_tensor(), gt) for t, s, gt in streams]
    metrics = summarize(torch.cat(errors), thresholds_for(5.0))
    return {column: metrics[key] for column, key in COLUMNS.items()}


def pixels_and_ideal_batches(pairs: int, contrast: float):
    """The test pairs side by side as pixels, every boundary, and the boundaries visible above
    ``contrast``: ``((template, source, pose), (all_t, all_s, pose), (visible_t, visible_s, pose))``."""
    return zip(
        batches("pixels", pairs), batches("all-boundaries", pairs), batches("visible", pairs, contrast), strict=True
    )


@torch.no_grad()
def stage1_sides(model: DPCN, pairs: int, contrast: float) -> dict[str, float]:
    """Stage-1 rotation (mod 180 degrees) Acc@1 of learned vs ideal features, per side."""
    model.eval()

    def ideal(image: torch.Tensor, channels: int) -> torch.Tensor:
        return model.rotation_scale_input(image).repeat(1, channels, 1, 1)

    hits: dict[str, list[torch.Tensor]] = {}
    streams = pixels_and_ideal_batches(pairs, contrast)
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


@torch.no_grad()
def stage1_misses(model: DPCN, pairs: int, peaks: int = 5, contrast: float = 0.05) -> dict[str, float]:
    """Stage 1 with the model's window grid: where its misses (rotation mod 180 off by > 1
    degree) come from. Scores are log-polar correlation peak heights; a template's visible
    share is how much of its region boundaries has a style-A contrast above ``contrast``."""
    model.eval()
    angle_errors, found, first, second, scales, shifts, visible = [], [], [], [], [], [], []
    streams = pixels_and_ideal_batches(pairs, contrast)
    for (template, source, gt), (all_t, _, _), (visible_t, _, _) in streams:
        visible.append(visible_t.flatten(1).sum(dim=1) / all_t.flatten(1).sum(dim=1).clamp_min(1e-6))
        rs, _ = model.rotation_scale(template, source, peaks, model.spectrum_window_grid)
        candidate_errors = wrap_angle(rs.candidate_angle - gt[:, 2:3], period=180.0).abs()
        true_peak = (candidate_errors <= 1.0) & ((rs.candidate_scale / gt[:, 3:4] - 1.0).abs() <= 0.05)
        angle_errors.append(candidate_errors[:, 0])
        found.append(true_peak.any(dim=1))
        first.append(rs.candidate_score[:, 0])
        second.append(rs.candidate_score[:, 1] if peaks > 1 else torch.full_like(rs.candidate_score[:, 0], torch.nan))
        scales.append(gt[:, 3])
        shifts.append(gt[:, :2].norm(dim=1))
    error, found, first, second = torch.cat(angle_errors), torch.cat(found), torch.cat(first), torch.cat(second)
    scale, shift, visible = torch.cat(scales), torch.cat(shifts), torch.cat(visible)
    hit = error <= 1.0

    def acc(mask: torch.Tensor) -> float:
        return 100.0 * float(hit[mask].float().mean()) if mask.any() else float("nan")

    share = f"template boundaries > {contrast:g} visible"
    by_visibility = {
        f"within 1 deg, {share} {label} ({int(mask.sum())} pairs), %": acc(mask)
        for label, mask in (
            ("< 70 %", visible < 0.7),
            ("70-90 %", (visible >= 0.7) & (visible < 0.9)),
            (">= 90 %", visible >= 0.9),
        )
    }
    return {
        "rotation mod 180 within 1 deg, %": acc(torch.ones_like(hit)),
        "misses": float((~hit).sum()),
        f"misses with the true peak among the {peaks} strongest": float((found & ~hit).sum()),
        "median peak score, hits": float(first[hit].median()) if hit.any() else float("nan"),
        "median second peak score, hits": float(second[hit].median()) if hit.any() else float("nan"),
        "median peak score, misses": float(first[~hit].median()) if (~hit).any() else float("nan"),
        "within 1 deg, scale < 0.9, %": acc(scale < 0.9),
        "within 1 deg, scale 0.9-1.1, %": acc((scale >= 0.9) & (scale <= 1.1)),
        "within 1 deg, scale > 1.1, %": acc(scale > 1.1),
        "within 1 deg, |t| < 30 px, %": acc(shift < 30.0),
        "within 1 deg, |t| >= 30 px, %": acc(shift >= 30.0),
        f"median share of {share}, hits": float(visible[hit].median()) if hit.any() else float("nan"),
        f"median share of {share}, misses": float(visible[~hit].median()) if (~hit).any() else float("nan"),
        **by_visibility,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=300)
    parser.add_argument("--contrast", type=float, nargs="*", default=[0.02, 0.05, 0.1])
    parser.add_argument(
        "--grain",
        type=float,
        nargs="*",
        default=[0.02],
        help="also rows whose template shows the boundaries of a grain (texture amplitude) step above G",
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--checkpoint", help="a trained DPCN checkpoint: which stage-1 extractor loses the pairs")
    parser.add_argument(
        "--sides-contrast",
        type=float,
        default=0.05,
        help="template contrast threshold of the per-side check and of the misses by visible boundaries",
    )
    parser.add_argument("--window-grid", type=int, default=None, help="stage-1 window grid (default: the checkpoint's)")
    parser.add_argument("--peaks", type=int, default=5, help="stage-1 peaks searched for the true one in the misses")
    parser.add_argument(
        "--no-radius-window",
        action="store_true",
        help="the classical rows without stage 1's log-radius window (stage 1 as the paper describes it)",
    )
    args = parser.parse_args()
    if args.pairs < 1 or args.threads < 1 or args.peaks < 1:
        parser.error("--pairs, --threads and --peaks must be >= 1")
    if min([*args.contrast, *args.grain, args.sides_contrast]) < 0:
        parser.error("contrasts must be >= 0")
    torch.set_num_threads(args.threads)
    model = None
    if args.checkpoint:  # before the long part: a bad path fails at once
        try:
            model = load_matcher(args.checkpoint, spectrum_window_grid=args.window_grid).model
        except (CheckpointError, ValueError) as error:
            parser.error(str(error))

    runs = [("pixels", 0.0, None), ("gradient", 0.0, None), ("all-boundaries", 0.0, None)]
    runs += [(f"visible>{c:g}", c, None) for c in args.contrast]
    runs += [(f"visible>{c:g}|grain>{g:g}", c, g) for c in args.contrast for g in args.grain]
    window = "without" if args.no_radius_window else "with"
    print(
        f"sim_heterogeneous test pairs (seed 2), first {args.pairs}; "
        f"classical estimator {window} the log-radius window; Acc in %"
    )
    print(("{:<26}" + "{:>8}" * len(COLUMNS)).format("features", *COLUMNS))
    for name, contrast, grain in runs:
        started = time.perf_counter()
        mode = "visible" if name.startswith("visible") else name
        acc = evaluate(mode, args.pairs, contrast, grain, radius_window=not args.no_radius_window)
        row = ("{:<26}" + "{:>8.1f}" * len(COLUMNS)).format(name, *acc.values())
        print(f"{row}   ({time.perf_counter() - started:.0f} s)", flush=True)
    if model is not None:
        print(f"\nstage 1 of {args.checkpoint}, rotation (mod 180 degrees) within 1 degree, %")
        print("template features / source features")
        for name, acc in stage1_sides(model, args.pairs, args.sides_contrast).items():
            print(f"  {name:<32}{acc:>6.1f}")
        grid = model.spectrum_window_grid
        print(f"\nstage-1 misses, learned features, {grid} x {grid} spectrum windows (the model's setting)")
        for name, value in stage1_misses(model, args.pairs, args.peaks, args.sides_contrast).items():
            print(f"  {name:<72}{value:>8.3g}" if "score" in name or "share" in name else f"  {name:<72}{value:>8.1f}")


if __name__ == "__main__":
    main()
