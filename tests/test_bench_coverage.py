"""The coverage benchmark: real configs, real scenes on disk, the classical estimator."""

import pytest

from dpcn.data.scene import make_dataset

from .conftest import load_benchmark, write_checkpoint


@pytest.fixture(scope="module")
def coverage():
    return load_benchmark("bench_coverage")


def test_bins_add_up_and_every_crop_meets_min_valid(coverage, tmp_path, capsys):
    root = make_dataset(tmp_path / "maps", n_scenes=3, seed=3, size=(720, 720), gap=0)
    overrides = [f"data.root={root}", "image_size=96", "data.dataset.translation=20", "data.test_length=24"]
    coverage.main(["--data", "s2d", "--stages", "test", "--bins", "0.5", "0.6", "--", *overrides])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("classical on s2d")
    rows = {line[:30].strip(): line[30:].split() for line in lines[2:]}
    assert rows["held-out scene, all"][0] == "24"
    binned = [int(v[0]) for k, v in rows.items() if k.startswith("held-out scene, [")]
    assert sum(binned) == 24
    assert "held-out scene, [0.00, 0.50)" not in rows  # data.dataset.min_valid = 0.5 holds for every crop
    assert all(0.0 <= float(v) <= 100.0 for values in rows.values() for v in values[1:])


def test_bad_arguments_are_refused(coverage):
    with pytest.raises(SystemExit):
        coverage.main(["--stages", "fit"])
    with pytest.raises(SystemExit):
        coverage.main(["--bins", "1.5"])
    with pytest.raises(SystemExit, match="checkpoint not found: /nonexistent.ckpt"):
        coverage.main(["--checkpoint", "/nonexistent.ckpt"])


def test_shared_setup_refuses_bad_configs_in_one_line(coverage):
    # evaluation_setup: the set-up of every evaluation benchmark (coverage, confidence, misses, ceiling)
    with pytest.raises(SystemExit, match=r"^bench_x: In 'config': Could not find 'data/nosuch'"):
        coverage.evaluation_setup("nosuch", None, [], "bench_x")
    with pytest.raises(SystemExit, match=r"^bench_x: Could not override 'nosuch\.key'"):
        coverage.evaluation_setup("s2d", None, ["nosuch.key=1"], "bench_x")


def test_pairs_the_checkpoint_was_not_built_for_end_in_one_line(coverage, tmp_path):
    root = make_dataset(tmp_path / "maps", n_scenes=3, seed=3, size=(720, 720), gap=0)
    checkpoint = write_checkpoint(tmp_path / "a.ckpt", "data=s2d", "image_size=96")
    overrides = [f"data.root={root}", "image_size=128", "data.dataset.translation=20", "data.test_length=4"]
    with pytest.raises(SystemExit, match=r"^held-out scene: this model was built for 96x96 images, got 128x128"):
        coverage.main(["--data", "s2d", "--checkpoint", str(checkpoint), "--stages", "test", "--", *overrides])
