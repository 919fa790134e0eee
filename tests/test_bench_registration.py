"""The classical registration benchmark (the README's first table) runs and counts its pairs."""

import re

import numpy as np
import pytest

from .conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_registration")


def test_pairs_are_opencv_warps_of_photo_crops(bench):
    templates, sources, truth, names = bench.make_pairs(3, seed=0, size=64)
    assert templates.shape == sources.shape == (3, 64, 64) and truth.shape == (3, 4)
    assert len(set(names)) == 3 and not np.array_equal(templates[0], sources[0])


def test_score_counts_a_pair_within_every_threshold(bench):
    truth = np.array([[0.0, 0.0, 179.9, 1.0], [0.0, 0.0, 10.0, 1.0]])
    estimates = np.array([[0.9, -0.9, -179.8, 1.009], [1.1, 0.0, 10.0, 1.0]])  # wraps; then x off
    scored = bench.score(estimates, truth)
    assert scored["all"] == 50.0 and scored["x<=1px"] == 50.0 and scored["rot<=0.5deg"] == 100.0
    assert scored["ok_mask"].tolist() == [True, False]


def test_prints_a_row_per_method_with_its_pair_count(bench, capsys):
    bench.main(["--pairs", "4", "--batch", "2", "--imreg-pairs", "1", "--no-radius-window"])
    lines = capsys.readouterr().out.splitlines()
    rows = {re.split(r"\s{2,}", line)[0]: line.split() for line in lines if re.search(r"\s\d+\.\d+$", line)}
    assert rows["dpcn batched (batch 2)"][-10] == "4"
    assert rows["dpcn one pair at a time"][-10] == "4"  # not the 50 of a full run
    assert rows["OpenCV Fourier-Mellin"][-10] == "4"
    assert rows["dpcn batched, no radius window"][-10] == "4"
    for row in rows.values():
        assert all(0.0 <= float(v) <= 100.0 for v in row[-9:-4])  # the five accuracies, in %
    assert any(line.startswith("speed-up of dpcn batched:") for line in lines)


@pytest.mark.parametrize("args", [["--pairs", "-3"], ["--batch", "0"], ["--imreg-pairs", "x"]])
def test_bad_counts_are_usage_errors(bench, capsys, args):
    with pytest.raises(SystemExit) as exit_info:  # was a ValueError traceback from sample_poses
        bench.main(args)
    assert exit_info.value.code == 2
    assert f"argument {args[0]}: expected an integer >= 1" in capsys.readouterr().err
