"""The paper's metrics (eq. 15-16): accuracy within a threshold and mean squared error.

Errors are per pair: ``|dx|``, ``|dy|`` in pixels, the rotation error in degrees wrapped to
``[0, 180]``, and ``|d scale|`` (absolute, as in the paper's tables).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor

__all__ = [
    "COMPONENTS",
    "CURVE_THRESHOLDS",
    "PAIR_COLUMNS",
    "accuracy_curve",
    "pose_errors",
    "summarize",
    "format_table",
    "write_csv",
    "read_curve_csv",
    "write_curve_csv",
    "write_pairs_csv",
    "thresholds_for",
]

COMPONENTS = ("x", "y", "rot", "scale")
# One evaluated pair: the true pose, the estimate, its confidence and the errors (pixels, degrees).
PAIR_COLUMNS = (
    "pair", "tx", "ty", "angle", "scale", "pred_tx", "pred_ty", "pred_angle", "pred_scale",
    "confidence", "err_x", "err_y", "err_rot", "err_scale",
)  # fmt: skip


# Thresholds of the accuracy curves (the paper's appendix plots Acc at 0 to 19 px): every table
# threshold of both data kinds lies on them (x, y 1, 5, 10 px; rotation 0.5, 1 deg; scale 0.02, 0.2).
CURVE_THRESHOLDS: dict[str, tuple[float, ...]] = {
    "x": tuple(float(t) for t in range(20)),
    "y": tuple(float(t) for t in range(20)),
    "rot": tuple(round(0.1 * t, 1) for t in range(21)),
    "scale": tuple(round(0.01 * t, 2) for t in range(21)),
}


def thresholds_for(translation_px: float = 5.0) -> dict[str, dict[str, float]]:
    """The paper's thresholds (``translation_px``: 5 for simulation, 10 for Aero-Ground) and strict ones."""
    return {
        "paper": {"x": translation_px, "y": translation_px, "rot": 1.0, "scale": 0.2},
        "strict": {"x": 1.0, "y": 1.0, "rot": 0.5, "scale": 0.02},
    }


def pose_errors(prediction: Tensor, truth: Tensor) -> Tensor:
    """``(N, 4)`` absolute errors of ``(N, 4)`` ``(tx, ty, angle, scale)`` poses."""
    err = (prediction.double() - truth.double()).abs()
    d_angle = torch.remainder(prediction[:, 2].double() - truth[:, 2].double() + 180.0, 360.0) - 180.0
    err[:, 2] = d_angle.abs()
    return err


def _percent_within(errors: Tensor, limit: float) -> float:
    """Acc in % of one component's errors: within means ``<= limit`` (NaN: outside)."""
    return 100.0 * float((errors <= limit).double().mean())


def summarize(errors: Tensor, thresholds: Mapping[str, Mapping[str, float]]) -> dict[str, float]:
    """``{"acc_x@5": %, ..., "mse_x": ...}`` for ``(N, 4)`` errors."""
    out: dict[str, float] = {}
    for i, name in enumerate(COMPONENTS):
        for limit in sorted({t[name] for t in thresholds.values()}, reverse=True):
            out[f"acc_{name}@{limit:g}"] = _percent_within(errors[:, i], limit)
        out[f"mse_{name}"] = float((errors[:, i] ** 2).mean())
    out["n"] = float(errors.shape[0])
    return out


def accuracy_curve(
    errors: Tensor, thresholds: Mapping[str, Sequence[float]] = CURVE_THRESHOLDS
) -> list[tuple[str, float, float]]:
    """Accuracy against threshold, the paper's appendix plots: ``(component, threshold, Acc
    in %)`` rows for ``(N, 4)`` :func:`pose_errors` (a tensor or an array), per component of ``thresholds`` (pixels,
    degrees, absolute scale) in their order; an error equal to the threshold counts as within.
    A NaN error (a failed estimate) counts as outside every threshold."""
    errors = torch.as_tensor(errors)
    if errors.ndim != 2 or errors.shape[1] != len(COMPONENTS) or errors.shape[0] == 0:
        raise ValueError(f"errors must be (N, 4) with N >= 1, got {tuple(errors.shape)}")
    unknown = set(thresholds) - set(COMPONENTS)
    if unknown:
        raise ValueError(f"unknown components {sorted(unknown)}; expected some of {list(COMPONENTS)}")
    rows = []
    for name, limits in thresholds.items():
        try:
            values = None if isinstance(limits, str) else [float(limit) for limit in limits]
        except (TypeError, ValueError):
            values = None
        if values is None or not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError(f"thresholds of {name} must be a list of finite numbers >= 0, got {limits!r}")
        column = errors[:, COMPONENTS.index(name)]
        rows.extend((name, limit, _percent_within(column, limit)) for limit in values)
    return rows


def format_table(rows: Sequence[tuple[str, Mapping[str, float]]]) -> str:
    """Plain-text table, one row per method/data set, columns as in the paper's tables."""
    if not rows:
        return ""
    keys = [k for k in rows[0][1] if k != "n"]
    width = max(len(name) for name, _ in rows)
    lines = [f"{'':{width}s} " + " ".join(f"{k:>12s}" for k in keys) + f" {'n':>6s}"]
    for name, metrics in rows:
        cells = []
        for k in keys:
            value = metrics[k]
            cells.append(f"{value:12.2f}" if k.startswith("acc") else f"{value:12.4g}")
        lines.append(f"{name:{width}s} " + " ".join(cells) + f" {int(metrics.get('n', 0)):6d}")
    return "\n".join(lines)


def write_csv(path: str | Path, rows: Sequence[tuple[str, Mapping[str, float]]]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = list(rows[0][1])
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["name", *keys])
        for name, metrics in rows:
            writer.writerow([name, *(metrics[k] for k in keys)])
    return path


def write_curve_csv(path: str | Path, curve: Sequence[tuple[str, float, float]]) -> Path:
    """:func:`accuracy_curve` rows as a CSV of ``component, threshold, acc``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["component", "threshold", "acc"])
        writer.writerows((name, f"{limit:g}", f"{acc:.4f}") for name, limit, acc in curve)
    return path


def read_curve_csv(path: str | Path) -> list[tuple[str, float, float]]:
    """The rows of an ``accuracy_<stage>.csv`` (:func:`write_curve_csv`): ``(component,
    threshold, Acc in %)``. ``ValueError`` naming the file and the row for anything else."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"accuracy curve not found: {path}")
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header != ["component", "threshold", "acc"]:
            raise ValueError(f"{path}: not an accuracy curve (header {header}, expected component,threshold,acc)")
        rows = []
        for line, row in enumerate(reader, start=2):
            try:
                name, limit, acc = row
                value = (name, float(limit), float(acc))
            except ValueError:
                raise ValueError(f"{path}, row {line}: expected component,threshold,acc, got {row}") from None
            if name not in COMPONENTS or not (math.isfinite(value[1]) and 0.0 <= value[2] <= 100.0):
                expected = f"a component of {', '.join(COMPONENTS)}, a finite threshold and an Acc in [0, 100]"
                raise ValueError(f"{path}, row {line}: expected {expected}, got {row}")
            rows.append(value)
    if not rows:
        raise ValueError(f"{path}: no rows")
    return rows


def write_pairs_csv(
    path: str | Path,
    truth: Tensor,
    prediction: Tensor,
    confidence: Tensor | None,
    names: Sequence[str] | None = None,
) -> Path:
    """Every evaluated pair as a row of :data:`PAIR_COLUMNS`: ``(N, 4)`` true and estimated
    ``(tx, ty, angle, scale)`` poses, ``(N,)`` confidences (empty cells without), and their
    :func:`pose_errors`; ``pair`` is the index in the data set, and ``names`` (one per pair,
    e.g. a pre-cut CSV's) adds a ``name`` column after it. For accuracy at any threshold, and
    for looking at the misses."""
    if names is not None and len(names) != truth.shape[0]:
        raise ValueError(f"{len(names)} names for {truth.shape[0]} pairs")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    errors = pose_errors(prediction, truth)
    header = list(PAIR_COLUMNS)
    if names is not None:
        header.insert(1, "name")
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for i in range(truth.shape[0]):
            conf = "" if confidence is None else f"{float(confidence[i]):.6g}"
            values = [*truth[i].tolist(), *prediction[i].tolist()]
            row = [i, *(f"{v:.6g}" for v in values), conf, *(f"{v:.6g}" for v in errors[i].tolist())]
            if names is not None:
                row.insert(1, names[i])
            writer.writerow(row)
    return path
