"""bench_training.py evaluates on the pairs it trained on."""

from .conftest import load_benchmark


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
