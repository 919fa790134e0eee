"""What the procedural map pairs allow: the classical estimator on ideal feature maps.

A diagnostic for the map-pair benchmark (the map-pair counterpart of ``bench_sim_ceiling.py``).
The procedural scenes are rendered from a known world (:func:`dpcn.data.scene.scene_truth`:
class labels and heights), so every fixed validation pair (held-out regions) and test pair
(held-out scene) of a map data config can be cut again, with the same crops and poses, from
feature maps a perfect extractor could produce, and matched by the classical estimator (the
spectrum / log-polar / correlation pipeline DPCN trains through):

``pixels``
    the rasters themselves (the classical rows of the README's map-pair table).
``elevation``
    template: the world's heights without noise, as the stereo map encodes them (grey 20 =
    ground, 255 = 25 m), where the robot observed and 0 (no data) elsewhere, so the
    no-data shapes stay; source: the same heights everywhere (with the aerial image's cars).
    What an extractor that recovers elevation perfectly on both sides gives.
``boundaries``
    every class boundary of the world's label map (roads, marks, sidewalks, grass, soil,
    buildings, trees, cars), where the robot observed (template) and everywhere (source):
    the geometry the two images share, without the no-data shapes. A LiDAR intensity map
    shows these boundaries (reflectance differs by class); an elevation map only those of:
``objects``
    what stands metres above the ground (buildings, trees, cars), outlined as ``boundaries``;
``raised``
    and the sidewalks too: the outline of everything at least a kerb (0.15 m) above the
    road, every height step of the world.

With ``--checkpoint`` it also asks which of a trained model's two stage-1 extractors loses
the pairs: stage 1 (rotation modulo 180 degrees, one centred spectrum window) on the learned
features of both images, and on the learned features of one image against the ideal maps of
the other (one copy per feature channel).

The ideal rasters are written next to links to the real ones in a temporary folder, so the
pairs come from the data config's own sampler (``data.root=`` that folder) and are the same
pairs; the scenes must be :func:`dpcn.data.scene.make_dataset`'s (the built-in ones, or a
``data.root`` written by ``python -m dpcn make-data`` with ``--dataset-seed``), which is
checked by rendering each scene's template modality again.

    python benchmarks/bench_map_ceiling.py --data s2d [--checkpoint CKPT] [--stages validate,test] \
        [-- data.builtin_scenes=8 ...]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from hydra.utils import instantiate

from dpcn.data.aeroground import PAIRS, DataError, _find_image, read_image
from dpcn.data.maps import builtin_root
from dpcn.data.scene import (
    BUILDING,
    CAR,
    SIDEWALK,
    STEREO_GROUND,
    STEREO_MAX_M,
    TREE,
    generate_scene,
    scene_index,
    scene_seed,
    scene_truth,
)
from dpcn.metrics import summarize, thresholds_for
from dpcn.pose import wrap_angle

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_coverage import evaluation_parser, evaluation_setup, matched_batches, parse_stages  # noqa: E402  (the same evaluation set-up)

MODES = ("elevation", "boundaries", "objects", "raised")
_KERNEL = np.ones((3, 3), np.uint8)


def elevation_grey(height: np.ndarray) -> np.ndarray:
    """(H, W) uint8: heights in metres as the stereo map encodes them (no noise, no holes)."""
    grey = STEREO_GROUND + np.clip(height, 0.0, STEREO_MAX_M) * ((255.0 - STEREO_GROUND) / STEREO_MAX_M)
    return np.round(grey).astype(np.uint8)


def boundaries(labels: np.ndarray) -> np.ndarray:
    """(H, W) uint8: 255 on every class boundary of ``labels`` (2-3 px wide), 0 elsewhere."""
    changes = cv2.dilate(labels, _KERNEL) != cv2.erode(labels, _KERNEL)
    return changes.astype(np.uint8) * 255


def ideal_maps(mode: str, truth: dict[str, np.ndarray], source_modality: str) -> tuple[np.ndarray, np.ndarray]:
    """``(template, source)`` full-scene uint8 rasters of ``mode`` (before the template's mask)."""
    suffix = "_satellite" if source_modality == "satellite" else ""
    if mode == "elevation":
        return elevation_grey(truth["height"]), elevation_grey(truth["height" + suffix])
    if mode == "boundaries":
        return boundaries(truth["labels"]), boundaries(truth["labels" + suffix])
    if mode in ("objects", "raised"):
        classes = (BUILDING, TREE, CAR) + ((SIDEWALK,) if mode == "raised" else ())
        above = [np.isin(truth[key], classes).astype(np.uint8) for key in ("labels", "labels" + suffix)]
        return boundaries(above[0]), boundaries(above[1])
    raise ValueError(f"unknown mode {mode!r}; modes: {', '.join(MODES)}")


def _modality_file(folder: Path, stem: str) -> Path | None:
    """The raster ``folder/stem.<ext>`` as the map reader finds it, or ``None``."""
    found = _find_image(folder, stem)
    return found[0] if found else None


def write_ideal_roots(root: Path, pair: str, out: Path, dataset_seed: int = 0) -> dict[str, Path]:
    """For each mode, ``out/<mode>/<scene>/``: links to every file of ``root/<scene>/`` but the
    pair's two rasters, which are the mode's ideal maps (the template's zero where its mask says
    no data). Returns ``{mode: root}``. Raises ``SystemExit`` naming a scene that
    :func:`dpcn.data.scene.make_dataset` with ``dataset_seed`` did not write."""
    template_modality, source_modality = PAIRS[pair]
    scenes = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith((".", "_")))
    roots = {mode: out / mode for mode in MODES}
    for folder in scenes:
        template_file = _modality_file(folder, template_modality)
        if template_file is None or _modality_file(folder, source_modality) is None:
            continue  # the pair's sampler skips or names it
        try:
            seed = scene_seed(dataset_seed, scene_index(folder.name))
        except ValueError as error:
            raise SystemExit(f"bench_map_ceiling: {error}: procedural scenes only") from None
        rendered, _ = read_image(template_file)
        size = rendered.shape[:2]
        if not np.array_equal(generate_scene(seed, size)[template_modality], rendered):
            raise SystemExit(
                f"bench_map_ceiling: {template_file} is not scene {folder.name} of make_dataset(seed={dataset_seed}) "
                "(--dataset-seed?): procedural scenes only"
            )
        mask_file = _modality_file(folder, f"{template_modality}_mask")
        observed = read_image(mask_file)[0] > 0 if mask_file is not None else np.ones(size, bool)
        truth = scene_truth(seed, size)
        for mode, mode_root in roots.items():
            target = mode_root / folder.name
            target.mkdir(parents=True)
            for file in folder.iterdir():
                if file.stem not in (template_modality, source_modality):
                    (target / file.name).symlink_to(file.resolve())
            template, source = ideal_maps(mode, truth, source_modality)
            cv2.imwrite(str(target / f"{template_modality}.png"), np.where(observed, template, 0).astype(np.uint8))
            cv2.imwrite(str(target / f"{source_modality}.png"), source)
    return roots


def classical_accuracy(data: str, overrides: list[str], stage: str, columns: dict[str, str]) -> dict[str, float]:
    """The classical estimator's accuracies (%) on a stage's fixed pairs."""
    cfg, matcher, _ = evaluation_setup(data, None, overrides, "bench_map_ceiling")
    _, batches = matched_batches(matcher, instantiate(cfg.data), stage)
    errors = torch.cat([batch_errors for _, _, batch_errors in batches])
    metrics = summarize(errors, thresholds_for(float(cfg.data.translation_threshold)))
    return {column: metrics[key] for column, key in columns.items()}


def _with_root(overrides: list[str], root: Path | None) -> list[str]:
    """``overrides`` reading the pairs from ``root`` (``None``: as given)."""
    if root is None:
        return overrides
    return [o for o in overrides if not o.startswith(("data.root=", "+data.root="))] + [f"data.root={root}"]


def _loader(data: str, overrides: list[str], stage: str):
    cfg, _, _ = evaluation_setup(data, None, overrides, "bench_map_ceiling")
    datamodule = instantiate(cfg.data)
    datamodule.setup(stage)
    return datamodule.val_dataloader() if stage == "validate" else datamodule.test_dataloader()


@torch.no_grad()
def stage1_sides(model, data: str, overrides: list[str], roots: dict[str, Path], stage: str) -> dict[str, float]:
    """Stage-1 rotation (mod 180 degrees) within 1 degree (%), learned against ideal features per side."""
    model.eval()
    streams = [_loader(data, overrides, stage)] + [
        _loader(data, _with_root(overrides, root), stage) for root in roots.values()
    ]
    hits: dict[str, list[torch.Tensor]] = {}
    for batch, *ideal in zip(*streams, strict=True):
        gt = batch["pose"]
        model.check_inputs(batch["template"], batch["source"])  # a size the model was not built for: its own error
        _, features = model.rotation_scale(batch["template"], batch["source"])
        learned_t, learned_s = features["rs_template"], features["rs_source"]
        channels = learned_t.shape[1]

        def as_features(image: torch.Tensor, c: int = channels) -> torch.Tensor:
            return model.rotation_scale_input(image.mean(dim=1, keepdim=True)).repeat(1, c, 1, 1)

        combos = {"learned / learned": (learned_t, learned_s)}
        for mode, items in zip(roots, ideal, strict=True):
            if not torch.equal(items["pose"], gt):
                raise RuntimeError("the ideal pairs are not the real ones (poses differ)")
            combos[f"learned / {mode}"] = (learned_t, as_features(items["source"]))
            combos[f"{mode} / learned"] = (as_features(items["template"]), learned_s)
        for name, (template_features, source_features) in combos.items():
            angle = model.rotation_scale_from_features(template_features, source_features).angle
            hits.setdefault(name, []).append(wrap_angle(angle - gt[:, 2], period=180.0).abs() <= 1.0)
    return {name: 100.0 * float(torch.cat(h).float().mean()) for name, h in hits.items()}


def main(argv: list[str] | None = None) -> None:
    parser = evaluation_parser(__doc__, "map data config (l2d, l2sat, s2d, s2sat)")
    parser.add_argument("--dataset-seed", type=int, default=0, help="make_dataset's seed of data.root (built-in: 0)")
    args = parser.parse_args(argv)
    stages = parse_stages(parser, args.stages)
    if args.data not in PAIRS:
        parser.error(f"--data takes a map pair ({', '.join(PAIRS)}), got {args.data!r}")
    cfg, matcher, _ = evaluation_setup(args.data, args.checkpoint, args.overrides, "bench_map_ceiling")
    root = Path(cfg.data.root) if cfg.data.root else builtin_root(n_scenes=int(cfg.data.builtin_scenes))
    if not root.is_dir():
        parser.error(f"data.root {root} does not exist or is not a folder")
    t = f"{float(cfg.data.translation_threshold):g}"
    columns = {
        f"x@{t}": f"acc_x@{t}", f"y@{t}": f"acc_y@{t}", "rot@1": "acc_rot@1", "s@0.2": "acc_scale@0.2",
        "x@1": "acc_x@1", "y@1": "acc_y@1", "rot@0.5": "acc_rot@0.5", "s@0.02": "acc_scale@0.02",
    }  # fmt: skip
    labels = {"validate": "held-out regions", "test": "held-out scene"}
    try:
        if args.checkpoint:  # before the long part: pairs of a size the model was not built for
            blank = torch.zeros(1, int(cfg.channels), int(cfg.image_size), int(cfg.image_size))
            matcher.model.check_inputs(blank, blank)
        with tempfile.TemporaryDirectory(prefix="dpcn-ceiling-") as tmp:
            started = time.perf_counter()
            roots = write_ideal_roots(root, args.data, Path(tmp), args.dataset_seed)
            print(f"{args.data}: ideal maps of {root} written in {time.perf_counter() - started:.0f} s")
            print(f"classical estimator, Acc in %\n{'pairs, features':<30}" + "".join(f"{c:>8}" for c in columns))
            for stage in stages:
                for mode, mode_root in [("pixels", None), *roots.items()]:
                    acc = classical_accuracy(args.data, _with_root(args.overrides, mode_root), stage, columns)
                    row = "".join(f"{v:>8.1f}" for v in acc.values())
                    print(f"{labels[stage] + ', ' + mode:<30}{row}", flush=True)
            if args.checkpoint:
                model = matcher.model
                print(f"\nstage 1 of {args.checkpoint}: rotation (mod 180 degrees) within 1 degree, %, centred window")
                print("template features / source features")
                for stage in stages:
                    for name, acc in stage1_sides(model, args.data, args.overrides, roots, stage).items():
                        print(f"  {labels[stage] + ', ' + name:<46}{acc:>6.1f}", flush=True)
    except (DataError, ValueError) as error:  # bad data or sizes: one line, as the CLI's
        raise SystemExit(f"bench_map_ceiling: {error}") from None
    sys.stdout.flush()


if __name__ == "__main__":
    main()
