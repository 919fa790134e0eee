"""Classical registration benchmark: dpcn vs OpenCV Fourier-Mellin vs imreg_dft.

Real photographs bundled with scikit-image, 256x256 central crops, poses drawn uniformly
(rotation [-180, 180), scale [0.8, 1.2], translation +-50 px), source = cv2.warpAffine of the
template (the project's pose convention). Prints accuracy (share of pairs within 1 px in x
and y, 0.5 degree and 1 % scale, and each alone), median errors, and time per pair, with
the ratios between methods measured in the same run.

    python benchmarks/bench_registration.py [--pairs 400] [--batch 64] [--threads 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import torch

from dpcn import PhaseCorrelationEstimator, sample_poses
from dpcn.baselines import imreg_dft_similarity, opencv_fourier_mellin

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_inference import positive_int  # noqa: E402  (the benchmarks' argparse type for counts)

PHOTOS = (
    "astronaut", "camera", "coffee", "chelsea", "rocket", "cat", "brick", "grass",
    "gravel", "immunohistochemistry", "hubble_deep_field", "moon", "page", "text", "coins", "horse",
)  # fmt: skip


def load_photos(size: int = 256) -> dict[str, np.ndarray]:
    from skimage import data

    photos = {}
    for name in PHOTOS:
        image = getattr(data, name)()
        if image.ndim == 3:
            image = cv2.cvtColor(image[..., :3], cv2.COLOR_RGB2GRAY)
        image = image.astype(np.float32) / (255.0 if image.max() > 1 else 1.0)
        if min(image.shape) < size:
            continue
        top, left = (image.shape[0] - size) // 2, (image.shape[1] - size) // 2
        photos[name] = np.ascontiguousarray(image[top : top + size, left : left + size])
    return photos


def make_pairs(n: int, seed: int, size: int = 256):
    photos = load_photos(size)
    names = list(photos)
    poses = sample_poses(n, torch.Generator().manual_seed(seed), 50.0, (-180.0, 180.0), (0.8, 1.2), torch.float64)
    templates, sources, which = [], [], []
    for i in range(n):
        name = names[i % len(names)]
        m = cv2.getRotationMatrix2D((size / 2, size / 2), float(poses.angle[i]), float(poses.scale[i]))
        m[0, 2] += float(poses.tx[i])
        m[1, 2] += float(poses.ty[i])
        templates.append(photos[name])
        sources.append(cv2.warpAffine(photos[name], m, (size, size)))
        which.append(name)
    return np.stack(templates), np.stack(sources), poses.as_tensor().numpy(), which


def score(estimates: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    err = np.abs(estimates - truth)
    err[:, 2] = np.abs((estimates[:, 2] - truth[:, 2] + 180.0) % 360.0 - 180.0)
    err[:, 3] = np.abs(estimates[:, 3] / truth[:, 3] - 1.0)
    ok = (err[:, 0] <= 1) & (err[:, 1] <= 1) & (err[:, 2] <= 0.5) & (err[:, 3] <= 0.01)
    return {
        "all": 100 * ok.mean(),
        "x<=1px": 100 * (err[:, 0] <= 1).mean(),
        "y<=1px": 100 * (err[:, 1] <= 1).mean(),
        "rot<=0.5deg": 100 * (err[:, 2] <= 0.5).mean(),
        "scale<=1%": 100 * (err[:, 3] <= 0.01).mean(),
        "med_px": float(np.median(np.maximum(err[:, 0], err[:, 1]))),
        "med_deg": float(np.median(err[:, 2])),
        "med_scale%": 100 * float(np.median(err[:, 3])),
        "ok_mask": ok,
    }


def run_dpcn(templates, sources, batch: int, device: str, **options):
    estimator = PhaseCorrelationEstimator(**options).to(device)
    t = torch.from_numpy(templates)[:, None].to(device)
    s = torch.from_numpy(sources)[:, None].to(device)
    with torch.inference_mode():
        estimator(t[:batch], s[:batch])  # warm-up
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        start = time.perf_counter()
        out = [estimator(t[i : i + batch], s[i : i + batch]).as_tensor() for i in range(0, len(t), batch)]
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        elapsed = time.perf_counter() - start
    return torch.cat(out).double().cpu().numpy(), elapsed / len(t)


def run_pairwise(fn, templates, sources, limit: int | None = None):
    n = len(templates) if limit is None else min(limit, len(templates))
    start = time.perf_counter()
    out = []
    for i in range(n):
        pose = fn(templates[i], sources[i])
        out.append([float(pose.tx[0]), float(pose.ty[0]), float(pose.angle[0]), float(pose.scale[0])])
    return np.array(out), (time.perf_counter() - start) / n, n


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=positive_int, default=400)
    parser.add_argument("--batch", type=positive_int, default=64)
    parser.add_argument("--threads", type=positive_int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--window-grids", default="", help="also time dpcn with these spectrum_window_grid values, e.g. 3"
    )
    parser.add_argument(
        "--imreg-pairs", type=positive_int, default=None, help="limit imreg_dft to this many pairs (slow)"
    )
    parser.add_argument(
        "--decoupled", action="store_true", help="also dpcn with stage 1's decoupled (DPCN++) correlation"
    )
    parser.add_argument(
        "--no-radius-window",
        action="store_true",
        help="also dpcn without stage 1's log-radius Hann window (stage 1 as the paper describes it)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)

    templates, sources, truth, names = make_pairs(args.pairs, args.seed)
    print(f"{args.pairs} pairs of 256x256 crops of {len(set(names))} scikit-image photos; "
          f"rotation [-180, 180), scale [0.8, 1.2], translation +-50 px; torch threads {args.threads}, "
          f"device {args.device}")  # fmt: skip

    rows = []
    est, per_pair = run_dpcn(templates, sources, args.batch, args.device)
    rows.append((f"dpcn batched (batch {args.batch})", score(est, truth), per_pair, len(truth)))
    for grid in (int(g) for g in args.window_grids.split(",") if g):
        est_g, per_g = run_dpcn(templates, sources, args.batch, args.device, spectrum_window_grid=grid)
        rows.append((f"dpcn batched, {grid}x{grid} spectrum windows", score(est_g, truth), per_g, len(truth)))
    if args.decoupled:
        est_d, per_d = run_dpcn(templates, sources, args.batch, args.device, rotation_scale_correlation="decoupled")
        rows.append(("dpcn batched, decoupled stage 1", score(est_d, truth), per_d, len(truth)))
    n_one = min(50, args.pairs)
    if args.no_radius_window:
        est_r, per_r = run_dpcn(templates, sources, args.batch, args.device, radius_window=False)
        rows.append(("dpcn batched, no radius window", score(est_r, truth), per_r, len(truth)))
    one, per_one = run_dpcn(templates[:n_one], sources[:n_one], 1, args.device)
    rows.append(("dpcn one pair at a time", score(one, truth[:n_one]), per_one, n_one))
    cv, per_cv, n_cv = run_pairwise(opencv_fourier_mellin, templates, sources)
    rows.append(("OpenCV Fourier-Mellin", score(cv, truth[:n_cv]), per_cv, n_cv))
    try:
        import imreg_dft  # noqa: F401

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ird, per_ird, n_ird = run_pairwise(imreg_dft_similarity, templates, sources, args.imreg_pairs)
        rows.append(("imreg_dft.similarity", score(ird, truth[:n_ird]), per_ird, n_ird))
    except ModuleNotFoundError:
        print("(imreg_dft not installed: pip install imreg_dft to compare with it)")

    header = f"{'method':34s} {'pairs':>5s} {'all-ok%':>8s} {'x':>6s} {'y':>6s} {'rot':>6s} {'scale':>6s} "
    header += f"{'med px':>7s} {'med deg':>8s} {'med sc%':>8s} {'ms/pair':>8s}"
    print(header)
    for name, s, t, n in rows:
        print(
            f"{name:34s} {n:5d} {s['all']:8.1f} {s['x<=1px']:6.1f} {s['y<=1px']:6.1f} {s['rot<=0.5deg']:6.1f} "
            f"{s['scale<=1%']:6.1f} {s['med_px']:7.3f} {s['med_deg']:8.3f} {s['med_scale%']:8.3f} {1000 * t:8.2f}"
        )
    base = rows[0][2]
    print("speed-up of dpcn batched: " + ", ".join(f"{t / base:.1f}x vs {name}" for name, _, t, _ in rows[1:]))
    failed = [names[i] for i in np.flatnonzero(~rows[0][1]["ok_mask"])]
    if failed:
        print("dpcn batched misses:", ", ".join(f"{n} x{failed.count(n)}" for n in sorted(set(failed))))
    if not math.isfinite(rows[0][1]["all"]):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
