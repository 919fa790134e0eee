"""Procedural stand-in for Aero-Ground style data: one seeded world, four modalities.

:func:`generate_scene` builds a small town (roads with lane marks and sidewalks, buildings
with flat or gabled roofs, trees, grass, open ground, parked cars) and renders it, all
co-registered at the same pixel grid (0.1 m/pixel nominal), as

* ``lidar``: ground-robot LiDAR intensity map. Reflectance-driven (dark road, bright lane
  marks, mid vegetation, car sparkle), sparse and speckled with point density and intensity
  falling off with range from the robot's path, nothing beyond 25-35 m (250-350 px) of the
  path, building walls as bright thin outlines on the side facing the robot, roofs unseen,
  holes behind buildings (line of sight).
* ``stereo``: ground-robot stereo elevation map. Heights mapped to grey (ground ~20, 25 m
  -> 255), noise growing with range, smoothed, holes (low-texture areas, occlusion), a
  shorter range (15-22 m) than the LiDAR.
* ``drone``: RGB orthophoto, summer, shading and cast shadows from a random sun.
* ``satellite``: RGB, rendered at 1/3 resolution then upsampled (blurry), another season
  and sun (colours and shadows differ), semi-transparent clouds with their shadows, JPEG
  artefacts, and a few parked cars missing, moved or added.
* ``lidar_mask`` / ``stereo_mask``: 255 where the robot's sensor covered the ground (in
  range and in line of sight; the LiDAR map is still speckled inside it), 0 = no data.

:func:`write_scene` and :func:`make_dataset` write scenes in the folder layout that
:mod:`dpcn.data.aeroground` reads. :func:`scene_truth` gives the world a scene renders (class
labels and heights), for diagnostics such as ``benchmarks/bench_map_ceiling.py``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "generate_scene",
    "scene_truth",
    "scene_seed",
    "scene_index",
    "write_scene",
    "make_dataset",
    "MODALITIES",
    "MASKED_MODALITIES",
]

MODALITIES = ("lidar", "stereo", "drone", "satellite")
MASKED_MODALITIES = ("lidar", "stereo")

# Label classes of the world.
SOIL, GRASS, SIDEWALK, ROAD, MARK, BUILDING, TREE, CAR = range(8)
PIXEL_M = 0.1  # metres per pixel
STEREO_MAX_M = 25.0  # elevation mapped to grey 255
STEREO_GROUND = 20.0  # grey of elevation 0 (no data stays 0)

_CAR_COLOURS = np.array(
    [
        [0.92, 0.92, 0.92],
        [0.08, 0.08, 0.09],
        [0.62, 0.63, 0.65],
        [0.40, 0.41, 0.43],
        [0.65, 0.10, 0.10],
        [0.12, 0.22, 0.50],
        [0.80, 0.80, 0.78],
        [0.20, 0.30, 0.22],
    ],
    np.float32,
)
_ROOF_COLOURS = np.array(
    [
        [0.55, 0.27, 0.20],  # terracotta
        [0.42, 0.42, 0.44],  # grey concrete
        [0.30, 0.30, 0.32],  # dark tar
        [0.72, 0.72, 0.70],  # light membrane
        [0.50, 0.40, 0.33],  # brown shingles
        [0.35, 0.40, 0.45],  # blue-grey metal
    ],
    np.float32,
)


# --------------------------------------------------------------------------------------
# helpers


def _noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Smooth value noise with features of about ``cell`` pixels, zero mean, unit std."""
    h, w = shape
    gh, gw = max(2, int(math.ceil(h / cell)) + 2), max(2, int(math.ceil(w / cell)) + 2)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    if cell <= 1.5:
        out = rng.standard_normal(shape).astype(np.float32)
    else:
        big = cv2.resize(grid, (int(round(gw * cell)), int(round(gh * cell))), interpolation=cv2.INTER_CUBIC)
        out = big[:h, :w]
    out = out - out.mean()
    return out / (out.std() + 1e-6)


def _fbm(rng: np.random.Generator, shape: tuple[int, int], cells: Sequence[float]) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    amp = 1.0
    for c in cells:
        out += amp * _noise(rng, shape, c)
        amp *= 0.5
    return out / (out.std() + 1e-6)


def _densify(points: np.ndarray, step: float = 4.0) -> np.ndarray:
    """Resample a polyline every ``step`` pixels of arc length."""
    seg = np.diff(points, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    t = np.arange(0.0, s[-1], step)
    return np.stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])], axis=1)


def _tangents(dense: np.ndarray) -> np.ndarray:
    d = np.gradient(dense, axis=0)
    return d / (np.linalg.norm(d, axis=1, keepdims=True) + 1e-9)


def _poly_int(points: np.ndarray) -> np.ndarray:
    return np.round(points).astype(np.int32).reshape(-1, 1, 2)


def _box(cx: float, cy: float, length: float, width: float, angle_rad: float) -> np.ndarray:
    """Corners of a rotated rectangle whose ``length`` runs along ``angle_rad``."""
    u = np.array([math.cos(angle_rad), math.sin(angle_rad)])
    v = np.array([-u[1], u[0]])
    c = np.array([cx, cy])
    hl, hw = length / 2.0, width / 2.0
    return np.stack([c + hl * u + hw * v, c - hl * u + hw * v, c - hl * u - hw * v, c + hl * u - hw * v])


def _shift_max(acc: np.ndarray, src: np.ndarray, dx: int, dy: int, drop: float) -> None:
    """acc[y, x] = max(acc[y, x], src[y + dy, x + dx] - drop) where defined."""
    h, w = src.shape
    if abs(dx) >= w or abs(dy) >= h:
        return
    ys_d = slice(max(0, -dy), h - max(0, dy))
    xs_d = slice(max(0, -dx), w - max(0, dx))
    ys_s = slice(max(0, dy), h - max(0, -dy))
    xs_s = slice(max(0, dx), w - max(0, -dx))
    np.maximum(acc[ys_d, xs_d], src[ys_s, xs_s] - drop, out=acc[ys_d, xs_d])


def _cast_shadow(height: np.ndarray, azimuth: float, elevation: float) -> np.ndarray:
    """Soft cast-shadow strength in [0, 1] for a sun at ``azimuth`` (deg, image x towards
    y) and ``elevation`` (deg). Ray-marched at half resolution."""
    h, w = height.shape
    small = cv2.resize(height, (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_LINEAR)
    px = 2 * PIXEL_M
    ux, uy = math.cos(math.radians(azimuth)), math.sin(math.radians(azimuth))
    slope = math.tan(math.radians(elevation)) * px  # metres of ray rise per small pixel
    hmax = float(small.max())
    acc = np.full_like(small, -1e9)
    k = 1
    last = None
    while k * slope < hmax + 0.5:
        d = (int(round(k * ux)), int(round(k * uy)))
        if d != last:
            _shift_max(acc, small, d[0], d[1], k * slope)
            last = d
        k += 1
    strength = np.clip((acc - small) / 0.4, 0.0, 1.0)
    strength = cv2.resize(strength, (w, h), interpolation=cv2.INTER_LINEAR)
    return cv2.GaussianBlur(strength, (0, 0), 1.2)


def _hillshade(height: np.ndarray, azimuth: float, elevation: float) -> np.ndarray:
    """Lambertian shading relative to flat ground (1 on flat ground)."""
    hs = cv2.GaussianBlur(height, (0, 0), 1.0)
    gx = cv2.Sobel(hs, cv2.CV_32F, 1, 0, ksize=3) / (8.0 * PIXEL_M)
    gy = cv2.Sobel(hs, cv2.CV_32F, 0, 1, ksize=3) / (8.0 * PIXEL_M)
    el, az = math.radians(elevation), math.radians(azimuth)
    sx, sy, sz = math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)
    shade = (-gx * sx - gy * sy + sz) / np.sqrt(1.0 + gx * gx + gy * gy)
    return np.clip(shade / sz, 0.35, 1.35)


def _visibility(occluder: np.ndarray, viewpoints: np.ndarray, radius: float, factor: int = 4) -> np.ndarray:
    """Union over ``viewpoints`` (x, y full-res pixels) of the area within ``radius`` pixels
    and in line of sight (occluders hide what lies behind them; their first pixel is seen).
    Computed at ``1/factor`` resolution with polar warps; returns a full-res bool map."""
    h, w = occluder.shape
    hq, wq = max(1, h // factor), max(1, w // factor)
    occ = cv2.resize(occluder.astype(np.float32), (wq, hq), interpolation=cv2.INTER_AREA) > 0.3
    occ = occ.astype(np.float32)
    rq = radius / factor
    n_r = max(2, int(math.ceil(rq)))
    vis = np.zeros((hq, wq), np.float32)
    for x, y in viewpoints / factor:
        x0, x1 = int(max(0, x - rq - 2)), int(min(wq, x + rq + 3))
        y0, y1 = int(max(0, y - rq - 2)), int(min(hq, y + rq + 3))
        if x1 <= x0 or y1 <= y0:
            continue
        centre = (float(x - x0), float(y - y0))
        roi = np.ascontiguousarray(occ[y0:y1, x0:x1])
        pol = cv2.warpPolar(roi, (n_r, 360), centre, rq, cv2.INTER_NEAREST | cv2.WARP_FILL_OUTLIERS)
        blocked = np.maximum.accumulate(pol, axis=1)
        blocked[:, 1:] = blocked[:, :-1].copy()
        blocked[:, 0] = 0.0
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP | cv2.WARP_FILL_OUTLIERS
        back = cv2.warpPolar(1.0 - blocked, (x1 - x0, y1 - y0), centre, rq, flags)
        np.maximum(vis[y0:y1, x0:x1], back, out=vis[y0:y1, x0:x1])
    vis = cv2.resize(vis, (w, h), interpolation=cv2.INTER_LINEAR)
    return vis > 0.5


# --------------------------------------------------------------------------------------
# the world


@dataclass
class _Car:
    x: float
    y: float
    angle: float  # radians
    colour: int


@dataclass
class _World:
    labels: np.ndarray  # uint8 classes, without cars
    height: np.ndarray  # float32 metres, without cars
    roof_rgb: np.ndarray  # float32 (H, W, 3), valid on buildings
    tree_var: np.ndarray  # float32 [0, 1] per tree
    fine: np.ndarray
    medium: np.ndarray
    coarse: np.ndarray
    path_dist: np.ndarray  # float32 distance (px) to the robot path
    viewpoints: np.ndarray  # (N, 2) robot positions (x, y)
    cars: list[_Car]
    cars_satellite: list[_Car]


def _make_roads(rng: np.random.Generator, h: int, w: int):
    roads = []
    n_extra = int(rng.integers(0, 2))
    kinds = ["h", "v"] + ["d"] * n_extra
    for kind in kinds:
        n_ctrl = 5
        if kind == "h":
            xs = np.linspace(-0.15 * w, 1.15 * w, n_ctrl)
            ys = rng.uniform(0.25, 0.75) * h + np.cumsum(rng.normal(0, 0.06 * h, n_ctrl))
        elif kind == "v":
            ys = np.linspace(-0.15 * h, 1.15 * h, n_ctrl)
            xs = rng.uniform(0.25, 0.75) * w + np.cumsum(rng.normal(0, 0.06 * w, n_ctrl))
        else:
            a = rng.uniform(0, math.pi)
            cx, cy = rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h
            t = np.linspace(-0.9, 0.9, n_ctrl) * math.hypot(h, w)
            xs = cx + t * math.cos(a) + rng.normal(0, 0.04 * w, n_ctrl)
            ys = cy + t * math.sin(a) + rng.normal(0, 0.04 * h, n_ctrl)
        ctrl = np.stack([xs, ys], axis=1)
        dense = _densify(ctrl, 4.0)
        # Smooth the corners a little.
        k = 9
        pad = np.concatenate([np.repeat(dense[:1], k, 0), dense, np.repeat(dense[-1:], k, 0)])
        kernel = np.ones(2 * k + 1) / (2 * k + 1)
        dense = np.stack([np.convolve(pad[:, i], kernel, mode="valid") for i in range(2)], axis=1)
        roads.append(
            {
                "pts": dense,
                "width": float(rng.uniform(40, 80)),
                "walk": float(rng.uniform(8, 16)),
                "driven": kind != "d" or rng.random() < 0.5,
            }
        )
    return roads


def _build_world(seed: int, size: tuple[int, int]) -> _World:
    h, w = int(size[0]), int(size[1])
    if h < 64 or w < 64:
        raise ValueError(f"scene size must be at least 64x64, got {size}")
    rng = np.random.default_rng(seed)
    shape = (h, w)
    labels = np.full(shape, SOIL, np.uint8)
    height = np.zeros(shape, np.float32)

    fine = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), 0.7)
    fine /= fine.std() + 1e-6
    medium = _fbm(rng, shape, [10, 5])
    coarse = _fbm(rng, shape, [160, 60])

    # Grass and open ground.
    labels[_fbm(rng, shape, [220, 90, 40]) > -0.2] = GRASS
    height += 0.08 * coarse  # gentle terrain roughness

    # Roads, sidewalks, lane marks.
    roads = _make_roads(rng, h, w)
    walk = np.zeros(shape, np.uint8)
    road = np.zeros(shape, np.uint8)
    marks = np.zeros(shape, np.uint8)
    for r in roads:
        poly = _poly_int(r["pts"])
        cv2.polylines(walk, [poly], False, 1, int(r["width"] + 2 * r["walk"]))
        cv2.polylines(road, [poly], False, 1, int(r["width"]))
    for r in roads:
        pts, tan = r["pts"], _tangents(r["pts"])
        normal = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
        s = np.arange(len(pts)) * 4.0
        dash = (s % 60.0) < 30.0
        edges = np.flatnonzero(np.diff(dash.astype(np.int8)) != 0) + 1
        for seg in np.split(np.arange(len(pts)), edges):
            if len(seg) > 1 and dash[seg[0]]:
                cv2.polylines(marks, [_poly_int(pts[seg])], False, 1, 3)
        for side in (-1.0, 1.0):
            edge = pts + side * (r["width"] / 2.0 - 5.0) * normal
            cv2.polylines(marks, [_poly_int(edge)], False, 1, 2)
    marks &= road
    labels[walk > 0] = SIDEWALK
    labels[road > 0] = ROAD
    labels[marks > 0] = MARK
    height[walk > 0] = 0.15 * (road[walk > 0] == 0)  # kerb

    # Road direction lookup for aligning buildings and parking cars.
    all_pts = np.concatenate([r["pts"] for r in roads])
    all_tan = np.concatenate([_tangents(r["pts"]) for r in roads])
    inside = (all_pts[:, 0] > -50) & (all_pts[:, 0] < w + 50) & (all_pts[:, 1] > -50) & (all_pts[:, 1] < h + 50)
    all_pts, all_tan = all_pts[inside], all_tan[inside]

    # Buildings.
    blocked = cv2.dilate(walk, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (25, 25)))
    roof_rgb = np.zeros((h, w, 3), np.float32)
    n_try = int(90 * h * w / 1024**2) + 5
    for _ in range(n_try):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        nearest = int(np.argmin((all_pts[:, 0] - cx) ** 2 + (all_pts[:, 1] - cy) ** 2))
        ang = math.atan2(all_tan[nearest, 1], all_tan[nearest, 0])
        if rng.random() < 0.5:
            ang += math.pi / 2
        if rng.random() < 0.15:
            ang = rng.uniform(0, math.pi)
        length, width = rng.uniform(70, 190), rng.uniform(55, 120)
        corners = _box(cx, cy, length, width, ang)
        x0, y0 = np.floor(corners.min(0)).astype(int) - 1
        x1, y1 = np.ceil(corners.max(0)).astype(int) + 2
        x0c, y0c, x1c, y1c = max(0, x0), max(0, y0), min(w, x1), min(h, y1)
        if x1c - x0c < 10 or y1c - y0c < 10:
            continue
        poly = np.zeros((y1c - y0c, x1c - x0c), np.uint8)
        cv2.fillPoly(poly, [_poly_int(corners - [x0c, y0c])], 1)
        sel = poly > 0
        if blocked[y0c:y1c, x0c:x1c][sel].any():
            continue
        hb = float(rng.uniform(4.0, 22.0))
        yy, xx = np.mgrid[y0c:y1c, x0c:x1c].astype(np.float32)
        v = -(xx - cx) * math.sin(ang) + (yy - cy) * math.cos(ang)  # across the long axis
        roof = np.full(poly.shape, hb, np.float32)
        if rng.random() < 0.5:  # gabled roof, ridge along the long axis
            roof += rng.uniform(1.5, 3.5) * (1.0 - np.abs(v) / (width / 2.0))
        colour = _ROOF_COLOURS[rng.integers(len(_ROOF_COLOURS))] * rng.uniform(0.85, 1.15)
        lab = labels[y0c:y1c, x0c:x1c]
        lab[sel] = BUILDING
        height[y0c:y1c, x0c:x1c][sel] = roof[sel]
        roof_rgb[y0c:y1c, x0c:x1c][sel] = colour
        blk = blocked[y0c:y1c, x0c:x1c]
        blk |= cv2.dilate(poly, np.ones((25, 25), np.uint8))

    # Trees: clusters in open areas plus street trees.
    tree_var = np.zeros(shape, np.float32)
    centres = []
    n_clusters = int(rng.integers(6, 12) * h * w / 1024**2) + 1
    for _ in range(n_clusters):
        ccx, ccy = rng.uniform(0, w), rng.uniform(0, h)
        spread = rng.uniform(20, 90)
        for _ in range(int(rng.integers(3, 14))):
            centres.append((ccx + rng.normal(0, spread), ccy + rng.normal(0, spread), rng.uniform(10, 28)))
    for r in roads:
        if rng.random() < 0.6:
            pts, tan = r["pts"], _tangents(r["pts"])
            side = rng.choice([-1.0, 1.0])
            off = r["width"] / 2.0 + r["walk"] + rng.uniform(6, 14)
            spacing = int(rng.integers(18, 30))  # in dense steps of 4 px
            for i in range(int(rng.integers(0, spacing)), len(pts), spacing):
                p = pts[i] + side * off * np.array([-tan[i, 1], tan[i, 0]])
                centres.append((p[0], p[1], rng.uniform(9, 18)))
    for tx, ty, rad in centres:
        ix, iy = int(round(tx)), int(round(ty))
        if not (0 <= ix < w and 0 <= iy < h) or labels[iy, ix] in (BUILDING, ROAD, MARK):
            continue
        ht = float(rng.uniform(4.0, 14.0))
        r = int(math.ceil(rad))
        x0, x1, y0, y1 = max(0, ix - r), min(w, ix + r + 1), max(0, iy - r), min(h, iy + r + 1)
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
        d2 = ((xx - tx) ** 2 + (yy - ty) ** 2) / (rad * rad)
        lobes = 1.0 + 0.18 * medium[y0:y1, x0:x1]
        canopy = ht * np.sqrt(np.clip(lobes - d2, 0.0, None))
        sel = canopy > 0.2
        lab = labels[y0:y1, x0:x1]
        hgt = height[y0:y1, x0:x1]
        on = sel & (canopy > hgt)
        lab[on] = TREE
        hgt[on] = canopy[on]
        tree_var[y0:y1, x0:x1][on] = rng.random()

    # Parked cars along the road edges.
    cars: list[_Car] = []
    for r in roads:
        pts, tan = r["pts"], _tangents(r["pts"])
        for side in (-1.0, 1.0):
            off = r["width"] / 2.0 - 12.0
            i = int(rng.integers(0, 15))
            while i < len(pts):
                if rng.random() < 0.2:
                    p = pts[i] + side * off * np.array([-tan[i, 1], tan[i, 0]])
                    if 0 <= p[0] < w and 0 <= p[1] < h:
                        ang = math.atan2(tan[i, 1], tan[i, 0]) + rng.normal(0, 0.04)
                        cars.append(_Car(float(p[0]), float(p[1]), ang, int(rng.integers(len(_CAR_COLOURS)))))
                    i += int(rng.integers(12, 16))
                else:
                    i += int(rng.integers(6, 20))
    # The satellite was taken another day: some cars left, some moved, a few new.
    cars_sat = []
    for c in cars:
        u = rng.random()
        if u < 0.3:
            continue
        if u < 0.45:
            shift = rng.uniform(20, 70) * rng.choice([-1.0, 1.0])
            c = _Car(c.x + shift * math.cos(c.angle), c.y + shift * math.sin(c.angle), c.angle, c.colour)
        cars_sat.append(c)
    for _ in range(max(1, len(cars) // 8)):
        r = roads[int(rng.integers(len(roads)))]
        i = int(rng.integers(len(r["pts"])))
        tan = _tangents(r["pts"])[i]
        p = r["pts"][i] + rng.choice([-1.0, 1.0]) * (r["width"] / 2 - 12) * np.array([-tan[1], tan[0]])
        if 0 <= p[0] < w and 0 <= p[1] < h:
            cars_sat.append(
                _Car(
                    float(p[0]),
                    float(p[1]),
                    math.atan2(tan[1], tan[0]),
                    int(rng.integers(len(_CAR_COLOURS))),
                )
            )

    # Robot path: the right-hand lane of the driven roads.
    # Each driven road is driven over a random stretch (at least half of it).
    path_img = np.zeros(shape, np.uint8)
    viewpoints = []
    for r in roads:
        if not r["driven"]:
            continue
        pts, tan = r["pts"], _tangents(r["pts"])
        lane = pts + (r["width"] / 4.0) * np.stack([-tan[:, 1], tan[:, 0]], axis=1)
        n = len(lane)
        keep = int(n * rng.uniform(0.5, 1.0))
        start = int(rng.integers(0, n - keep + 1))
        lane = lane[start : start + keep]
        cv2.polylines(path_img, [_poly_int(lane)], False, 1, 1)
        vp = lane[::10]  # every 40 px
        vp = vp[(vp[:, 0] >= 0) & (vp[:, 0] < w) & (vp[:, 1] >= 0) & (vp[:, 1] < h)]
        viewpoints.append(vp)
    path_dist = cv2.distanceTransform((path_img == 0).astype(np.uint8), cv2.DIST_L2, 5)
    return _World(
        labels,
        height,
        roof_rgb,
        tree_var,
        fine,
        medium,
        coarse,
        path_dist.astype(np.float32),
        np.concatenate(viewpoints),
        cars,
        cars_sat,
    )


def _with_cars(world: _World, cars: list[_Car]):
    labels = world.labels.copy()
    height = world.height.copy()
    car_rgb = np.zeros(labels.shape + (3,), np.float32)
    glass = np.zeros(labels.shape, np.uint8)
    for c in cars:
        body = _poly_int(_box(c.x, c.y, 44, 19, c.angle))
        cv2.fillPoly(labels, [body], CAR)
        cv2.fillPoly(height, [body], 1.5)
        cv2.fillPoly(car_rgb, [body], _CAR_COLOURS[c.colour].tolist())
        # Windscreen band.
        fx, fy = c.x + 7 * math.cos(c.angle), c.y + 7 * math.sin(c.angle)
        cv2.fillPoly(glass, [_poly_int(_box(fx, fy, 7, 16, c.angle))], 1)
    return labels, height, car_rgb, glass > 0


# --------------------------------------------------------------------------------------
# renderers


def _render_rgb(
    world: _World,
    cars: list[_Car],
    palette: Mapping[int, Sequence[float]],
    tree_colours: tuple[Sequence[float], Sequence[float]],
    sun: tuple[float, float],
    rng: np.random.Generator,
) -> np.ndarray:
    labels, height, car_rgb, glass = _with_cars(world, cars)
    h, w = labels.shape
    rgb = np.zeros((h, w, 3), np.float32)
    for cls, col in palette.items():
        rgb[labels == cls] = col
    t0, t1 = np.asarray(tree_colours[0], np.float32), np.asarray(tree_colours[1], np.float32)
    tree = labels == TREE
    v = world.tree_var[tree][:, None]
    rgb[tree] = t0 * (1 - v) + t1 * v
    bld = labels == BUILDING
    rgb[bld] = world.roof_rgb[bld]
    car = labels == CAR
    rgb[car] = car_rgb[car]
    rgb[glass & car] *= 0.35

    fine, medium, coarse = world.fine, world.medium, world.coarse
    amp_fine = np.select(
        [labels == GRASS, labels == SOIL, labels == TREE, labels == BUILDING],
        [0.16, 0.12, 0.10, 0.03],
        0.05,
    ).astype(np.float32)
    amp_med = np.select([labels == GRASS, labels == SOIL, labels == TREE], [0.10, 0.12, 0.22], 0.02).astype(np.float32)
    amp_coarse = np.select([labels == GRASS, labels == SOIL, labels == ROAD], [0.12, 0.10, 0.05], 0.0).astype(
        np.float32
    )
    tex = 1.0 + amp_fine * fine + amp_med * medium + amp_coarse * coarse
    rgb *= tex[..., None]

    az, el = sun
    rgb *= _hillshade(height, az, el)[..., None]
    shadow = _cast_shadow(height, az, el)[..., None]
    rgb *= 1.0 - shadow * np.array([0.58, 0.55, 0.47], np.float32)
    rgb += rng.normal(0, 0.012, rgb.shape).astype(np.float32)
    return rgb


def _render_lidar(world: _World, rng: np.random.Generator):
    labels, height, _, _ = _with_cars(world, world.cars)
    h, w = labels.shape
    max_range = float(rng.uniform(250, 350))
    refl = np.array([0.36, 0.50, 0.44, 0.20, 0.92, 0.85, 0.68, 0.60], np.float32)[labels]
    refl *= 1.0 + 0.22 * world.fine + 0.08 * world.medium
    refl[labels == CAR] += 0.35 * (world.fine[labels == CAR] > 1.5)  # retro-reflectors

    bld = (labels == BUILDING).astype(np.uint8)
    interior = cv2.erode(bld, np.ones((3, 3), np.uint8), iterations=2) > 0
    occluder = bld.astype(bool)
    vis = _visibility(occluder, world.viewpoints, max_range)
    d = world.path_dist / max_range
    cover = vis & (d <= 1.0) & ~interior

    density = np.clip(1.05 - d**1.6, 0.12, 1.0)
    density[labels == TREE] *= 0.6
    wall = (labels == BUILDING) & cover  # outlines facing the robot, hit by many scans
    density[wall] = 0.95
    refl[wall] = 0.95
    keep = rng.random((h, w), dtype=np.float32) < density
    inten = refl * (1.0 - 0.35 * d) + rng.normal(0, 0.05, (h, w)).astype(np.float32)
    lidar = np.where(cover & keep, np.clip(inten, 0.02, 1.0) * 255.0, 0.0)
    return np.round(lidar).astype(np.uint8), cover


def _render_stereo(world: _World, rng: np.random.Generator):
    labels, height, _, _ = _with_cars(world, world.cars)
    h, w = labels.shape
    max_range = float(rng.uniform(150, 220))
    bld = (labels == BUILDING).astype(np.uint8)
    interior = cv2.erode(bld, np.ones((3, 3), np.uint8), iterations=4) > 0
    vis = _visibility(bld.astype(bool), world.viewpoints, max_range)
    d = world.path_dist / max_range
    cover = vis & (d <= 1.0) & ~interior
    # Holes: low-texture surfaces (roads) and matching failures.
    holes_n = _fbm(rng, (h, w), [24, 10])
    holes = holes_n > np.where(labels == ROAD, 0.5, 1.3)
    holes |= rng.random((h, w), dtype=np.float32) < 0.03
    sigma = 0.15 + 1.2 * d**2
    elev = height + sigma * rng.standard_normal((h, w)).astype(np.float32)
    elev = cv2.GaussianBlur(elev, (0, 0), 1.8)
    grey = STEREO_GROUND + np.clip(elev, 0, STEREO_MAX_M) * ((255.0 - STEREO_GROUND) / STEREO_MAX_M)
    valid = cover & ~holes
    valid = cv2.morphologyEx(valid.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
    stereo = np.where(valid, np.clip(grey, 1, 255), 0)
    return np.round(stereo).astype(np.uint8), valid


def _to_u8(rgb: np.ndarray) -> np.ndarray:
    return np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def generate_scene(seed: int = 0, size: tuple[int, int] = (1024, 1024)) -> dict[str, np.ndarray]:
    """Generate one co-registered procedural scene (see the module docstring).

    Args:
        seed: the scene is a pure function of ``seed`` and ``size``.
        size: ``(H, W)`` in pixels (0.1 m/pixel nominal).

    Returns:
        ``{"lidar": (H, W) uint8, "stereo": (H, W) uint8, "drone": (H, W, 3) uint8 RGB,
        "satellite": (H, W, 3) uint8 RGB, "lidar_mask": (H, W) uint8, "stereo_mask":
        (H, W) uint8}``; masks are 255 where the ground robot observed, 0 where no data.
    """
    world = _build_world(seed, size)
    h, w = world.labels.shape
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 1])

    lidar, lidar_cover = _render_lidar(world, rng)
    stereo, stereo_valid = _render_stereo(world, rng)

    sun_az, sun_el = float(rng.uniform(0, 360)), float(rng.uniform(35, 60))
    drone_palette = {
        SOIL: (0.56, 0.48, 0.37),
        GRASS: (0.30, 0.45, 0.19),
        SIDEWALK: (0.66, 0.65, 0.62),
        ROAD: (0.31, 0.31, 0.33),
        MARK: (0.93, 0.93, 0.90),
    }
    drone = _render_rgb(
        world,
        world.cars,
        drone_palette,
        ((0.13, 0.30, 0.10), (0.24, 0.38, 0.13)),
        (sun_az, sun_el),
        rng,
    )

    sat_az = sun_az + rng.choice([-1.0, 1.0]) * rng.uniform(70, 180)
    sat_el = float(rng.uniform(28, 65))
    sat_palette = {
        SOIL: (0.62, 0.53, 0.40),
        GRASS: (0.55, 0.52, 0.30),
        SIDEWALK: (0.72, 0.70, 0.67),
        ROAD: (0.42, 0.41, 0.43),
        MARK: (0.80, 0.80, 0.77),
    }
    sat = _render_rgb(
        world,
        world.cars_satellite,
        sat_palette,
        ((0.25, 0.32, 0.12), (0.58, 0.36, 0.14)),
        (sat_az, sat_el),
        rng,
    )
    # Sensor: lower resolution, colour cast and haze.
    small = cv2.resize(sat, (max(1, w // 3), max(1, h // 3)), interpolation=cv2.INTER_AREA)
    sat = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    sat = sat * np.array([1.04, 1.0, 0.93], np.float32) * 0.92 + 0.06
    # Semi-transparent clouds and their shadows.
    cloud_n = _fbm(rng, (h, w), [300, 120, 50])
    alpha = np.clip((cloud_n - rng.uniform(0.6, 1.2)) * 0.8, 0.0, 0.7)
    off = (int(rng.integers(-60, 61)), int(rng.integers(-60, 61)))
    shade = np.zeros_like(alpha)
    _shift_max(shade, alpha, off[0], off[1], 0.0)
    sat *= (1.0 - 0.4 * shade)[..., None]
    sat = sat * (1.0 - alpha[..., None]) + alpha[..., None] * np.array([0.93, 0.94, 0.96], np.float32)
    sat_u8 = _to_u8(sat)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(sat_u8, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 55])
    sat_u8 = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)

    return {
        "lidar": lidar,
        "stereo": stereo,
        "drone": _to_u8(drone),
        "satellite": sat_u8,
        "lidar_mask": (lidar_cover.astype(np.uint8) * 255),
        "stereo_mask": (stereo_valid.astype(np.uint8) * 255),
    }


def scene_truth(seed: int = 0, size: tuple[int, int] = (1024, 1024)) -> dict[str, np.ndarray]:
    """The world that :func:`generate_scene` (same ``seed`` and ``size``) renders: what a
    perfect feature extractor could recover from each modality, for diagnostics.

    Returns:
        ``{"labels": (H, W) uint8, "height": (H, W) float32}`` with the parked cars the
        ground robot and the drone see, and ``"labels_satellite"``, ``"height_satellite"``
        with the satellite's (a few missing, moved or added). Labels are the classes
        ``SOIL, GRASS, SIDEWALK, ROAD, MARK, BUILDING, TREE, CAR = 0..7``; heights in metres.
    """
    world = _build_world(seed, size)
    labels, height, _, _ = _with_cars(world, world.cars)
    labels_sat, height_sat, _, _ = _with_cars(world, world.cars_satellite)
    return {"labels": labels, "height": height, "labels_satellite": labels_sat, "height_satellite": height_sat}


# --------------------------------------------------------------------------------------
# writing


def _write_png(path: Path, image: np.ndarray) -> None:
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"could not encode {path}")
    path.write_bytes(buf.tobytes())


def write_scene(
    root: str | Path,
    name: str,
    scene: Mapping[str, np.ndarray],
    regions: Mapping[str, Sequence[Sequence[float]]] | None = None,
) -> Path:
    """Write ``scene`` (as returned by :func:`generate_scene`) to ``root/name/``.

    Writes ``<modality>.png`` for each of lidar, stereo, drone, satellite present in
    ``scene`` (RGB arrays are stored as colour PNGs), ``<modality>_mask.png`` for the masks
    present, and ``regions.json`` if ``regions`` (``{"train": [[x0, y0, x1, y1], ...], ...}``)
    is given. Returns the scene folder.
    """
    folder = Path(root) / name
    folder.mkdir(parents=True, exist_ok=True)
    written = 0
    for key in MODALITIES + tuple(f"{m}_mask" for m in MODALITIES):
        if key in scene:
            _write_png(folder / f"{key}.png", np.asarray(scene[key]))
            written += 1
    if written == 0:
        raise ValueError(f"scene has none of the keys {MODALITIES}; got {sorted(scene)}")
    if regions is not None:
        lines = [
            f"  {json.dumps(str(k))}: {json.dumps([[int(round(v)) for v in r] for r in rects])}"
            for k, rects in regions.items()
        ]
        (folder / "regions.json").write_text("{\n" + ",\n".join(lines) + "\n}\n")
    return folder


def _scene_name(i: int) -> str:
    letters = ""
    i += 1
    while i > 0:
        i, r = divmod(i - 1, 26)
        letters = chr(ord("a") + r) + letters
    return f"scene_{letters}"


def scene_index(name: str) -> int:
    """The index ``i`` of :func:`make_dataset`'s scene ``name`` (``scene_a`` -> 0, ``scene_af`` -> 31)."""
    letters = name.removeprefix("scene_")
    if not name.startswith("scene_") or not letters or not all("a" <= c <= "z" for c in letters):
        raise ValueError(f"{name!r} is not a scene name of make_dataset (scene_a, scene_b, ...)")
    i = 0
    for c in letters:
        i = 26 * i + ord(c) - ord("a") + 1
    return i - 1


def scene_seed(dataset_seed: int, index: int) -> int:
    """The :func:`generate_scene` seed of scene ``index`` of ``make_dataset(seed=dataset_seed)``."""
    return int(np.random.SeedSequence([int(dataset_seed) & 0xFFFFFFFF, int(index)]).generate_state(1)[0])


_README = """\
Procedural Aero-Ground style data set (dpcn.data.scene.make_dataset, seed {seed}).

Layout (read by dpcn.data.aeroground.MapPairs):
  <scene>/lidar.png, stereo.png       ground-robot maps (grey), 0.1 m/pixel
  <scene>/drone.png, satellite.png    aerial maps (RGB), same size, co-registered
  <scene>/lidar_mask.png, stereo_mask.png   255 = observed by the robot, 0 = no data
  <scene>/regions.json  {{"train": [[x0, y0, x1, y1], ...], "val": [...], "test": [...]}}
      pixel rectangles from which crop centres are drawn; here train = x < {split},
      val = test = x >= {split} + {gap} (a gap of {gap} px keeps crops of the two apart).
Scenes: {scenes}. Size (H, W): {size}.
"""


# Crop centres of the two splits this far apart never share a pixel: with 256 px crops,
# +-50 px, any rotation and scales >= 0.8, a pair reaches (hypot(128, 128) + 50 sqrt(2)) / 0.8
# = 315 px from its crop centre.
SPLIT_GAP = 630


def make_dataset(
    out: str | Path,
    n_scenes: int = 8,
    seed: int = 0,
    size: tuple[int, int] = (1280, 2560),
    train_fraction: float = 0.6,
    gap: int = SPLIT_GAP,
) -> Path:
    """Generate ``n_scenes`` scenes (``scene_a``, ``scene_b``, ...) under ``out``.

    Each scene gets ``regions.json`` (regions bound crop *centres*): ``train`` = the left
    ``train_fraction`` of the width minus ``gap``, ``val`` = ``test`` = the rest right of
    the gap. With the default gap (:data:`SPLIT_GAP`) training and validation crops of the
    default pose ranges never overlap: validation measures a held-out area, as in the paper.
    Crop centres also keep ~315 px from the raster border, so each split needs room.
    Also writes ``README.txt``. Returns ``out``.
    """
    if n_scenes < 1:
        raise ValueError(f"n_scenes must be >= 1, got {n_scenes}")
    if not 0.0 < train_fraction < 1.0:
        raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")
    h, w = int(size[0]), int(size[1])
    if gap < 0 or (gap > 0 and w < 2 * gap):
        raise ValueError(
            f"the split gap ({gap} px) must be >= 0 and at most half the scene width ({w} px): "
            "use a wider scene or a smaller gap (0: adjacent train and val areas)"
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    split = max(1, int(round(train_fraction * (w - gap))))
    regions = {"train": [[0, 0, split, h]], "val": [[split + gap, 0, w, h]], "test": [[split + gap, 0, w, h]]}
    names = []
    for i in range(n_scenes):
        name = _scene_name(i)
        write_scene(out, name, generate_scene(scene_seed(seed, i), (h, w)), regions)
        names.append(name)
    (out / "README.txt").write_text(
        _README.format(seed=seed, split=split, gap=gap, scenes=", ".join(names), size=(h, w))
    )
    return out
