"""The inference-speed benchmark: rounds taken in turn, one row per timed model."""

import re

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


def test_a_stream_matches_each_pair_alone_in_order(bench):
    calls = []
    stream = bench.one_at_a_time(lambda start, stop: calls.append((start, stop)), 3)
    assert calls == []  # built, not run
    stream()
    assert calls == [(0, 1), (1, 2), (2, 3)]


def test_prints_one_row_per_variant_and_the_classical_estimator(bench, capsys):
    args = ["--presets", "tiny", "--size", "64", "--batch", "2", "--rounds", "1", "--radii", "64,32"]
    bench.main([*args, "--unet-dtype", "bfloat16"])
    lines = capsys.readouterr().out.splitlines()
    rows = [re.split(r"\s{2,}", line.strip()) for line in lines[2:] if line.strip()]
    labels = [row[0] for row in rows]
    assert labels == [
        "DPCN tiny, radii=64, bfloat16 U-Nets",  # longer than the default column: still its own column
        "DPCN tiny, radii=32, bfloat16 U-Nets",
        "classical (no U-Nets)",
    ]
    for row in rows:  # params, ms per pair alone and in batches, pairs per second
        params, one, batched, rate = row[1:]
        assert float(one) > 0 and float(batched) > 0 and int(rate) > 0
    assert int(rows[0][1]) > 0 and int(rows[2][1]) == 0
    params_end = lines[1].index("params") + len("params")  # the columns line up under the header
    assert all(line[:params_end].endswith(row[1]) for line, row in zip(lines[2:], rows, strict=True))


def test_one_template_adds_a_column_per_model(bench, capsys):
    bench.main(["--presets", "tiny", "--size", "64", "--batch", "3", "--rounds", "1", "--one-template"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].endswith("one template (ms/source)")
    rows = [re.split(r"\s{2,}", line.strip()) for line in lines[2:] if line.strip()]
    assert [row[0] for row in rows] == ["DPCN tiny", "classical (no U-Nets)"]
    for row in rows:  # params, alone, batched, rate, one template against the batch's sources
        assert len(row) == 6 and float(row[5]) > 0


def test_compiled_unets_are_timed_as_their_own_rows(bench, capsys):
    # The eager backend traces the U-Nets with dynamo without a C++ compiler (CI machines).
    bench.main(["--presets", "tiny", "--size", "64", "--batch", "2", "--rounds", "1", "--compile", "eager"])
    lines = capsys.readouterr().out.splitlines()
    rows = [re.split(r"\s{2,}", line.strip()) for line in lines[2:] if line.strip()]
    assert [row[0] for row in rows] == ["DPCN tiny, compiled (eager)", "classical (no U-Nets)"]
    assert all(float(row[2]) > 0 and float(row[3]) > 0 for row in rows)


def test_a_rotation_range_adds_a_variant_per_model(bench, capsys):
    bench.main(["--presets", "tiny", "--size", "64", "--batch", "2", "--rounds", "1", "--rotation-range", "0,180"])
    lines = capsys.readouterr().out.splitlines()
    labels = [re.split(r"\s{2,}", line.strip())[0] for line in lines[2:] if line.strip()]
    assert labels == ["DPCN tiny, range=None", "DPCN tiny, range=(0.0, 180.0)", "classical (no U-Nets)"]


def test_half_turn_passes_add_a_variant_per_model(bench, capsys):
    args = ["--presets", "tiny", "--size", "64", "--batch", "2", "--rounds", "1"]
    bench.main([*args, "--half-turn-passes", "every,winner"])
    lines = capsys.readouterr().out.splitlines()
    labels = [re.split(r"\s{2,}", line.strip())[0] for line in lines[2:] if line.strip()]
    assert labels == ["DPCN tiny, half-turn pass=every", "DPCN tiny, half-turn pass=winner", "classical (no U-Nets)"]


def test_gated_hypotheses_on_simulated_pairs(bench, capsys):
    args = ["--presets", "tiny", "--size", "64", "--batch", "2", "--rounds", "1", "--pairs", "heterogeneous"]
    bench.main([*args, "--hypotheses", "3", "--hypothesis-ratios", "0,0.7"])
    lines = capsys.readouterr().out.splitlines()
    labels = [re.split(r"\s{2,}", line.strip())[0] for line in lines[2:] if line.strip()]
    assert labels == ["DPCN tiny, K=3, ratio=0.0", "DPCN tiny, K=3, ratio=0.7", "classical (no U-Nets)"]


def test_chunk_sizes_time_the_same_model_chunked_differently(bench, capsys, monkeypatch):
    from dpcn.models import DPCN

    chunks, match = [], DPCN.match

    def recorded(self, template, source, chunk_size=None):
        chunks.append((len(source), chunk_size))
        return match(self, template, source, chunk_size)

    monkeypatch.setattr(DPCN, "match", recorded)
    bench.main(["--presets", "tiny", "--size", "64", "--batch", "3", "--rounds", "1", "--chunks", "1,3"])
    lines = capsys.readouterr().out.splitlines()
    labels = [re.split(r"\s{2,}", line.strip())[0] for line in lines[2:] if line.strip()]
    assert labels == ["DPCN tiny, chunk=1", "DPCN tiny, chunk=3", "classical (no U-Nets)"]
    assert {(3, 1), (3, 3)} <= set(chunks) and all(size is not None for _, size in chunks)


@pytest.mark.parametrize(
    "args,message",
    [
        (["--rounds", "0"], "argument --rounds: expected an integer >= 1, got '0'"),
        (["--chunks", "4,0"], "argument --chunks: expected an integer >= 1, got '0'"),
        (["--radii", "abc"], "argument --radii: expected comma-separated integers, got 'abc'"),
        (["--radii", "1"], "inference_radii must be an integer >= 2 or None, got 1"),
        (["--hypothesis-ratios", "2"], "hypothesis_ratio must be a finite number in [0, 1], got 2.0"),
        (["--ckpt", "no/such.ckpt"], "checkpoint not found: no/such.ckpt"),
        (
            ["--presets", "huge"],
            "--presets: no model config huge (conf/model has paper, tiny, tiny_full, tiny_full_s2d)",
        ),
        (["--rotation-range", "abc"], "argument --rotation-range: expected LOW,HIGH, got 'abc'"),
        (["--half-turn-passes", "winner,some"], "half_turn_pass must be one of winner, every, got 'some'"),
        (
            ["--compile", "nosuch"],
            "--compile: 'nosuch' is not a torch.compile backend (torch.compiler.list_backends())",
        ),
        (
            ["--rotation-range", "0,400"],
            "rotation_range must be [low, high] in degrees with 0 < high - low <= 360, got (0.0, 400.0)",
        ),
    ],
)
def test_bad_arguments_exit_with_one_line(bench, capsys, args, message):
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--presets", "tiny", "--size", "64", *args])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith(message)
