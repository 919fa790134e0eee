"""bench_training.py evaluates on the pairs it trained on."""

from .conftest import compose_config, load_benchmark


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
    ]
    assert load_benchmark("bench_training").evaluation_overrides(fit) == [
        "data.builtin_scenes=32",
        "image_size=128",
        "data.root=/maps",
        "+data.dataset.min_valid=0.5",
        "seed=3",
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
    quick = bench.evaluation_overrides(["+experiment=quick"])
    assert quick == ["data.epoch_size=256", "data.val_length=64", "data.test_length=64"]
    assert compose_config(*quick).data.test_length == 64
