"""bench_training.py evaluates on the pairs it trained on."""

import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from .conftest import compose_config, load_benchmark
from .test_training_cli import SMALL


def test_evaluations_repeat_the_data_overrides_of_fit():
    fit = [
        "loss.kl_align=1",
        "data.builtin_scenes=32",  # once forgotten: the 32-scene run was validated on the 8-scene val set
        "trainer.max_epochs=7",
        "image_size=128",
        "data.root=/maps",
        "+data.dataset.min_valid=0.5",
        "model.net.depth=2",
        "seed=3",
        "model.train_spectrum_window=nearest",
        "rotation_views=4",  # an inference setting: fit ignores it, the evaluations apply it
        "rotation_range=[0,180]",
    ]
    assert load_benchmark("bench_training").evaluation_overrides(fit) == [
        "data.builtin_scenes=32",
        "image_size=128",
        "data.root=/maps",
        "+data.dataset.min_valid=0.5",
        "seed=3",
        "rotation_views=4",
        "rotation_range=[0,180]",
    ]


def test_evaluations_repeat_the_data_keys_of_an_experiment():
    bench = load_benchmark("bench_training")
    spelled = bench.evaluation_overrides(["experiment=paper_difficulty", "trainer.max_epochs=2", "seed=43"])
    assert spelled == ["data.dataset.appearance_change=0.3", "seed=43"]
    assert compose_config("data=sim_dynamic", *spelled).data.dataset.appearance_change == 0.3
    # The command line's own value wins, as it does in fit.
    assert bench.evaluation_overrides(["experiment=paper_difficulty", "data.dataset.appearance_change=0.5"]) == [
        "data.dataset.appearance_change=0.5"
    ]
    # An experiment's training keys stay with the training.
    assert bench.evaluation_overrides(["experiment=finetune_translation"]) == []
    # The data an experiment picks (its defaults list) is fit's; the evaluations name their own.
    assert bench.evaluation_overrides(["experiment=paper_table1"]) == [
        "data.dataset.appearance_change=0.3",
        "rotation_views=4",
    ]
    quick = bench.evaluation_overrides(["+experiment=quick"])
    assert quick == ["data.epoch_size=256", "data.val_length=64", "data.test_length=64"]
    assert compose_config(*quick).data.test_length == 64


def test_a_run_evaluates_the_data_an_experiment_trains_on(tmp_path):
    """Without --data, fit composes its own (here the dynamic pairs of experiment=paper_table1),
    and the evaluations default to that, with the experiment's pairs and inference settings."""
    out = tmp_path / "bench"
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_training.py"
    args = [sys.executable, str(script), "--ckpt", "last", "--out", str(out), "--", "experiment=paper_table1", *SMALL]
    done = subprocess.run(args, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "fit data=sim_dynamic experiment=paper_table1" in done.stdout
    assert "DPCN sim_dynamic (test)" in done.stdout and "classical sim_dynamic (test)" in done.stdout
    fit = OmegaConf.load(out / "fit" / ".hydra" / "config.yaml")
    assert fit.data.name == "sim_dynamic" and fit.model.net.log_spectrum is True
    test = OmegaConf.load(out / "test-sim_dynamic-DPCN" / ".hydra" / "config.yaml")
    assert test.data.dataset.appearance_change == 0.3 and test.rotation_views == 4
    # the classical estimator on the same pairs, without the checkpoint's inference settings
    classical = OmegaConf.load(out / "test-sim_dynamic-classical" / ".hydra" / "config.yaml")
    assert classical.data.dataset.appearance_change == 0.3 and classical.rotation_views is None


def test_the_trained_data_is_read_from_the_fit_run(tmp_path):
    bench = load_benchmark("bench_training")
    with pytest.raises(SystemExit, match=r"config.yaml is missing .*pass --data"):
        bench.trained_data(tmp_path)
    (tmp_path / ".hydra").mkdir()
    OmegaConf.save(compose_config("experiment=paper_table1"), tmp_path / ".hydra" / "config.yaml")
    assert bench.trained_data(tmp_path) == "sim_dynamic"
