"""The confidence-ranking benchmark: exact statistics, a real run on scenes on disk, bad input."""

import math

import pytest
import torch

from dpcn.data.scene import make_dataset
from dpcn.training.module import load_matcher

from .conftest import load_benchmark, write_checkpoint


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


def test_split_by_ratio_counts_the_ambiguous_pairs(bench):
    correct = torch.tensor([True, False, True, True, False])
    ratio = torch.tensor([0.9, 0.7, 0.2, 0.69, 0.0])
    assert bench.split_by_ratio(correct, ratio, 0.7) == pytest.approx((2, 40.0, 50.0, 200.0 / 3.0))
    n, share, ambiguous, clear = bench.split_by_ratio(correct, ratio, 0.95)  # none ambiguous
    assert (n, share, clear) == (0, 0.0, 60.0) and math.isnan(ambiguous)


def test_stage1_peak_ratio_is_what_the_gate_reads(bench, tmp_path):
    checkpoint = write_checkpoint(tmp_path / "a.ckpt", "data=s2d", "image_size=96")
    model = load_matcher(checkpoint, rotation_hypotheses=2, hypothesis_ratio=0.5).model.eval()
    generator = torch.Generator().manual_seed(1)
    template, source = (torch.rand(4, 1, 96, 96, generator=generator) for _ in range(2))
    ratio = bench.stage1_peak_ratio(model, template, source)
    with torch.no_grad():
        score = model(template, source).rotation_scale.candidate_score  # the forward pass's own peaks
    assert ratio.shape == (4,) and bool(((ratio >= 0) & (ratio <= 1)).all())
    assert torch.allclose(ratio, score[:, 1] / score[:, 0])
    for threshold in (0.3, 0.5, 0.9):
        model.hypothesis_ratio = threshold
        assert torch.equal(ratio >= threshold, model.ambiguous_pairs(score))


def test_checkpoint_run_prints_the_stage1_split(bench, tmp_path, capsys):
    root = make_dataset(tmp_path / "maps", n_scenes=3, seed=3, size=(720, 720), gap=0)
    checkpoint = write_checkpoint(tmp_path / "a.ckpt", "data=s2d", "image_size=96")
    overrides = [f"data.root={root}", "image_size=96", "data.dataset.translation=20", "data.test_length=12"]
    arguments = ["--data", "s2d", "--checkpoint", str(checkpoint), "--stages", "test", "--keep", "1", "--ratio", "0.5"]
    bench.main([*arguments, "--", *overrides])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("DPCN (a.ckpt) on s2d")
    split = lines[4]
    assert split.startswith("held-out scene") and "second peak >= 0.5 x first" in split
    n = int(split.split("stage 1:")[1].split()[0])
    share = float(split.split("first, ")[1].split()[0])
    assert 0 <= n <= 12 and share == pytest.approx(100.0 * n / 12, abs=0.05)


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
    for ratio in ("0", "1.5", "x"):
        with pytest.raises(SystemExit):
            bench.main(["--ratio", ratio])
    with pytest.raises(SystemExit):
        bench.main(["--stages", "fit"])
    with pytest.raises(SystemExit, match="checkpoint not found: /nonexistent.ckpt"):
        bench.main(["--checkpoint", "/nonexistent.ckpt"])
