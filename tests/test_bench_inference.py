"""The inference-speed benchmark: rounds taken in turn, one row per timed model."""

import pytest

from .conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_inference")


def test_rounds_run_every_call_in_turn_after_its_warmup(bench):
    order = []
    calls = {name: (lambda name=name: order.append(name)) for name in ("a", "b", "c")}
    medians = bench.timed_in_turn(calls, "cpu", rounds=2, warmup=1)
    # warm-up of each first, then every round visits every call once, in the same order
    assert order == ["a", "b", "c", "a", "b", "c", "a", "b", "c"]
    assert set(medians) == {"a", "b", "c"} and all(t >= 0 for t in medians.values())


def test_prints_one_row_per_variant_and_the_classical_estimator(bench, capsys):
    bench.main(["--presets", "tiny", "--size", "64", "--batch", "2", "--rounds", "1", "--radii", "64,32"])
    lines = capsys.readouterr().out.splitlines()
    rows = [line for line in lines[2:] if line.strip()]
    labels = [row[:34].strip() for row in rows]
    assert labels == ["DPCN tiny, radii=64", "DPCN tiny, radii=32", "classical (no U-Nets)"]
    for row in rows:  # params, ms per pair alone and in batches, pairs per second
        params, one, batched, rate = row[34:].split()
        assert float(one) > 0 and float(batched) > 0 and int(rate) > 0
    assert int(rows[0][34:].split()[0]) > 0 and int(rows[2][34:].split()[0]) == 0
