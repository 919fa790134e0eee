"""Accuracy against threshold, as the paper's appendix plots it: one panel per component.

Draws the ``accuracy_<stage>.csv`` files that ``python -m dpcn validate|test`` writes (one line
per file, labelled as given), x and y in pixels, rotation in degrees and scale, into one PNG:

    python benchmarks/plot_accuracy.py --out accuracy.png \
        "DPCN=outputs/test/<time>/accuracy_test.csv" "classical=outputs/test/<time>/accuracy_test.csv"

Each curve is ``LABEL=PATH`` (a bare ``PATH`` is labelled by its run folder). Needs matplotlib
(``pip install -e ".[bench]"``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dpcn.metrics import COMPONENTS, read_curve_csv

AXES = {"x": "x error (px)", "y": "y error (px)", "rot": "rotation error (°)", "scale": "scale error"}


def parse_curve(text: str) -> tuple[str, Path]:
    """``LABEL=PATH`` (or ``PATH``, labelled by its folder) -> ``(label, path)``."""
    label, sep, path = text.rpartition("=")
    if not sep:
        return Path(text).parent.name or text, Path(text)
    if not label or not path:
        raise argparse.ArgumentTypeError(f"a curve is LABEL=PATH or PATH, got {text!r}")
    return label, Path(path)


def plot(curves: list[tuple[str, list[tuple[str, float, float]]]], out: Path, title: str | None = None) -> Path:
    """One panel per component found in the curves, a line per curve; written to ``out``."""
    import matplotlib

    matplotlib.use("Agg")  # files only: no display needed
    from matplotlib import pyplot as plt

    components = [c for c in COMPONENTS if any(name == c for _, rows in curves for name, _, _ in rows)]
    figure, axes = plt.subplots(1, len(components), figsize=(3.6 * len(components), 3.4), squeeze=False)
    for ax, component in zip(axes[0], components, strict=True):
        for label, rows in curves:
            points = sorted((limit, acc) for name, limit, acc in rows if name == component)
            if points:
                ax.plot(*zip(*points, strict=True), marker=".", label=label)
        ax.set_xlabel(AXES[component])
        ax.set_ylim(0, 101)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("Acc (%)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize="small", frameon=False)
    if title:
        figure.suptitle(title)
    figure.tight_layout(rect=(0, 0.08, 1, 1))  # room for the legend below the panels
    figure.savefig(out, dpi=110)
    plt.close(figure)
    return out


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("curves", nargs="+", type=parse_curve, help="LABEL=PATH of an accuracy_<stage>.csv")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--title", default=None)
    args = parser.parse_args(argv)
    if not args.out.parent.is_dir():
        parser.error(f"--out {args.out}: folder {args.out.parent} does not exist")
    try:
        curves = [(label, read_curve_csv(path)) for label, path in args.curves]
    except ValueError as error:
        parser.error(str(error))
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        parser.error('needs matplotlib: pip install -e ".[bench]"')
    out = plot(curves, args.out, args.title)
    print(f"wrote {out}", file=sys.stderr)
    return out


if __name__ == "__main__":
    main()
