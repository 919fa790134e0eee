"""Simulated template/source pairs (DPCN paper, CoRL 2020, section 3.1).

Pairs of 2D bird's-eye-like images related by a known similarity pose, generated on the fly
from a seed. :class:`SimulatedPairs` items are ``{"template", "source", "pose"}`` with the
project's pose convention (:mod:`dpcn.pose`): for ``pose = (tx, ty, angle, scale)``::

    M = cv2.getRotationMatrix2D((W / 2, H / 2), angle, scale); M[0, 2] += tx; M[1, 2] += ty
    source ~ cv2.warpAffine(template_scene_in_source_style, M, (W, H))

Kinds (:data:`SIM_KINDS`)
-------------------------
``homogeneous``
    template = style A; source = the *same* style-A rendering warped by the pose (plus mild
    noise). With ``noise=0``, ``cv2.warpAffine(template, M, (W, H))`` equals ``source`` wherever
    the warped template is defined (mean abs difference ~1e-7, max ~1e-3 from OpenCV's
    fixed-point bilinear weights).
``heterogeneous``
    template = style A, source = style B of the same scene: a strong appearance change
    (non-monotonic intensities, other texture, outlines, gamma, sensor noise). Only the geometry
    of the region boundaries is shared. Plain phase correlation on raw pixels mostly fails:
    translation-only pairs (±30 px, 256 px): ``cv2.phaseCorrelate`` within 2 px for 30/30
    homogeneous pairs, 4/30 heterogeneous ones; NCC of template vs un-warped source: mean 0.98
    homogeneous, mean |NCC| about 0.3 heterogeneous (some pairs anti-correlated).
``dynamic``
    heterogeneous plus ``obstacles`` dynamic obstacles drawn into *each* image independently
    after the warp (so every obstacle is in one image only). A dynamic pair is bit-identical to
    the heterogeneous pair of the same (seed, epoch, index, args) except on the obstacle
    pixels; with ``obstacles=0`` it is identical.

Geometry
--------
The scene lives on a canvas larger than the output: a disc of radius
``(hypot(W, H) / 2 + sqrt(2) * translation) / scale[0]`` (+ a few px) around the centre, enough
for any angle, any translation in range and the smallest scale (so no source pixel is ever
empty). The template is the central ``H x W`` crop (offset ``o``) of the style-A rendering; the
source is ``cv2.warpAffine`` (bilinear) of the style-B (homogeneous: style-A) rendering with
``M`` composed with the crop offset (``t' = t - A o``). Only the regions actually needed (the
crop, and the pre-image of the source frame) are rendered. All random fields are defined on
canvas-aligned lattices, so the scene and the template do not depend on the pose, and the
template is the same for all three kinds (before dynamic obstacles; homogeneous vs the others:
up to float rounding, ~1e-7).

Scene (shared by both styles)
-----------------------------
A uint8 label map of ``K`` region classes, ``K`` uniform in 4..8; lengths are relative to
``L = sqrt(H * W)``: terrain = a smooth random field (bicubic, node spacing ``L / 5``)
thresholded into 2-3 classes (irregular blobs); on top, per ``L x L`` tile of the canvas (each
tile has its own random stream and is generated only if it can reach the rendered region):
8 filled ellipses (semi-axes 0.02-0.12 L) and 8 star-shaped polygons (3-8 vertices, radius
0.04-0.15 L) in random order, then (over all tiles) 2 thick polylines per tile (roads/walls,
1-3 segments of 0.15-0.35 L, thickness 2 to 2 + 0.03 L px). Each shape has a random class.

Style A (template; homogeneous source)
--------------------------------------
per-class grey level U(0.1, 0.9) (3 channels: plus a per-class RGB tint U(-0.15, 0.15));
plus fine texture (unit-variance noise on a 2-px lattice, bilinear) times a per-class amplitude
U(0.02, 0.1); times smooth shading ``1 + 0.15 * S`` (S in [-1, 1], spacing L / 2); Gaussian
blur sigma 0.8 px; clipped to [0, 1].

Style B (heterogeneous/dynamic source)
--------------------------------------
per-class levels U(0.05, 0.95) redrawn (up to 50 times) until ``|corr(level_A, level_B)| <=
0.3`` over the classes (a non-monotonic mapping: some regions keep their contrast, others are
inverted); each class is "outline only" with probability 0.35 (interior set to one shared
random fill level, never all classes); grain texture (3-px lattice) with per-class amplitude
U(0, 0.12); directional streaks (noise stretched 12 px along a random direction, 1.5 px
across) with per-class amplitude U(0, 0.1); all region boundaries (2 px wide) emphasised by a
signed constant of magnitude U(0.25, 0.5); smooth shading ``1 + 0.2 * S`` (spacing L / 1.5);
Gaussian blur sigma 0.6 px; clip; gamma ``exp(U(ln 0.5, ln 2))``; contrast to [lo, hi] with
lo U(0, 0.15), hi U(0.85, 1). 3 channels: the grey style-B image (after the warp) through a
false-colour map picked per pair from JET, VIRIDIS, HOT, OCEAN, TWILIGHT, PLASMA.

Appearance change (heterogeneous/dynamic)
-----------------------------------------
``appearance_change = w`` in [0, 1] cross-fades the source: ``w * style B + (1 - w) * style A``
(both warped, style A clipped to [0, 1]; 3 channels: the false-colour image and the RGB style
A), before obstacles and noise. ``w = 1`` (the default) renders no style-A source and gives
exactly the pairs above; ``w = 0`` gives the homogeneous source with the heterogeneous sensor
noise. The template never changes. The classical estimator on the 500 heterogeneous test
pairs (``python -m dpcn test -m model=classical data.dataset.appearance_change=1,0.5,0.3,0.2,0``),
x@5px / y@5px / rot@1° / scale@0.2 in %: w = 1: 14.0 / 14.4 / 3.8 / 87.2; 0.5: 35.8 / 33.2 /
19.4 / 87.0; 0.3: 56.8 / 59.0 / 46.8 / 92.4; 0.2: 68.2 / 71.6 / 62.2 / 94.0; 0: 80.6 / 81.0 /
76.8 / 97.4 (``data=sim_homogeneous``: 98.4 / 98.4 / 98.2 / 99.8). So the sensor noise and row
banding alone cost it a fifth of the rotations.

Obstacles (dynamic)
-------------------
per image: exactly ``obstacles`` of them, centre uniform in the image; 60% cars (rotated
rectangles 0.05-0.1 L long, 0.4-0.55 as wide), 40% people (discs of radius 0.012-0.025 L);
flat dark U(0, 0.2) or bright U(0.8, 1) fill (per channel) with a 1-px border of 1 - fill.
Their sharp, high-contrast edges weigh heavily in a magnitude spectrum: on the dynamic test
pairs at ``appearance_change=0.3`` the classical estimator finds 49.6 / 50.4 / 37.6 / 91.2 %
(x@5px / y@5px / rot@1° / scale@0.2) with one obstacle per image and 31.6 / 31.6 / 17.2 / 91.6 %
with four (``python -m dpcn test -m model=classical data=sim_dynamic
data.dataset.appearance_change=0.3 data.dataset.obstacles=1,2,3,4``), against 56.8 / 59.0 /
46.8 / 92.4 % with none. The paper's obstacles cost its classical estimator nothing (its
dynamic row averages 64.1 %, its heterogeneous row 63.9 %), so these dynamic pairs are harder
than the paper's at every ``appearance_change``.

Noise
-----
Applied last, then everything is clipped to [0, 1]: template ``+ N(0, noise)``; homogeneous
source ``+ N(0, noise)``; heterogeneous/dynamic source ``+ N(0, 2 * noise)`` per pixel plus a
per-row banding offset ``N(0, noise)``. ``noise=0`` disables all of it. The pixel noise is a
random window (random sign) of a fixed bank of N(0, 1) samples (template and source from
disjoint halves), ~10x cheaper than fresh normals.

Determinism
-----------
Every item is a pure function of (seed, epoch, index, kind, other args): each part uses its
own stream ``numpy.random.default_rng([seed, epoch, index, stream])`` (scene, pose, style A,
style B, noise, template obstacles, source obstacles), so worker processes, re-runs and
resumed runs give identical data, and the pose/scene do not depend on ``kind``. The pose is
drawn with :func:`dpcn.pose.sample_poses` (torch generator seeded from the pose stream), and
the returned float32 values are exactly the ones rendered.

Speed (256 x 256, one core with ``cv2.setNumThreads(1)``, wall time per pair, best / median
of 6 rounds of 40 pairs on the shared 2-core development machine): 1 channel: homogeneous
4.5 / 7.2 ms, heterogeneous 6.7 / 8.0 ms, dynamic 7.2 / 8.1 ms; 3 channels: 9.3 / 11.4,
10.3 / 11.8, 11.3 / 12.8 ms. The first item of a process also builds the 16 MB noise bank
(~40 ms). Cost grows with the rendered area, i.e. with ``(size + translation) / scale[0]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from dpcn.pose import sample_poses

__all__ = ["SIM_KINDS", "SimulatedPairs"]

SIM_KINDS = ("homogeneous", "heterogeneous", "dynamic")

# Independent random streams of one item: ``default_rng([seed, epoch, index, stream])``.
# Keeping them apart makes every part of a pair independent of the others (and of ``kind``).
_SCENE, _POSE, _STYLE_A, _STYLE_B, _NOISE, _OBST_TEMPLATE, _OBST_SOURCE = range(7)

_PAD = 4  # context pixels around every rendered region (blur kernels, bilinear taps)
_U_STD = math.sqrt(12.0)  # scales uniform [-0.5, 0.5) noise to unit variance

# False-colour maps of the 3-channel source (picked per pair).
_COLORMAPS = (
    cv2.COLORMAP_JET,
    cv2.COLORMAP_VIRIDIS,
    cv2.COLORMAP_HOT,
    cv2.COLORMAP_OCEAN,
    cv2.COLORMAP_TWILIGHT,
    cv2.COLORMAP_PLASMA,
)

Rect = tuple[int, int, int, int]  # canvas pixels (x0, y0, x1, y1), half-open


# --------------------------------------------------------------------------- helpers


def _lattice(
    coarse: np.ndarray | None,
    step: int,
    rect: Rect,
    fn: Callable[[int, int, int, int], np.ndarray] | None = None,
) -> np.ndarray:
    """Bilinearly upsample lattice values into ``rect`` (canvas pixels).

    Lattice node ``(i, j)`` sits at canvas pixel ``(step * j + c, step * i + c)`` with
    ``c = (step - 1) / 2``, which makes ``cv2.resize(..., INTER_LINEAR)`` by ``step`` land on
    whole canvas pixels: the result at a canvas pixel does not depend on ``rect``. The values
    come from ``coarse`` (a canvas-level lattice array, node ``j`` at column ``j + 1``) or, when
    ``fn`` is given, from ``fn(i0, j0, rows, cols)``.
    """
    x0, y0, x1, y1 = rect
    j0, i0 = x0 // step - 1, y0 // step - 1
    cols = -(-(x1 - step * j0) // step) + 2
    rows = -(-(y1 - step * i0) // step) + 2
    if fn is None:
        values = coarse[i0 + 1 : i0 + 1 + rows, j0 + 1 : j0 + 1 + cols]
    else:
        values = fn(i0, j0, rows, cols)
    fine = cv2.resize(values, (cols * step, rows * step), interpolation=cv2.INTER_LINEAR)
    return fine[y0 - step * i0 : y1 - step * i0, x0 - step * j0 : x1 - step * j0]


def _smooth(grid: np.ndarray, spacing: float, rect: Rect, step: int = 4) -> np.ndarray:
    """A smooth random field on ``rect``: ``grid`` (node ``(i, j)`` at canvas pixel
    ``((j - 1) * spacing, (i - 1) * spacing)``) bicubically interpolated at every ``step``-th
    pixel, bilinear in between (much faster than a full-resolution bicubic warp)."""

    def coarse(i0: int, j0: int, rows: int, cols: int) -> np.ndarray:
        c = (step - 1) / 2.0
        m = np.array(
            [
                [step / spacing, 0.0, (step * j0 + c) / spacing + 1.0],
                [0.0, step / spacing, (step * i0 + c) / spacing + 1.0],
            ]
        )
        return cv2.warpAffine(
            grid,
            m,
            (cols, rows),
            flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REFLECT,
        )

    return _lattice(None, step, rect, coarse)


def _grid(rng: np.random.Generator, canvas: tuple[int, int], spacing: float) -> np.ndarray:
    """Uniform [-0.5, 0.5) float32 values on the nodes of a canvas-level lattice/grid."""
    hc, wc = canvas
    shape = (int(math.ceil(hc / spacing)) + 6, int(math.ceil(wc / spacing)) + 6)
    return rng.random(shape, dtype=np.float32) - np.float32(0.5)


def _lut(values: np.ndarray) -> np.ndarray:
    """A 256-entry float32 lookup table (class id -> value) for cv2.LUT."""
    lut = np.zeros((1, 256, values.shape[1]) if values.ndim == 2 else 256, dtype=np.float32)
    if values.ndim == 2:
        lut[0, : len(values)] = values
    else:
        lut[: len(values)] = values
    return lut


def _union(a: Rect, b: Rect) -> Rect:
    return min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])


def _sub(image: np.ndarray, outer: Rect, inner: Rect) -> np.ndarray:
    return image[inner[1] - outer[1] : inner[3] - outer[1], inner[0] - outer[0] : inner[2] - outer[0]]


# --------------------------------------------------------------------------- scene


@dataclass
class _Scene:
    """The random geometry shared by both styles, in canvas pixels.

    The shapes are generated per ``tile x tile`` canvas tile, from a stream of their own, and
    only for the tiles that can reach the rendered region: the cost does not grow with the
    canvas margin, and the scene at a canvas pixel does not depend on the region rendered.
    """

    key: list[int]  # [seed, epoch, index, _SCENE]: the tile streams extend it
    n_classes: int
    terrain_grid: np.ndarray  # uint8 grid, spacing terrain_spacing
    terrain_spacing: float
    terrain_lut: np.ndarray  # uint8 (256,): smoothed terrain value -> class
    length: float  # L = sqrt(H * W)
    canvas: tuple[int, int]


# A shape: kind, params, class, centre x, centre y (canvas pixels).
_Shape = tuple[str, tuple, int, float, float]
_ELLIPSES_PER_TILE, _POLYGONS_PER_TILE, _LINES_PER_TILE = 8, 8, 2
_MAX_LINE = 3 * 0.35  # longest polyline, in L


def _make_scene(key: list[int], canvas: tuple[int, int], length: float) -> _Scene:
    rng = np.random.default_rng(key)
    hc, wc = canvas
    n_classes = int(rng.integers(4, 9))
    # Terrain: a smooth random field quantised into 2-3 classes (irregular blob regions).
    spacing = length / 5.0
    shape = (int(math.ceil(hc / spacing)) + 4, int(math.ceil(wc / spacing)) + 4)
    terrain_grid = rng.integers(0, 256, shape, dtype=np.uint8)
    n_terrain = int(rng.integers(2, 4))
    terrain_classes = rng.choice(n_classes, size=n_terrain, replace=False)
    thresholds = np.sort(rng.uniform(100.0, 156.0, n_terrain - 1))
    terrain_lut = terrain_classes[np.digitize(np.arange(256), thresholds)].astype(np.uint8)
    return _Scene(key, n_classes, terrain_grid, spacing, terrain_lut, length, canvas)


def _tile_shapes(scene: _Scene, ty: int, tx: int, rect: Rect) -> tuple[list[_Shape], list[_Shape]]:
    """The shapes centred in one tile that reach ``rect``: (ellipses and polygons in drawing
    order, polylines). The random draws do not depend on ``rect``."""
    rng = np.random.default_rng([*scene.key, 1, ty, tx])
    length, k = scene.length, scene.n_classes
    x0, y0, x1, y1 = rect

    def centres(n: int) -> tuple[np.ndarray, np.ndarray]:
        return (tx + rng.random(n)) * length, (ty + rng.random(n)) * length

    def reaches(cx: np.ndarray, cy: np.ndarray, radius: np.ndarray) -> np.ndarray:
        return (cx + radius >= x0) & (cx - radius <= x1) & (cy + radius >= y0) & (cy - radius <= y1)

    # Ellipses.
    n = _ELLIPSES_PER_TILE
    cx, cy = centres(n)
    axes = np.maximum(rng.uniform(0.02, 0.12, (n, 2)) * length, 1.0)
    ang = rng.uniform(0, 180, n)
    cls = rng.integers(0, k, n)
    hit = reaches(cx, cy, axes.max(1))
    areas: list[_Shape | None] = [
        ("ellipse", (axes[i, 0], axes[i, 1], ang[i]), int(cls[i]), cx[i], cy[i]) if hit[i] else None for i in range(n)
    ]
    # Star-shaped polygons with 3-8 vertices.
    n = _POLYGONS_PER_TILE
    cx, cy = centres(n)
    radius = np.maximum(rng.uniform(0.04, 0.15, n) * length, 2.0)
    n_vert = rng.integers(3, 9, n)
    theta = np.sort(rng.uniform(0, 2 * np.pi, (n, 8)), axis=1)
    rfac = rng.uniform(0.4, 1.0, (n, 8))
    cls = rng.integers(0, k, n)
    hit = reaches(cx, cy, radius)
    vertices = (radius[:, None] * rfac)[..., None] * np.stack([np.cos(theta), np.sin(theta)], -1)
    areas += [("poly", (vertices[i, : n_vert[i]],), int(cls[i]), cx[i], cy[i]) if hit[i] else None for i in range(n)]
    order = rng.permutation(len(areas))  # random occlusions
    # Thick polylines (roads, walls), drawn on top of all areas.
    n = _LINES_PER_TILE
    cx, cy = centres(n)
    n_seg = rng.integers(1, 4, n)
    heading = rng.uniform(0, 2 * np.pi, n)
    turns = rng.normal(0.0, 0.5, (n, 3))
    seg_len = rng.uniform(0.15, 0.35, (n, 3)) * length
    thick = rng.uniform(2.0, 2.0 + 0.03 * length, n)
    cls = rng.integers(0, k, n)
    direction = heading[:, None] + np.concatenate([np.zeros((n, 1)), np.cumsum(turns[:, :2], 1)], 1)
    steps = seg_len[..., None] * np.stack([np.cos(direction), np.sin(direction)], -1)
    points = np.concatenate([np.zeros((n, 1, 2)), np.cumsum(steps, 1)], 1)  # (n, 4, 2)
    hit = reaches(cx, cy, np.abs(points).max((1, 2)) + thick)
    lines: list[_Shape] = [
        ("line", (points[i, : n_seg[i] + 1], int(round(thick[i]))), int(cls[i]), cx[i], cy[i])
        for i in range(n)
        if hit[i]
    ]
    return [a for a in (areas[i] for i in order) if a is not None], lines


def _draw_labels(scene: _Scene, rect: Rect) -> np.ndarray:
    """The uint8 class map of ``rect`` (canvas pixels)."""
    x0, y0, x1, y1 = rect
    terrain = _smooth(scene.terrain_grid, scene.terrain_spacing, rect)
    labels = cv2.LUT(terrain, scene.terrain_lut)
    fx = 16.0  # cv2 drawing with shift=4 (1/16 px precision)
    # Tiles whose shapes can reach the rect (a shape reaches at most _MAX_LINE * L + 3 px).
    tile = scene.length
    reach = (_MAX_LINE + 0.04) * tile + 3.0
    hc, wc = scene.canvas
    tx0, tx1 = (
        max(0, int((x0 - reach) // tile)),
        min(int(math.ceil(wc / tile)), int((x1 + reach) // tile) + 1),
    )
    ty0, ty1 = (
        max(0, int((y0 - reach) // tile)),
        min(int(math.ceil(hc / tile)), int((y1 + reach) // tile) + 1),
    )
    areas: list[_Shape] = []
    lines: list[_Shape] = []
    for ty in range(ty0, ty1):
        for tx in range(tx0, tx1):
            tile_areas, tile_lines = _tile_shapes(scene, ty, tx, rect)
            areas += tile_areas
            lines += tile_lines
    for kind, params, cls, cx, cy in areas + lines:
        if kind == "ellipse":
            ax, ay, ang = params
            cv2.ellipse(
                labels,
                (int(round((cx - x0) * fx)), int(round((cy - y0) * fx))),
                (int(round(ax * fx)), int(round(ay * fx))),
                ang,
                0,
                360,
                cls,
                -1,
                cv2.LINE_8,
                4,
            )
        elif kind == "poly":
            pts = np.round((params[0] + (cx - x0, cy - y0)) * fx).astype(np.int32)
            cv2.fillPoly(labels, [pts], cls, cv2.LINE_8, 4)
        else:
            pts, thickness = params
            pts = np.round((pts + (cx - x0, cy - y0)) * fx).astype(np.int32)
            cv2.polylines(labels, [pts], False, cls, thickness, cv2.LINE_8, 4)
    return labels


# --------------------------------------------------------------------------- styles


@dataclass
class _StyleA:
    colour: np.ndarray  # (K,) grey or (K, 3) RGB base level per class
    texture_amp: np.ndarray  # (K,)
    texture_grid: np.ndarray  # spacing 2 px
    shading_grid: np.ndarray  # spacing length / 2
    shading_spacing: float


def _make_style_a(
    rng: np.random.Generator, scene: _Scene, canvas: tuple[int, int], length: float, channels: int
) -> _StyleA:
    k = scene.n_classes
    grey = rng.uniform(0.1, 0.9, k)
    tint = rng.uniform(-0.15, 0.15, (k, 3))
    colour = grey if channels == 1 else np.clip(grey[:, None] + tint, 0.0, 1.0)
    spacing = length / 2.0
    return _StyleA(
        colour=colour,
        texture_amp=rng.uniform(0.02, 0.1, k),
        texture_grid=_grid(rng, canvas, 2) * np.float32(_U_STD),
        shading_grid=_grid(rng, canvas, spacing) * np.float32(2.0),
        shading_spacing=spacing,
    )


def _render_a(style: _StyleA, labels: np.ndarray, rect: Rect) -> np.ndarray:
    """Style A on ``rect``: float32 (h, w, C), not clipped."""
    texture = _lattice(style.texture_grid, 2, rect)
    shading = _smooth(style.shading_grid, style.shading_spacing, rect)
    amp = cv2.LUT(labels, _lut(style.texture_amp))
    factor = 1.0 + np.float32(0.15) * shading
    if style.colour.ndim == 1:
        base = cv2.LUT(labels, _lut(style.colour))
        image = ((base + amp * texture) * factor)[..., None]
    else:
        base = cv2.LUT(cv2.merge([labels, labels, labels]), _lut(style.colour))
        image = (base + (amp * texture)[..., None]) * factor[..., None]
    image = cv2.GaussianBlur(image, (0, 0), 0.8)
    return image if image.ndim == 3 else image[..., None]


@dataclass
class _StyleB:
    level: np.ndarray  # (K,) per-class level (outline classes: the fill level)
    grain_amp: np.ndarray  # (K,)
    streak_amp: np.ndarray  # (K,)
    edge: float  # signed edge emphasis
    gamma: float
    low: float
    high: float
    grain_grid: np.ndarray  # spacing 3 px
    streak_grid: np.ndarray  # anisotropic, see _render_b
    streak_angle: float
    shading_grid: np.ndarray
    shading_spacing: float
    colormap: int


def _make_style_b(
    rng: np.random.Generator,
    scene: _Scene,
    style_a: _StyleA,
    canvas: tuple[int, int],
    length: float,
) -> _StyleB:
    k = scene.n_classes
    grey_a = style_a.colour if style_a.colour.ndim == 1 else style_a.colour.mean(1)
    # Per-class levels nearly uncorrelated with style A: a non-monotonic mapping in which
    # some regions keep their contrast and others are inverted.
    best, best_corr = None, np.inf
    for _ in range(50):
        level = rng.uniform(0.05, 0.95, k)
        corr = abs(np.corrcoef(grey_a, level)[0, 1])
        if corr < best_corr:
            best, best_corr = level, corr
        if corr <= 0.3:
            break
    level = best
    outline = rng.random(k) < 0.35
    if outline.all():
        outline[rng.integers(k)] = False
    level = np.where(outline, rng.uniform(0.0, 1.0), level)
    hc, wc = canvas
    diag = math.hypot(hc, wc)
    streak_shape = (int(diag / 1.5) + 4, int(diag / 12.0) + 4)  # rows: across, cols: along
    shading_spacing = length / 1.5
    return _StyleB(
        level=level,
        grain_amp=rng.uniform(0.0, 0.12, k),
        streak_amp=rng.uniform(0.0, 0.1, k),
        edge=float(rng.uniform(0.25, 0.5) * rng.choice([-1.0, 1.0])),
        gamma=float(math.exp(rng.uniform(math.log(0.5), math.log(2.0)))),
        low=float(rng.uniform(0.0, 0.15)),
        high=float(rng.uniform(0.85, 1.0)),
        grain_grid=_grid(rng, canvas, 3) * np.float32(_U_STD),
        streak_grid=(rng.random(streak_shape, dtype=np.float32) - np.float32(0.5)) * np.float32(_U_STD),
        streak_angle=float(rng.uniform(0.0, np.pi)),
        shading_grid=_grid(rng, canvas, shading_spacing) * np.float32(2.0),
        shading_spacing=shading_spacing,
        colormap=int(rng.choice(_COLORMAPS)),
    )


def _render_b(style: _StyleB, labels: np.ndarray, rect: Rect, canvas: tuple[int, int]) -> np.ndarray:
    """Style B (grey) on ``rect``: float32 (h, w) in [0, 1]."""
    x0, y0, x1, y1 = rect
    grain = _lattice(style.grain_grid, 3, rect)
    # Streaks: noise stretched 12 px along the direction streak_angle, 1.5 px across it.
    c, s = math.cos(style.streak_angle), math.sin(style.streak_angle)
    hc, wc = canvas
    rows, cols = style.streak_grid.shape
    # canvas P -> (along, across) = R(-angle) (P - centre); grid (col, row) = (along/12, across/1.5)
    m = np.array([[c / 12.0, s / 12.0, 0.0], [-s / 1.5, c / 1.5, 0.0]])
    centre = np.array([x0 - wc / 2.0, y0 - hc / 2.0])
    m[:, 2] = m[:, :2] @ centre + (cols / 2.0, rows / 2.0)
    streak = cv2.warpAffine(
        style.streak_grid,
        m,
        (x1 - x0, y1 - y0),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT,
    )
    shading = _smooth(style.shading_grid, style.shading_spacing, rect)
    edges = cv2.morphologyEx(labels, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))
    edges = np.minimum(edges, 1).astype(np.float32)
    image = (
        cv2.LUT(labels, _lut(style.level))
        + cv2.LUT(labels, _lut(style.grain_amp)) * grain
        + cv2.LUT(labels, _lut(style.streak_amp)) * streak
        + np.float32(style.edge) * edges
    ) * (1.0 + np.float32(0.2) * shading)
    image = cv2.GaussianBlur(image, (0, 0), 0.6)
    np.clip(image, 0.0, 1.0, out=image)
    image = cv2.pow(image, style.gamma)
    return image * np.float32(style.high - style.low) + np.float32(style.low)


# --------------------------------------------------------------------------- obstacles


def _draw_obstacles(rng: np.random.Generator, image: np.ndarray, count: int, length: float) -> None:
    """Draw ``count`` small cars (rotated rectangles) / people (discs) into ``image`` in place."""
    h, w, channels = image.shape
    for _ in range(count):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        dark = rng.random() < 0.5
        value = rng.uniform(0.0, 0.2, channels) if dark else rng.uniform(0.8, 1.0, channels)
        border = 1.0 - value
        color = tuple(float(v) for v in value)
        border_color = tuple(float(v) for v in border)
        if rng.random() < 0.6:  # car
            car_len = rng.uniform(0.05, 0.1) * length
            car_wid = car_len * rng.uniform(0.4, 0.55)
            ang = rng.uniform(0, 2 * np.pi)
            ca, sa = math.cos(ang), math.sin(ang)
            corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * (
                car_len / 2,
                car_wid / 2,
            )
            pts = corners @ np.array([[ca, sa], [-sa, ca]]) + (cx, cy)
            pts = np.round(pts * 16).astype(np.int32)
            cv2.fillPoly(image, [pts], color, cv2.LINE_8, 4)
            cv2.polylines(image, [pts], True, border_color, 1, cv2.LINE_8, 4)
        else:  # person / small blob
            r = rng.uniform(0.012, 0.025) * length
            centre = (int(round(cx * 16)), int(round(cy * 16)))
            cv2.circle(image, centre, int(round(r * 16)), color, -1, cv2.LINE_8, 4)
            cv2.circle(image, centre, int(round(r * 16)), border_color, 1, cv2.LINE_8, 4)


# --------------------------------------------------------------------------- noise

_BANK_HALF = 1 << 21
_noise_bank: np.ndarray | None = None


def _gaussian(rng: np.random.Generator, shape: tuple[int, ...], half: int) -> np.ndarray:
    """i.i.d. N(0, 1) float32 noise of ``shape``: a random window (random sign) of a fixed bank
    of normal samples, from half ``half`` of it (template and source use disjoint halves, so they
    never share noise). Much faster than drawing fresh normals for every pair."""
    global _noise_bank
    n = math.prod(shape)
    if n > _BANK_HALF:
        return rng.standard_normal(shape, dtype=np.float32)
    if _noise_bank is None:
        _noise_bank = np.random.default_rng(0x5EED).standard_normal(2 * _BANK_HALF, dtype=np.float32)
    start = half * _BANK_HALF + int(rng.integers(0, _BANK_HALF - n + 1))
    sign = np.float32(1.0 if rng.random() < 0.5 else -1.0)
    return _noise_bank[start : start + n].reshape(shape) * sign


# --------------------------------------------------------------------------- dataset


def _check_range(name: str, value: object, positive: bool = False) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (low, high) pair of numbers, got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"{name} must be a finite (low, high) range with low <= high, got {value!r}")
    if positive and lo <= 0:
        raise ValueError(f"{name} must be positive, got {value!r}")
    return lo, hi


class SimulatedPairs(Dataset):
    """Seeded, on-the-fly simulated (template, source, pose) pairs; see the module docstring.

    Args:
        kind: one of :data:`SIM_KINDS`.
        length: number of pairs per epoch.
        size: output ``(H, W)`` (or one int for a square), at least 16 px each.
        seed: base seed (>= 0); a validation/test set is another seed at epoch 0.
        translation: ``tx, ty`` uniform in ``±translation`` px.
        rotation: angle uniform in ``[rotation[0], rotation[1])`` degrees, wrapped to (-180, 180].
        scale: scale uniform in ``[scale[0], scale[1]]``.
        channels: 1 (grey) or 3 (RGB).
        noise: standard deviation of the additive Gaussian pixel noise (0 disables all noise).
        obstacles: dynamic obstacles drawn into each image of a ``dynamic`` pair.
        appearance_change: weight of style B in a ``heterogeneous``/``dynamic`` source, the rest
            being the style-A (homogeneous) source: 1 (default) is the full change, 0 the
            homogeneous pair with the heterogeneous sensor noise. A difficulty axis between
            the two kinds (see "Appearance change" above); ignored by ``homogeneous``.

    Items are ``{"template": (C, H, W), "source": (C, H, W), "pose": (4,)}`` float32 tensors,
    images in [0, 1], pose ``(tx, ty, angle, scale)`` in the :mod:`dpcn.pose` convention
    (template -> source). :meth:`set_epoch` changes an attribute: DataLoader workers see it
    only if they are (re)started after the call (not with ``persistent_workers=True``).
    """

    def __init__(
        self,
        kind: str = "heterogeneous",
        length: int = 1000,
        size: int | tuple[int, int] = 256,
        seed: int = 0,
        translation: float = 50.0,
        rotation: tuple[float, float] = (-180.0, 180.0),
        scale: tuple[float, float] = (0.8, 1.2),
        channels: int = 1,
        noise: float = 0.02,
        obstacles: int = 4,
        appearance_change: float = 1.0,
    ) -> None:
        if kind not in SIM_KINDS:
            raise ValueError(f"kind must be one of {SIM_KINDS}, got {kind!r}")
        if not isinstance(length, (int, np.integer)) or isinstance(length, bool) or length < 1:
            raise ValueError(f"length must be an integer >= 1, got {length!r}")
        if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
            hw = (int(size), int(size))
        else:
            try:
                hw = tuple(int(v) for v in size)  # type: ignore[union-attr]
            except (TypeError, ValueError):
                raise ValueError(f"size must be an int or an (H, W) pair, got {size!r}") from None
            if len(hw) != 2:
                raise ValueError(f"size must be an int or an (H, W) pair, got {size!r}")
        if min(hw) < 16:
            raise ValueError(f"size must be at least 16 px in each dimension, got {size!r}")
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
        try:
            translation = float(translation)
        except (TypeError, ValueError):
            raise ValueError(f"translation must be a number >= 0, got {translation!r}") from None
        if not (math.isfinite(translation) and translation >= 0):
            raise ValueError(f"translation must be a finite number >= 0, got {translation!r}")
        rotation = _check_range("rotation", rotation)
        scale = _check_range("scale", scale, positive=True)
        if channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3, got {channels!r}")
        try:
            noise = float(noise)
        except (TypeError, ValueError):
            raise ValueError(f"noise must be a number >= 0, got {noise!r}") from None
        if not (math.isfinite(noise) and noise >= 0):
            raise ValueError(f"noise must be a finite number >= 0, got {noise!r}")
        if not isinstance(obstacles, (int, np.integer)) or isinstance(obstacles, bool) or obstacles < 0:
            raise ValueError(f"obstacles must be an integer >= 0, got {obstacles!r}")
        try:
            change = float(appearance_change)
        except (TypeError, ValueError):
            change = math.nan
        if isinstance(appearance_change, bool) or not 0.0 <= change <= 1.0:
            raise ValueError(f"appearance_change must be a number in [0, 1], got {appearance_change!r}")

        self.kind = kind
        self.length = int(length)
        self.size: tuple[int, int] = hw  # (H, W)
        self.seed = int(seed)
        self.translation = translation
        self.rotation = rotation
        self.scale = scale
        self.channels = int(channels)
        self.noise = noise
        self.obstacles = int(obstacles)
        self.appearance_change = change
        self.epoch = 0

        # Canvas: the output frame plus a margin covering every pose of the ranges (any angle).
        h, w = hw
        reach = (0.5 * math.hypot(w, h) + math.sqrt(2.0) * translation) / scale[0] + _PAD + 2
        self._offset = (
            max(0, math.ceil(reach - w / 2)),
            max(0, math.ceil(reach - h / 2)),
        )  # (ox, oy)
        self._canvas = (h + 2 * self._offset[1], w + 2 * self._offset[0])  # (Hc, Wc)
        self._scale_length = math.sqrt(h * w)

    def set_epoch(self, epoch: int) -> None:
        """Select the pairs of ``epoch`` (training draws fresh pairs each epoch)."""
        if not isinstance(epoch, (int, np.integer)) or isinstance(epoch, bool) or epoch < 0:
            raise ValueError(f"epoch must be an integer >= 0, got {epoch!r}")
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.length

    def __repr__(self) -> str:
        return (
            f"SimulatedPairs(kind={self.kind!r}, length={self.length}, size={self.size}, "
            f"seed={self.seed}, epoch={self.epoch}, translation={self.translation}, "
            f"rotation={self.rotation}, scale={self.scale}, channels={self.channels}, "
            f"noise={self.noise}, obstacles={self.obstacles}, appearance_change={self.appearance_change})"
        )

    def _rng(self, index: int, stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.epoch, index, stream])

    def _pose(self, index: int) -> np.ndarray:
        rng = self._rng(index, _POSE)
        generator = torch.Generator().manual_seed(int(rng.integers(0, 2**63 - 1)))
        pose = sample_poses(1, generator, self.translation, self.rotation, self.scale, dtype=torch.float64).as_tensor()[
            0
        ]
        # The float32 values returned are exactly the ones the pair is rendered with.
        return pose.numpy().astype(np.float32)

    def _make(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        h, w = self.size
        ox, oy = self._offset
        hc, wc = self._canvas
        length = self._scale_length
        pose = self._pose(index)
        tx, ty, angle, scale = (float(v) for v in pose)
        m = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), angle, scale)
        m[0, 2] += tx
        m[1, 2] += ty

        # Canvas regions: the template crop and the pre-image of the source frame.
        crop = (ox - _PAD, oy - _PAD, ox + w + _PAD, oy + h + _PAD)
        a_inv = np.linalg.inv(m[:, :2])
        corners = np.array([[-1.0, -1.0], [w, -1.0], [-1.0, h], [w, h]])
        pre = (corners - m[:, 2]) @ a_inv.T + (ox, oy)
        src = (
            max(0, int(math.floor(pre[:, 0].min())) - _PAD),
            max(0, int(math.floor(pre[:, 1].min())) - _PAD),
            min(wc, int(math.ceil(pre[:, 0].max())) + _PAD + 1),
            min(hc, int(math.ceil(pre[:, 1].max())) + _PAD + 1),
        )
        union = _union(crop, src)

        scene = _make_scene([self.seed, self.epoch, index, _SCENE], self._canvas, length)
        labels = _draw_labels(scene, union)
        style_a = _make_style_a(self._rng(index, _STYLE_A), scene, self._canvas, length, self.channels)

        def warp(image: np.ndarray, rect: Rect) -> np.ndarray:
            # source pixel q <- canvas pixel P = A^-1 (q - t) + o  ==  rect pixel P - rect origin
            m_rect = m.copy()
            m_rect[:, 2] -= m[:, :2] @ (ox - rect[0], oy - rect[1])
            out = cv2.warpAffine(image, m_rect, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            return out if out.ndim == 3 else out[..., None]

        if self.kind == "homogeneous":
            image_a = _render_a(style_a, labels, union)
            template = _sub(image_a, union, (ox, oy, ox + w, oy + h)).copy()
            source = warp(image_a, union)
        else:
            image_a = _render_a(style_a, _sub(labels, union, crop), crop)
            template = image_a[_PAD : _PAD + h, _PAD : _PAD + w].copy()
            style_b = _make_style_b(self._rng(index, _STYLE_B), scene, style_a, self._canvas, length)
            source = warp(_render_b(style_b, _sub(labels, union, src), src, self._canvas), src)
            if self.channels == 3:
                grey = np.clip(source[..., 0] * 255.0 + 0.5, 0, 255).astype(np.uint8)
                colour = cv2.applyColorMap(grey, style_b.colormap)[..., ::-1]  # BGR -> RGB
                source = colour.astype(np.float32) * np.float32(1.0 / 255.0)
            if self.appearance_change < 1.0:  # cross-fade towards the style-A (homogeneous) source
                change = np.float32(self.appearance_change)
                style_a_source = np.clip(warp(_render_a(style_a, _sub(labels, union, src), src), src), 0.0, 1.0)
                source = change * source + (np.float32(1.0) - change) * style_a_source
        np.clip(template, 0.0, 1.0, out=template)
        np.clip(source, 0.0, 1.0, out=source)

        if self.kind == "dynamic" and self.obstacles > 0:
            _draw_obstacles(self._rng(index, _OBST_TEMPLATE), template, self.obstacles, length)
            _draw_obstacles(self._rng(index, _OBST_SOURCE), source, self.obstacles, length)

        if self.noise > 0:
            rng = self._rng(index, _NOISE)
            sigma = np.float32(self.noise)
            template += _gaussian(rng, template.shape, 0) * sigma
            if self.kind == "homogeneous":
                source += _gaussian(rng, source.shape, 1) * sigma
            else:  # sensor noise of style B: stronger pixel noise plus row banding
                source += _gaussian(rng, source.shape, 1) * (2 * sigma)
                source += rng.standard_normal((h, 1, 1), dtype=np.float32) * sigma
            np.clip(template, 0.0, 1.0, out=template)
            np.clip(source, 0.0, 1.0, out=source)
        return template, source, pose

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        index = int(index)
        if index < 0:
            index += self.length
        if not 0 <= index < self.length:
            raise IndexError(f"index out of range for a dataset of length {self.length}")
        template, source, pose = self._make(index)
        return {
            "template": torch.from_numpy(np.ascontiguousarray(template.transpose(2, 0, 1))),
            "source": torch.from_numpy(np.ascontiguousarray(source.transpose(2, 0, 1))),
            "pose": torch.from_numpy(pose),
        }
