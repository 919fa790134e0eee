"""Accuracy-against-threshold curves: the CSV round trip, a real figure on disk, bad input."""

import cv2
import numpy as np
import pytest
import torch

from dpcn.metrics import accuracy_curve, read_curve_csv, write_curve_csv

from .conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("plot_accuracy")


def _curve(tmp_path, name, scale, seed):
    errors = torch.rand(50, 4, generator=torch.Generator().manual_seed(seed)) * torch.tensor([scale, scale, 1.0, 0.1])
    return write_curve_csv(tmp_path / name / "accuracy_test.csv", accuracy_curve(errors)), errors


def test_read_curve_csv_gives_back_what_was_written(tmp_path):
    path, errors = _curve(tmp_path, "a", 10.0, 0)
    rows = read_curve_csv(path)
    written = accuracy_curve(errors)
    assert [(n, t) for n, t, _ in rows] == [(n, t) for n, t, _ in written]
    assert [a for *_, a in rows] == pytest.approx([a for *_, a in written], abs=1e-4)
    x_at_5 = next(a for n, t, a in rows if (n, t) == ("x", 5.0))
    assert x_at_5 == pytest.approx(100.0 * float((errors[:, 0] <= 5.0).double().mean()), abs=1e-4)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (None, "accuracy curve not found"),
        ("name,tx\n", "not an accuracy curve (header ['name', 'tx']"),
        ("component,threshold,acc\nx,1,50\ny,abc,3\n", "row 3: expected component,threshold,acc, got ['y', 'abc'"),
        ("component,threshold,acc\nz,1,50\n", "row 2: expected a component of x, y, rot, scale"),
        ("component,threshold,acc\nx,1,150\n", "an Acc in [0, 100], got ['x', '1', '150']"),
        ("component,threshold,acc\n", "no rows"),
    ],
)
def test_read_curve_csv_names_the_file_and_row(tmp_path, text, message):
    path = tmp_path / "accuracy_test.csv"
    if text is not None:
        path.write_text(text)
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("(", r"\(")) as error:
        read_curve_csv(path)
    assert str(path) in str(error.value)


def test_plot_writes_one_panel_per_component(bench, tmp_path):
    dpcn_path, _ = _curve(tmp_path, "dpcn_run", 2.0, 1)
    classical_path, _ = _curve(tmp_path, "classical_run", 20.0, 2)
    out = bench.main([f"DPCN={dpcn_path}", str(classical_path), "--out", str(tmp_path / "acc.png"), "--title", "t"])
    image = cv2.imread(str(out))
    assert image is not None and image.shape[1] > 3 * image.shape[0]  # four panels side by side
    assert bench.parse_curve(str(classical_path)) == ("classical_run", classical_path)
    assert bench.parse_curve("a=b=c.csv")[0] == "a=b"  # the path is what follows the last "="
    # a panel per component present: a curve of x alone gives one
    x_only = write_curve_csv(tmp_path / "x.csv", [("x", 1.0, 50.0), ("x", 2.0, 80.0)])
    one = cv2.imread(str(bench.main([f"x={x_only}", "--out", str(tmp_path / "x.png")])))
    assert one.shape[1] < image.shape[1] / 2
    assert not np.all(one == one[0, 0])


def test_plot_bad_input_is_one_line(bench, tmp_path, capsys):
    good, _ = _curve(tmp_path, "a", 1.0, 0)
    for argv, message in [
        ([f"A={tmp_path / 'missing.csv'}", "--out", str(tmp_path / "o.png")], "accuracy curve not found"),
        ([f"A={good}", "--out", str(tmp_path / "no" / "o.png")], "does not exist"),
        (["=x.csv", "--out", str(tmp_path / "o.png")], "a curve is LABEL=PATH or PATH"),
    ]:
        with pytest.raises(SystemExit) as exit_:
            bench.main(argv)
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err
