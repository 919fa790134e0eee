"""Train DPCN with the real command line, then evaluate it and the classical estimator on the same pairs.

Runs ``python -m dpcn fit`` (timed), then ``python -m dpcn validate|test`` of the best checkpoint
(selected on the validation set) and of ``model=classical`` on every evaluation set, and prints
the paper's table (Table 1 for the simulated sets, Table 2/3 for the map pairs): MSE and
accuracy within the paper's thresholds, the strict accuracies, and the time per pair.

    # Table 1 (simulation): train on heterogeneous pairs, test on heterogeneous and dynamic ones
    python benchmarks/bench_training.py --data sim_heterogeneous --evaluate sim_heterogeneous,sim_dynamic
    # Table 2/3 (maps): l2sat on the built-in scenes; held-out region (validate) and held-out scene (test)
    python benchmarks/bench_training.py --data l2sat --stages validate,test   # 5 epochs: the data config's default
    # the paper's Table 1 setting (trains on the dynamic pairs the experiment picks; 4 views)
    python benchmarks/bench_training.py --evaluate sim_heterogeneous,sim_dynamic --ckpt last -- experiment=paper_table1

Everything after ``--`` is passed to ``fit`` as Hydra overrides; the evaluations repeat those of
the data (``data.*``: e.g. ``data.root=`` or ``data.builtin_scenes=``, also those an
``experiment=`` sets), ``image_size``, ``channels``, ``seed`` and the inference settings
(``rotation_views=``...). Outputs go to ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

from omegaconf import OmegaConf

from dpcn.cli import INFERENCE_KEYS

CONF = Path(__file__).resolve().parents[1] / "conf"
COLUMNS = [  # (metrics key, table header); {t} is the data set's translation threshold
    ("mse_x", "E_x"), ("acc_x@{t}", "Acc_x@{t}"), ("mse_y", "E_y"), ("acc_y@{t}", "Acc_y@{t}"),
    ("mse_rot", "E_rot"), ("acc_rot@1", "Acc_rot@1"), ("mse_scale", "E_scale"), ("acc_scale@0.2", "Acc_s@0.2"),
    ("acc_x@1", "x@1px"), ("acc_y@1", "y@1px"), ("acc_rot@0.5", "rot@0.5"), ("acc_scale@0.02", "s@0.02"),
]  # fmt: skip


# Top-level keys the evaluations repeat: what the model is built for, the seed, and the
# checkpoint's inference settings (fit ignores those; validate and test apply them).
REPEATED = ("image_size", "channels", "seed", *INFERENCE_KEYS)


def dpcn(*args: str, log: Path) -> float:
    """Run ``python -m dpcn ARGS``; stream its output to ``log``; return the wall time (s)."""
    env = {k: v for k, v in os.environ.items() if k not in ("DPCN_COMMAND",)}
    start = time.perf_counter()
    with log.open("w") as out:
        done = subprocess.run([sys.executable, "-m", "dpcn", *args], stdout=out, stderr=subprocess.STDOUT, env=env)
    if done.returncode != 0:
        sys.exit(f"python -m dpcn {' '.join(args)} failed ({done.returncode}); see {log}")
    return time.perf_counter() - start


def read_metrics(path: Path) -> dict[str, float]:
    with path.open() as f:
        row = next(csv.DictReader(f))
    return {k: float(v) for k, v in row.items() if k != "name"}


def experiment_overrides(name: str) -> list[str]:
    """``experiment=name`` spelled out as the ``key=value`` overrides its config file makes."""
    path = CONF / "experiment" / f"{name}.yaml"
    if not path.is_file():
        return []  # fit has already stopped on it, with Hydra's message
    flat: list[str] = []

    def walk(node: dict, prefix: str) -> None:
        for key, value in node.items():
            if isinstance(value, dict):
                walk(value, f"{prefix}{key}.")
            else:
                flat.append(f"{prefix}{key}={json.dumps(value)}")

    node = OmegaConf.to_container(OmegaConf.load(path))
    node.pop("defaults", None)  # the config groups it picks (data=...): fit's, and --evaluate's
    walk(node, "")
    return flat


def override_key(override: str) -> str:
    """The key a Hydra override sets (``+data.x=1`` -> ``data.x``)."""
    return override.split("=")[0].lstrip("+~")


def evaluation_overrides(overrides: list[str]) -> list[str]:
    """The fit overrides that the evaluations repeat: the image size and channels (the model is
    built for them), the seed, the checkpoint's inference settings (``rotation_views``...), and
    every ``data.`` key (where the maps are, how many built-in scenes, pose ranges,
    ``min_valid``...: the pairs evaluated must come from the data trained on), also those an
    ``experiment=`` sets (the command line's own win, as in fit). Keys of the training alone
    (``data.epoch_size``, ``data.batch_size``...) are harmless there."""

    given = {override_key(o) for o in overrides}
    expanded: list[str] = []
    for o in overrides:
        if override_key(o) == "experiment":
            expanded += [e for e in experiment_overrides(o.split("=", 1)[1]) if override_key(e) not in given]
        else:
            expanded.append(o)
    return [o for o in expanded if override_key(o) in REPEATED or override_key(o).startswith("data.")]


def trained_data(fit_dir: Path) -> str:
    """The data config a fit run trained on, as fit composed it (an experiment may pick it)."""
    config = fit_dir / ".hydra" / "config.yaml"
    if not config.is_file():
        sys.exit(f"{config} is missing (hydra.output_subdir=null?): pass --data to name the data trained on")
    return OmegaConf.load(config).data.name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--data", default=None, help="training data config (default: the config's, or the one an experiment= picks)"
    )
    parser.add_argument("--evaluate", default=None, help="data configs to evaluate, comma-separated (default: its own)")
    parser.add_argument("--stages", default="test", help="validate (held-out region/val set), test, or both")
    parser.add_argument("--ckpt", default="best", choices=["best", "last"])
    parser.add_argument("--out", default=None, help="output folder (default: outputs/bench/<data>-<time>)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for fit (after --)")
    args = parser.parse_args()
    out = Path(args.out or f"outputs/bench/{args.data or 'fit'}-{datetime.now():%Y-%m-%d_%H-%M-%S}").resolve()
    out.mkdir(parents=True, exist_ok=True)

    fit_dir = out / "fit"
    fit_args = ([f"data={args.data}"] if args.data else []) + args.overrides
    fit_seconds = dpcn("fit", *fit_args, f"hydra.run.dir={fit_dir}", log=out / "fit.log")
    trained = args.data or trained_data(fit_dir)
    ckpts = fit_dir / "checkpoints"
    best = sorted(ckpts.glob("best-*.ckpt"))
    ckpt = best[-1] if args.ckpt == "best" and best else ckpts / "last.ckpt"
    print(f"fit data={trained} {' '.join(args.overrides)}: {fit_seconds / 60:.1f} min; evaluating {ckpt.name}")

    shared = evaluation_overrides(args.overrides)
    # the checkpoint's inference settings are DPCN's: the classical command refuses them
    classical_shared = [o for o in shared if override_key(o) not in INFERENCE_KEYS]
    rows = []
    for data in (args.evaluate or trained).split(","):
        for stage in args.stages.split(","):
            for label, model, overrides in (
                ("DPCN", [f"ckpt_path={ckpt}"], shared),
                ("classical", ["model=classical"], classical_shared),
            ):
                run = out / f"{stage}-{data}-{label}"
                seconds = dpcn(
                    stage, f"data={data}", *model, *overrides, f"hydra.run.dir={run}", log=run.with_suffix(".log")
                )
                metrics = read_metrics(run / f"metrics_{stage}.csv")
                rows.append((f"{label} {data} ({'val' if stage == 'validate' else 'test'})", metrics, seconds))

    threshold = next(k.split("@")[1] for k in rows[0][1] if k.startswith("acc_x@") and k != "acc_x@1")
    header = [h.format(t=threshold) for _, h in COLUMNS]
    width = max(len(name) for name, _, _ in rows)
    print(f"{'':{width}s} " + " ".join(f"{h:>10s}" for h in header) + f" {'pairs':>6s} {'s total':>8s}")
    for name, metrics, seconds in rows:
        cells = []
        for key, _ in COLUMNS:
            value = metrics[key.format(t=threshold)]
            cells.append(f"{value:10.1f}" if key.startswith("acc") else f"{value:10.4g}")
        print(f"{name:{width}s} " + " ".join(cells) + f" {int(metrics['n']):6d} {seconds:8.1f}")
    print(f"(Acc in %, E = MSE; x, y in px, rot in degrees; thresholds {threshold} px, 1 deg, 0.2 and strict 1 px, "
          f"0.5 deg, 0.02; outputs in {out})")  # fmt: skip


if __name__ == "__main__":
    main()
