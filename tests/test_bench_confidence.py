"""The confidence-ranking benchmark: exact statistics, a real run on scenes on disk, bad input."""

import math

import pytest
import torch

from dpcn.data.scene import make_dataset

from .conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_confidence")


def test_ranking_auc_counts_ordered_pairs(bench):
    correct = torch.tensor([True, False, True, False])
    confidence = torch.tensor([0.9, 0.5, 0.4, 0.1])
    # (good, bad) pairs: (0.9, 0.5), (0.9, 0.1), (0.4, 0.1) ordered, (0.4, 0.5) not: 3 of 4
    assert bench.ranking_auc(correct, confidence) == pytest.approx(0.75)
    assert bench.ranking_auc(correct, -confidence) == pytest.approx(0.25)
    assert bench.ranking_auc(correct, torch.ones(4)) == pytest.approx(0.5)  # ties count half
    assert math.isnan(bench.ranking_auc(torch.ones(3, dtype=torch.bool), torch.rand(3)))


def test_most_confident_keeps_the_top_fraction(bench):
    correct = torch.tensor([True, True, False, True, False])
    confidence = torch.tensor([0.6, 0.9, 0.7, 0.8, 0.1])
    rows = bench.most_confident(correct, confidence, [1.0, 0.6, 0.2])
    assert [(f, n) for f, n, _, _ in rows] == [(1.0, 5), (0.6, 3), (0.2, 1)]
    assert [lowest for _, _, lowest, _ in rows] == pytest.approx([0.1, 0.7, 0.9])
    assert [rate for *_, rate in rows] == pytest.approx([60.0, 200.0 / 3.0, 100.0])


def test_classical_run_prints_consistent_rows(bench, tmp_path, capsys):
    root = make_dataset(tmp_path / "maps", n_scenes=3, seed=3, size=(720, 720), gap=0)
    overrides = [f"data.root={root}", "image_size=96", "data.dataset.translation=20", "data.test_length=20"]
    bench.main(["--data", "l2d", "--stages", "test", "--keep", "1,0.5", "--", *overrides])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("classical on l2d")
    rows = [line[18:].split() for line in lines[2:4]]
    assert [row[:2] for row in rows] == [["100%", "20"], ["50%", "10"]]
    assert float(rows[0][2]) <= float(rows[1][2])  # the cut's confidence rises as fewer are kept
    assert all(0.0 <= float(row[3]) <= 100.0 for row in rows)
    auc = lines[4].split("AUC")[1]
    assert auc.strip() == "nan" or 0.0 <= float(auc) <= 1.0


def test_bad_arguments_are_refused(bench):
    for keep in ("0", "1.5", "a,b", ""):
        with pytest.raises(SystemExit):
            bench.main(["--keep", keep])
    with pytest.raises(SystemExit):
        bench.main(["--stages", "fit"])
    with pytest.raises(SystemExit, match="checkpoint not found: /nonexistent.ckpt"):
        bench.main(["--checkpoint", "/nonexistent.ckpt"])
