"""The U-Net layout/dtype benchmark runs (on the CPU here) and reports every variant."""

import pytest

from .conftest import load_benchmark


def test_reports_each_variant(capsys):
    bench = load_benchmark("bench_unet_gpu")
    bench.main(["--device", "cpu", "--preset", "tiny", "--batch", "2", "--size", "32", "--rounds", "1"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("tiny U-Net, 2 images 32x32, cpu")
    rows = {line[:44].strip(): float(line[44:]) for line in lines[2:]}
    expected = {"channels-last (the project's), fp32", "channels-first, fp32", "channels-last, bfloat16 weights"}
    assert set(rows) == expected
    assert all(ms > 0 for ms in rows.values())
    with pytest.raises(SystemExit):
        bench.main(["--device", "cpu", "--batch", "0"])
