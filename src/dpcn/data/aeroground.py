"""Readers for Aero-Ground style map pairs: big co-registered rasters or pre-cut CSV pairs.

Folder layout read by :class:`MapPairs` (bring your own maps this way)::

    ROOT/
      <scene>/                       one folder per scene (names starting with "." or "_"
                                     are ignored)
        lidar.<ext>                  ground-robot LiDAR intensity map (template)
        stereo.<ext>                 ground-robot stereo elevation map (template)
        drone.<ext>                  drone orthomosaic (source)
        satellite.<ext>              satellite image (source)
        <modality>_mask.<ext>        optional no-data mask, nonzero = valid; an alpha
                                     channel of the raster (0 = no data) and non-finite
                                     float pixels mark no data too; without any of them
                                     every pixel is valid (only the template modality's
                                     mask file is used; it gives template_mask)
        regions.json                 optional: {"train": [[x0, y0, x1, y1], ...],
                                                "val": [...], "test": [...]}

* ``<ext>`` is one of png, jpg, jpeg, tif, tiff (exactly one file per modality). Only the
  two modalities of the requested pair must exist, in every scene used (pass ``scenes=``
  to leave some out).
* All rasters of a scene are co-registered: same pixel grid, same size (H, W), any of
  grey, RGB or RGBA. 8-bit and 16-bit integers are scaled by their range to [0, 1];
  other integer and floating-point rasters (e.g. elevation GeoTIFFs) are min-max
  normalised over their finite pixels unless already within [0, 1] (NaN/inf count as no
  data). **No-data pixels read as 0**, whatever the raster holds under them: the built-in
  maps store 0 there, and ``dpcn.load_image`` (``predict``) reads a single crop the same way.
* ``regions.json`` rectangles are pixel coordinates ``x0 <= x < x1``, ``y0 <= y < y1``
  bounding the crop *centres* of a split. A missing file means the whole raster is one
  region used for every split; a scene whose file lacks the requested split (or lists
  no rectangle for it) is not used for that split. The crop and the source footprint
  always stay inside the raster, so centres keep a pose-dependent margin from the border
  (e.g. ~315 px for 256 px crops, +-50 px, any rotation, scale >= 0.8); crops near a
  split line reach into the neighbouring rectangle.

Pairs (template modality, source modality): see :data:`PAIRS`.

Pre-cut pairs (:class:`CsvPairs`), as in the original DPCN release::

    DIR/pairs.csv        header: name, rotation, shift_x, shift_y[, scale]
    DIR/template/<name>.<ext>
    DIR/source/<name>.<ext>

Every item is a dict ``{"template": (C, H, W), "source": (C, H, W), "pose": (4,) =
(tx, ty, angle, scale), "template_mask": (1, H, W)}`` of float32 tensors, images and mask
in [0, 1], with the pose in the convention of :mod:`dpcn.pose`::

    M = cv2.getRotationMatrix2D((W / 2, H / 2), angle, scale); M[:, 2] += (tx, ty)
    source == cv2.warpAffine(template_as_seen_by_the_source_modality, M, (W, H))

All problems with the data raise :class:`DataError` (a ``ValueError``), at construction
time where possible.
"""

from __future__ import annotations

import csv
import functools
import json
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from dpcn.io import DpcnInputError, zero_no_data
from dpcn.io import read_image as _io_read_image
from dpcn.pose import pose_to_matrix, sample_poses

__all__ = ["DataError", "PAIRS", "IMAGE_EXTENSIONS", "MapPairs", "CsvPairs", "read_image"]

PAIRS: dict[str, tuple[str, str]] = {
    "l2d": ("lidar", "drone"),
    "l2sat": ("lidar", "satellite"),
    "s2d": ("stereo", "drone"),
    "s2sat": ("stereo", "satellite"),
}
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


class DataError(ValueError):
    """Bad or missing data on disk (message names the file, scene or row)."""


# --------------------------------------------------------------------------------------
# image reading


def read_image(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`dpcn.io.read_image` (the one decoder of the project: no-data pixels read as 0),
    raising :class:`DataError`: ``(image, valid)`` with ``image`` (H, W) or (H, W, 3) RGB of
    dtype uint8, uint16 or float32 in [0, 1], and ``valid`` a bool mask or None."""
    try:
        return _io_read_image(path)
    except DpcnInputError as e:
        raise DataError(str(e)) from None


@functools.lru_cache(maxsize=256)
def _cached(path: str, mtime_ns: int, size: int) -> tuple[np.ndarray, np.ndarray | None]:
    image, valid = read_image(path)
    image.setflags(write=False)
    if valid is not None:
        valid.setflags(write=False)
    return image, valid


def _crop_counts(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Observed pixels of every ``size`` crop of a bool ``mask``: ``(Hb - h + 1, Wb - w + 1)``
    int64, entry ``[oy, ox]`` for the crop whose top-left pixel is ``(ox, oy)``."""
    h, w = size
    total = cv2.integral(mask.astype(np.uint8), sdepth=cv2.CV_64F).astype(np.int64)
    return total[h:, w:] - total[:-h, w:] - total[h:, :-w] + total[:-h, :-w]


def _load(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-process cached :func:`read_image`."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise DataError(f"cannot read image file {path}: {e}") from e
    return _cached(str(Path(path).resolve()), st.st_mtime_ns, st.st_size)


def _scale_of(dtype: np.dtype) -> float:
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    return 1.0


def _to_tensor(image: np.ndarray, channels: int) -> torch.Tensor:
    """(H, W[, 3]) native dtype -> float32 (C, H, W) in [0, 1]."""
    scale = _scale_of(image.dtype)
    img = image.astype(np.float32) / scale
    if channels == 1:
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        img = img[None]
    else:
        img = np.repeat(img[None], 3, axis=0) if img.ndim == 2 else img.transpose(2, 0, 1)
    return torch.from_numpy(np.clip(np.ascontiguousarray(img), 0.0, 1.0))


def _find_image(folder: Path, stem: str) -> list[Path]:
    found = []
    for ext in IMAGE_EXTENSIONS:
        for e in {ext, ext.upper()}:
            p = folder / f"{stem}{e}"
            if p.is_file() and p not in found:
                found.append(p)
    return found


def _check_size(size: int | Sequence[int] | None, what: str = "size") -> tuple[int, int] | None:
    if size is None:
        return None
    if isinstance(size, (int, np.integer)):
        size = (int(size), int(size))
    size = tuple(int(s) for s in size)
    if len(size) != 2 or min(size) < 1:
        raise ValueError(f"{what} must be a positive int or (H, W), got {size}")
    return size  # type: ignore[return-value]


def _check_channels(channels: int) -> int:
    if channels not in (1, 3):
        raise ValueError(f"channels must be 1 (grey) or 3 (RGB), got {channels}")
    return int(channels)


# --------------------------------------------------------------------------------------
# MapPairs


@dataclass
class _Scene:
    name: str
    template_path: Path
    source_path: Path
    mask_path: Path | None
    shape: tuple[int, int]  # (H, W)


def _footprint(matrix: np.ndarray, size: tuple[int, int]) -> tuple[float, float, float, float]:
    """Extent (x_lo, x_hi, y_lo, y_hi), relative to the crop's top-left pixel, of the template
    crop and of the source footprint (where the source samples the template frame)."""
    h, w = size
    inv = cv2.invertAffineTransform(matrix)
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], np.float64)
    p = corners @ inv.T
    return (
        min(0.0, p[:, 0].min()),
        max(w - 1.0, p[:, 0].max()),
        min(0.0, p[:, 1].min()),
        max(h - 1.0, p[:, 1].max()),
    )


def _pose_matrix(tx: float, ty: float, angle: float, scale: float, size: tuple[int, int]) -> np.ndarray:
    m = pose_to_matrix(*(torch.tensor([v], dtype=torch.float64) for v in (tx, ty, angle, scale)), size=size)
    return m[0].numpy()


class MapPairs(Dataset):
    """Random (template, source, pose) crops from co-registered big maps (layout: module doc).

    Each item is a pure function of ``(seed, epoch, index)``: a scene and a rectangle of
    the split are drawn (weighted by usable area), a pose is drawn with
    :func:`dpcn.pose.sample_poses`, then a crop centre inside the rectangle such that the
    template crop and the source footprint lie inside the raster. The template is the
    ``size`` crop of the template modality; the source is the source modality warped
    directly from the big raster with the crop offset composed into the pose matrix, so
    that ``source == cv2.warpAffine(crop_of_source_modality, M(pose), (W, H))`` exactly and
    without an empty border. With a no-data mask, every template crop is at least
    ``min_valid`` observed: the offset is drawn up to ``max_tries`` times, and if none of
    those qualifies, uniformly among the offsets that do (found exactly from the mask's
    integral image, once per scene and process), so sparse scenes are not filled with
    mostly empty crops; only if no offset of the rectangle qualifies for the pose is the
    most observed crop used, with a warning naming the scene (once per scene and dataset
    object).

    Args:
        root: data root (see the module docstring for the layout).
        pair: one of :data:`PAIRS` (``l2d``, ``l2sat``, ``s2d``, ``s2sat``).
        split: name of the regions to draw centres from (``train``, ``val``, ``test``...).
        scenes: scene folder names to use (default: all scene folders of ``root``).
        exclude_scenes: scene folder names to leave out of ``scenes`` (e.g. the test scenes,
            so that ``scenes=None`` trains on every other scene); each must exist.
        length: number of items per epoch.
        size: crop size, int or ``(H, W)``.
        seed: base seed.
        translation, rotation, scale: pose ranges as in :func:`dpcn.pose.sample_poses`.
        channels: 1 (grey; colour maps are converted) or 3 (RGB; grey maps replicated).
        min_valid: minimum valid (mask) fraction of the template crop.
        max_tries: random offset draws per item before the exact draw among the qualifying
            ones (either way the crops meet ``min_valid``; the draws keep the items of
            earlier releases).
    """

    def __init__(
        self,
        root: str | Path,
        pair: str = "l2sat",
        split: str = "train",
        scenes: list[str] | None = None,
        exclude_scenes: list[str] | None = None,
        length: int = 1000,
        size: int | tuple[int, int] = 256,
        seed: int = 0,
        translation: float | tuple[float, float] = 50.0,
        rotation: tuple[float, float] = (-180.0, 180.0),
        scale: tuple[float, float] = (0.8, 1.2),
        channels: int = 1,
        min_valid: float = 0.5,
        max_tries: int = 20,
    ) -> None:
        if pair not in PAIRS:
            raise DataError(
                f"unknown pair {pair!r}; valid pairs: " + ", ".join(f"{k} ({a} -> {b})" for k, (a, b) in PAIRS.items())
            )
        self.size = _check_size(size)
        self.channels = _check_channels(channels)
        if int(length) < 1:
            raise ValueError(f"length must be >= 1, got {length}")
        if not 0.0 <= float(min_valid) <= 1.0:
            raise ValueError(f"min_valid must be in [0, 1], got {min_valid}")
        if int(max_tries) < 1:
            raise ValueError(f"max_tries must be >= 1, got {max_tries}")
        # Validate the pose ranges once (raises ValueError on bad ranges).
        sample_poses(1, torch.Generator().manual_seed(0), translation, rotation, scale)
        self.root = Path(root)
        self.pair = pair
        self.split = split
        self.length = int(length)
        self.seed = int(seed)
        self.translation = translation
        self.rotation = (float(rotation[0]), float(rotation[1]))
        self.scale = (float(scale[0]), float(scale[1]))
        self.min_valid = float(min_valid)
        self.max_tries = int(max_tries)
        self.epoch = 0
        self._warned: set[str] = set()
        self._qualifying: dict[int, np.ndarray] = {}  # scene index -> offsets meeting min_valid

        self.template_modality, self.source_modality = PAIRS[pair]
        names = self._scene_names(scenes, exclude_scenes)
        margin = self._worst_extent()
        self.scenes: list[_Scene] = []
        # (scene index, centre rectangle x0, y0, x1, y1)
        self._rects: list[tuple[int, tuple[float, float, float, float]]] = []
        weights = []
        seen_splits: set[str] = set()
        for name in names:
            scene = self._load_scene(name)
            regions = self._regions(scene, seen_splits)
            if not regions:
                continue
            k = len(self.scenes)
            self.scenes.append(scene)
            for rect in regions:
                weights.append(float(self._feasible(scene, rect, margin)))
                self._rects.append((k, rect))
        if not self._rects:
            raise DataError(
                f"no scene of {self.root} has regions for split {split!r} "
                f"(splits found in regions.json files: {sorted(seen_splits) or 'none'})"
            )
        w = np.asarray(weights, np.float64)
        self._weights = w / w.sum()

    # ---- construction helpers

    def _scene_names(self, scenes: list[str] | None, exclude: list[str] | None = None) -> list[str]:
        if not self.root.is_dir():
            raise DataError(f"data root {self.root} does not exist or is not a folder")
        available = sorted(p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith((".", "_")))
        if not available:
            raise DataError(
                f"no scene folders in {self.root} (expected {self.root}/<scene>/"
                f"{{lidar,stereo,drone,satellite}}.png ...)"
            )

        def known(names: list[str] | str, what: str) -> list[str]:
            names = [names] if isinstance(names, str) else list(names)
            unknown = [s for s in names if s not in available]
            if unknown:
                raise DataError(f"unknown scene(s) {unknown} in {what} for {self.root}; available: {available}")
            return names

        chosen = available if scenes is None else known(scenes, "scenes")
        if scenes is not None and not chosen:
            raise DataError("scenes is an empty list")
        if exclude:
            # the map data configs fill exclude_scenes from data.test_scenes: name both
            left_out = set(known(exclude, "exclude_scenes (data.test_scenes in the map data configs)"))
            kept = [s for s in chosen if s not in left_out]
            if not kept:
                raise DataError(
                    f"no scene left for split {self.split!r}: all of {chosen} in {self.root} are "
                    f"excluded (exclude_scenes={sorted(left_out)})"
                )
            chosen = kept
        return chosen

    def _modality_file(self, folder: Path, modality: str, required: bool = True) -> Path | None:
        found = _find_image(folder, modality)
        if len(found) > 1:
            raise DataError(
                f"scene {folder.name!r}: several files for {modality!r}: {[p.name for p in found]}; keep exactly one"
            )
        if not found:
            if not required:
                return None
            expected = ", ".join(f"{modality}{e}" for e in IMAGE_EXTENSIONS)
            raise DataError(
                f"scene {folder.name!r} ({folder}) has no {modality} raster needed "
                f"by pair {self.pair!r}: expected one of {expected}"
            )
        return found[0]

    def _load_scene(self, name: str) -> _Scene:
        folder = self.root / name
        tpath = self._modality_file(folder, self.template_modality)
        spath = self._modality_file(folder, self.source_modality)
        mpath = self._modality_file(folder, f"{self.template_modality}_mask", required=False)
        timg, _ = _load(tpath)
        simg, _ = _load(spath)
        if timg.shape[:2] != simg.shape[:2]:
            raise DataError(
                f"scene {name!r}: rasters differ in size: {tpath.name} is "
                f"{timg.shape[1]}x{timg.shape[0]} (WxH), {spath.name} is "
                f"{simg.shape[1]}x{simg.shape[0]}; they must be co-registered"
            )
        if mpath is not None:
            mimg, _ = _load(mpath)
            if mimg.shape[:2] != timg.shape[:2]:
                raise DataError(
                    f"scene {name!r}: mask {mpath.name} is {mimg.shape[1]}x"
                    f"{mimg.shape[0]} (WxH) but {tpath.name} is {timg.shape[1]}x"
                    f"{timg.shape[0]}"
                )
        return _Scene(name, tpath, spath, mpath, (int(timg.shape[0]), int(timg.shape[1])))

    def _regions(self, scene: _Scene, seen: set[str]) -> list[tuple[float, float, float, float]]:
        h, w = scene.shape
        path = self.root / scene.name / "regions.json"
        if not path.is_file():
            return [(0.0, 0.0, float(w), float(h))]
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DataError(f"cannot parse {path}: {e}") from e
        if not isinstance(data, dict):
            raise DataError(f'{path}: expected an object {{"train": [[x0, y0, x1, y1], ...], ...}}')
        seen.update(data)
        rects = data.get(self.split) or []
        if not isinstance(rects, list):
            raise DataError(f"{path}: {self.split!r} must be a list of [x0, y0, x1, y1]")
        out = []
        for i, r in enumerate(rects):
            ok = (
                isinstance(r, (list, tuple))
                and len(r) == 4
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in r)
            )
            if not ok:
                raise DataError(f"{path}: {self.split}[{i}] = {r!r} is not [x0, y0, x1, y1]")
            x0, y0, x1, y1 = (float(v) for v in r)
            if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
                raise DataError(
                    f"{path}: {self.split}[{i}] = {r} is outside the {w}x{h} (WxH) "
                    f"raster or empty (need 0 <= x0 < x1 <= {w}, 0 <= y0 < y1 <= {h})"
                )
            out.append((x0, y0, x1, y1))
        return out

    def _worst_extent(self) -> tuple[float, float, float, float]:
        """Worst-case crop + footprint extent over the pose ranges (relative to the crop's
        top-left pixel): extremes lie at translation and scale corners; angles sampled."""
        t = self.translation
        t_lo, t_hi = (-t, t) if isinstance(t, (int, float)) else (float(t[0]), float(t[1]))
        a_lo, a_hi = self.rotation
        angles = np.unique(np.concatenate([np.arange(a_lo, a_hi, 0.25), [a_lo, a_hi]]))
        h, w = self.size
        ext = [0.0, w - 1.0, 0.0, h - 1.0]
        corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64)
        c = np.array([w / 2.0, h / 2.0])
        for s in self.scale:
            for tx in (t_lo, t_hi):
                for ty in (t_lo, t_hi):
                    th = np.deg2rad(angles)[:, None]
                    # inverse map: p = R(-angle) (q - c - t) / s + c, R as in pose_to_matrix
                    qx, qy = corners[:, 0] - c[0] - tx, corners[:, 1] - c[1] - ty
                    px = (np.cos(th) * qx - np.sin(th) * qy) / s + c[0]
                    py = (np.sin(th) * qx + np.cos(th) * qy) / s + c[1]
                    ext = [
                        min(ext[0], px.min()),
                        max(ext[1], px.max()),
                        min(ext[2], py.min()),
                        max(ext[3], py.max()),
                    ]
        return ext[0] - 0.5, ext[1] + 0.5, ext[2] - 0.5, ext[3] + 0.5

    def _feasible(self, scene: _Scene, rect, margin) -> int:
        """Number of integer crop offsets usable in ``rect`` for every pose of the ranges
        (raises if none)."""
        hb, wb = scene.shape
        h, w = self.size
        x0, y0, x1, y1 = rect
        # centre = offset + (w / 2, h / 2) in [x0, x1); offset + lo >= 0; offset + hi <= size - 1
        ox_lo, ox_hi = (
            max(math.ceil(x0 - w / 2), math.ceil(-margin[0])),
            min(math.ceil(x1 - w / 2) - 1, math.floor(wb - 1 - margin[1])),
        )
        oy_lo, oy_hi = (
            max(math.ceil(y0 - h / 2), math.ceil(-margin[2])),
            min(math.ceil(y1 - h / 2) - 1, math.floor(hb - 1 - margin[3])),
        )
        if ox_hi < ox_lo or oy_hi < oy_lo:
            need_w = margin[1] - margin[0] + 1
            need_h = margin[3] - margin[2] + 1
            shown = [int(v) if v == int(v) else v for v in rect]
            raise DataError(
                f"scene {scene.name!r}: {self.split} region {shown}"
                f" is too small or too close to the border of the {wb}x{hb} (WxH) raster for "
                f"{w}x{h} crops with translation={self.translation}, rotation={self.rotation}, "
                f"scale={self.scale}: crop plus source footprint span up to {need_w:.0f}x"
                f"{need_h:.0f} px, so crop centres must lie in x in [{-margin[0] + w / 2:.0f}, "
                f"{wb - 1 - margin[1] + w / 2:.0f}], y in [{-margin[2] + h / 2:.0f}, "
                f"{hb - 1 - margin[3] + h / 2:.0f}]; use a bigger region or raster, a smaller "
                f"crop or narrower pose ranges"
            )
        return (ox_hi - ox_lo + 1) * (oy_hi - oy_lo + 1)

    # ---- dataset protocol

    def set_epoch(self, epoch: int) -> None:
        """Items of a new epoch are drawn afresh (still a pure function of seed, epoch, index)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if index < 0:
            index += self.length
        if not 0 <= index < self.length:
            raise IndexError(f"index {index} out of range for MapPairs of length {self.length}")
        rng = np.random.default_rng([self.seed & 0xFFFFFFFFFFFFFFFF, self.epoch & 0xFFFFFFFFFFFFFFFF, int(index)])
        k = int(rng.choice(len(self._rects), p=self._weights))
        scene_idx, (cx0, cy0, cx1, cy1) = self._rects[k]
        scene = self.scenes[scene_idx]
        gen = torch.Generator().manual_seed(int(rng.integers(0, 2**62)))
        pose = sample_poses(1, gen, self.translation, self.rotation, self.scale, dtype=torch.float64)
        tx, ty, angle, sc = (float(v[0]) for v in (pose.tx, pose.ty, pose.angle, pose.scale))
        h, w = self.size
        hb, wb = scene.shape
        matrix = _pose_matrix(tx, ty, angle, sc, (h, w))
        lo_x, hi_x, lo_y, hi_y = _footprint(matrix, (h, w))
        # Integer crop offsets o with centre o + (w/2, h/2) in the rectangle and the crop and
        # footprint inside the raster.
        ox_lo = max(math.ceil(cx0 - w / 2.0), math.ceil(-lo_x - 1e-6))
        ox_hi = min(math.ceil(cx1 - w / 2.0) - 1, math.floor(wb - 1 - hi_x + 1e-6))
        oy_lo = max(math.ceil(cy0 - h / 2.0), math.ceil(-lo_y - 1e-6))
        oy_hi = min(math.ceil(cy1 - h / 2.0) - 1, math.floor(hb - 1 - hi_y + 1e-6))
        if ox_hi < ox_lo or oy_hi < oy_lo:  # cannot happen: rectangles were checked
            raise DataError(f"scene {scene.name!r}: no room for pose {(tx, ty, angle, sc)}")

        timg, _ = _load(scene.template_path)
        mask = self._template_mask(scene)
        for _ in range(1 if mask is None else self.max_tries):
            ox = int(rng.integers(ox_lo, ox_hi + 1))
            oy = int(rng.integers(oy_lo, oy_hi + 1))
            if mask is None or mask[oy : oy + h, ox : ox + w].mean() >= self.min_valid:
                break
        else:  # no draw qualified: pick among the offsets that do
            box = self._qualifying_offsets(scene_idx, mask)[oy_lo : oy_hi + 1, ox_lo : ox_hi + 1]
            hits = np.flatnonzero(box)
            if hits.size:
                i = int(hits[rng.integers(hits.size)])
                oy, ox = oy_lo + i // box.shape[1], ox_lo + i % box.shape[1]
            else:
                counts = _crop_counts(mask, (h, w))[oy_lo : oy_hi + 1, ox_lo : ox_hi + 1]
                i = int(np.argmax(counts))
                oy, ox = oy_lo + i // box.shape[1], ox_lo + i % box.shape[1]
                if scene.name not in self._warned:
                    self._warned.add(scene.name)
                    frac = float(counts.flat[i]) / (h * w)
                    warnings.warn(
                        f"MapPairs: scene {scene.name!r} ({self.template_modality}, split {self.split!r}):"
                        f" no template crop with valid fraction >= min_valid={self.min_valid} in region"
                        f" {[round(v) for v in (cx0, cy0, cx1, cy1)]} for this pose; using the most"
                        f" observed one ({frac:.2f})",
                        stacklevel=2,
                    )

        template = timg[oy : oy + h, ox : ox + w]
        if mask is None:
            tmask = np.ones((h, w), np.float32)
        else:  # what the mask file hides reads as 0 too, like an alpha channel's no data
            observed = mask[oy : oy + h, ox : ox + w]
            template = zero_no_data(template, observed)
            tmask = observed.astype(np.float32)

        simg, _ = _load(scene.source_path)
        # Warp only the part of the big raster the footprint touches (cv2 maps are limited
        # to 32767 px): source(q) = S_big(M^-1 q + o) = S_sub(M^-1 q + o - b).
        bx0, by0 = max(0, int(math.floor(ox + lo_x)) - 1), max(0, int(math.floor(oy + lo_y)) - 1)
        bx1 = min(wb, int(math.ceil(ox + hi_x)) + 2)
        by1 = min(hb, int(math.ceil(oy + hi_y)) + 2)
        sub = simg[by0:by1, bx0:bx1]
        m_big = matrix.copy()
        m_big[:, 2] -= matrix[:, :2] @ np.array([ox - bx0, oy - by0], np.float64)
        source = cv2.warpAffine(
            sub,
            m_big,
            (w, h),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        return {
            "template": _to_tensor(template, self.channels),
            "source": _to_tensor(source, self.channels),
            "pose": torch.tensor([tx, ty, angle, sc], dtype=torch.float32),
            "template_mask": torch.from_numpy(tmask)[None],
        }

    def _template_mask(self, scene: _Scene) -> np.ndarray | None:
        """The template's observed pixels (mask file and/or alpha channel), or ``None``."""
        _, mask = _load(scene.template_path)
        if scene.mask_path is not None:
            mimg, _ = _load(scene.mask_path)
            observed = (mimg > 0) if mimg.ndim == 2 else (mimg > 0).any(-1)
            mask = observed if mask is None else observed & mask
        return mask

    def _qualifying_offsets(self, scene_idx: int, mask: np.ndarray) -> np.ndarray:
        """``(Hb - h + 1, Wb - w + 1)`` bool: crop offsets ``(oy, ox)`` whose template crop is
        at least ``min_valid`` observed (cached per scene)."""
        if scene_idx not in self._qualifying:
            h, w = self.size
            self._qualifying[scene_idx] = _crop_counts(mask, (h, w)) >= self.min_valid * h * w
        return self._qualifying[scene_idx]

    def __repr__(self) -> str:
        return (
            f"MapPairs(root={str(self.root)!r}, pair={self.pair!r}, split={self.split!r}, "
            f"scenes={[s.name for s in self.scenes]}, length={self.length}, size={self.size})"
        )


# --------------------------------------------------------------------------------------
# CsvPairs


class CsvPairs(Dataset):
    """Pre-cut (template, source) pairs listed in a CSV, as in the original DPCN release.

    Layout::

        <dir>/<file>.csv       header: name, rotation, shift_x, shift_y[, scale]
        <dir>/template/<name>.<ext>   (or template_dir/<name>.<ext>)
        <dir>/source/<name>.<ext>     (or source_dir/<name>.<ext>)

    ``<dir>`` is the CSV's folder, ``<ext>`` one of png, jpg, jpeg, tif, tiff (``name`` may
    also carry its extension). Column names are matched case-insensitively, surrounding
    spaces ignored; extra columns are ignored; ``scale`` defaults to 1.

    **Convention assumption:** ``rotation`` (degrees), ``shift_x``, ``shift_y`` (pixels) and
    ``scale`` are taken *directly* as this project's ``angle``, ``tx``, ``ty``, ``scale``
    (:mod:`dpcn.pose`): ``source == cv2.warpAffine(template, M, (W, H))`` with
    ``M = cv2.getRotationMatrix2D((W / 2, H / 2), rotation, scale)``, ``M[:, 2] +=
    (shift_x, shift_y)``. CSVs written in another convention (other sign, rotation about
    another centre, source -> template direction, radians...) must be converted first.

    If ``size`` is given and an image pair has another size, both images are resized to
    ``size`` with ``cv2.resize`` (INTER_AREA when shrinking, INTER_LINEAR otherwise) and
    the translation is rescaled so the pose stays exact for the resized images:
    ``t' = f * t + (I - scale * R(angle)) d`` with ``f`` the resize factor and
    ``d = ((f - 1) / 2, (f - 1) / 2)`` (the half-pixel shift of OpenCV's pixel-centre
    mapping); angle and scale are unchanged. The resize must keep the aspect ratio.
    Template and source of a row must have the same size.

    With ``poses=False`` the CSV needs only the ``name`` column (pairs whose pose is unknown,
    e.g. for ``python -m dpcn predict pairs=...``); items then have no ``"pose"``.
    """

    REQUIRED = ("name", "rotation", "shift_x", "shift_y")

    def __init__(
        self,
        csv_path: str | Path,
        template_dir: str | Path | None = None,
        source_dir: str | Path | None = None,
        size: int | tuple[int, int] | None = None,
        channels: int = 1,
        poses: bool = True,
    ) -> None:
        self.csv_path = Path(csv_path)
        self.poses = bool(poses)
        required = self.REQUIRED if self.poses else ("name",)
        expected = f"{', '.join(required)}[, scale]" if self.poses else "name"
        self.size = _check_size(size)
        self.channels = _check_channels(channels)
        if not self.csv_path.is_file():
            raise DataError(f"CSV file {self.csv_path} does not exist")
        base = self.csv_path.parent
        self.template_dir = Path(template_dir) if template_dir is not None else base / "template"
        self.source_dir = Path(source_dir) if source_dir is not None else base / "source"
        for d, what in ((self.template_dir, "template"), (self.source_dir, "source")):
            if not d.is_dir():
                raise DataError(f"{what} image folder {d} (for {self.csv_path}) does not exist")
        self.rows: list[dict] = []
        try:
            with open(self.csv_path, newline="", encoding="utf-8-sig") as f:
                reader = csv.reader(f)
                header = next(reader, None)
                if header is None:
                    raise DataError(f"{self.csv_path}: empty file (expected a header {expected})")
                cols = [c.strip().lower() for c in header]
                missing = [c for c in required if c not in cols]
                if missing:
                    raise DataError(
                        f"{self.csv_path}: missing column(s) {missing}; header is {header}; expected {expected}"
                    )
                wanted = (*self.REQUIRED, "scale") if self.poses else ("name",)
                idx = {c: cols.index(c) for c in wanted if c in cols}
                row_no = 0
                for row in reader:
                    if not row or all(not v.strip() for v in row):
                        continue
                    row_no += 1
                    where = f"{self.csv_path}: row {row_no} (line {reader.line_num})"
                    self.rows.append(self._parse_row(row, idx, where))
        except UnicodeDecodeError as e:
            raise DataError(f"{self.csv_path}: not a UTF-8 text CSV ({e})") from e
        except csv.Error as e:
            raise DataError(f"{self.csv_path}: malformed CSV ({e})") from e
        if not self.rows:
            raise DataError(f"{self.csv_path}: no data rows")

    def _parse_row(self, row: list[str], idx: dict[str, int], where: str) -> dict:
        if len(row) <= max(idx.values()):
            raise DataError(f"{where}: {len(row)} field(s), expected at least {max(idx.values()) + 1}")
        name = row[idx["name"]].strip()
        if not name:
            raise DataError(f"{where}: empty name")
        values = {}
        for col in ("rotation", "shift_x", "shift_y", "scale") if self.poses else ():
            if col not in idx:
                values[col] = 1.0
                continue
            text = row[idx[col]].strip()
            try:
                v = float(text)
            except ValueError:
                raise DataError(f"{where}: {col} = {text!r} is not a number") from None
            if not math.isfinite(v):
                raise DataError(f"{where}: {col} = {text!r} is not finite")
            values[col] = v
        if values.get("scale", 1.0) <= 0:
            raise DataError(f"{where}: scale = {values['scale']} must be > 0")
        paths = {}
        for what, folder in (("template", self.template_dir), ("source", self.source_dir)):
            found = _find_image(folder, name) or ([folder / name] if (folder / name).is_file() else [])
            if not found:
                raise DataError(
                    f"{where}: {what} image for {name!r} not found: expected "
                    f"{folder}/{name}.<{'|'.join(e[1:] for e in IMAGE_EXTENSIONS)}>"
                )
            paths[what] = found[0]
        return {"name": name, **values, **paths}

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        row = self.rows[index]
        template, talpha = read_image(row["template"])
        source, _ = read_image(row["source"])
        if template.shape[:2] != source.shape[:2]:
            raise DataError(
                f"{self.csv_path}: {row['name']!r}: template {row['template']} is "
                f"{template.shape[1]}x{template.shape[0]} (WxH) but source "
                f"{row['source']} is {source.shape[1]}x{source.shape[0]}"
            )
        tx, ty = row.get("shift_x", 0.0), row.get("shift_y", 0.0)
        angle, sc = row.get("rotation", 0.0), row.get("scale", 1.0)
        mask = np.ones(template.shape[:2], np.float32) if talpha is None else talpha.astype(np.float32)
        hs, ws = template.shape[:2]
        if self.size is not None and self.size != (hs, ws):
            h, w = self.size
            fx, fy = w / ws, h / hs
            if abs(fx - fy) > 1e-6 * max(fx, fy) + 0.5 / min(ws, hs):
                raise DataError(
                    f"{self.csv_path}: {row['name']!r}: resizing {ws}x{hs} (WxH) to "
                    f"{w}x{h} changes the aspect ratio; the pose would not be exact"
                )
            f = math.sqrt(fx * fy)
            interp = cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR
            template = cv2.resize(template, (w, h), interpolation=interp)
            source = cv2.resize(source, (w, h), interpolation=interp)
            mask = (cv2.resize(mask, (w, h), interpolation=cv2.INTER_LINEAR) > 0.5).astype(np.float32)
            th = math.radians(angle)
            a, b = sc * math.cos(th), sc * math.sin(th)
            dx, dy = (fx - 1) / 2.0, (fy - 1) / 2.0
            # (I - sR) d with sR = [[a, b], [-b, a]] as in pose_to_matrix.
            tx = fx * tx + (1 - a) * dx - b * dy
            ty = fy * ty + b * dx + (1 - a) * dy
        item = {
            "template": _to_tensor(template, self.channels),
            "source": _to_tensor(source, self.channels),
            "pose": torch.tensor([tx, ty, angle, sc], dtype=torch.float32),
            "template_mask": torch.from_numpy(np.ascontiguousarray(mask, np.float32))[None],
        }
        if not self.poses:
            del item["pose"]
        return item
