"""The miss-analysis benchmark: counts, real configs and scenes on disk, real checkpoints."""

import pytest
import torch

from dpcn.data.scene import make_dataset

from .conftest import load_benchmark, write_checkpoint


@pytest.fixture(scope="module")
def misses():
    return load_benchmark("bench_misses")


def _checkpoint(path, seed: int, *overrides: str):
    """An s2d-sized checkpoint file (96 x 96) for the benchmark."""
    return write_checkpoint(path, "data=s2d", "image_size=96", *overrides, seed=seed)


def test_counts_split_the_rotation_misses_by_size(misses):
    # (x, y, angle, scale) errors: ok, half-turn, near, wrong peak, translation miss with rot ok
    errors = torch.tensor(
        [
            [0.5, 0.5, 0.2, 0.0],
            [0.5, 0.5, 179.0, 0.0],
            [0.5, 0.5, 3.0, 0.0],
            [0.5, 0.5, 90.0, 0.0],
            [12.0, 0.5, 0.9, 0.0],
        ]
    )
    counts = misses.miss_counts(errors, translation_threshold=10.0)
    assert counts == {"n": 5, "rot>1": 3, "half-turn": 1, "1-5": 1, "5-175": 1, "xy miss|rot ok": 1}


def test_classical_rows_add_up(misses, tmp_path, capsys):
    root = make_dataset(tmp_path / "maps", n_scenes=3, seed=3, size=(720, 720), gap=0)
    overrides = [f"data.root={root}", "image_size=96", "data.dataset.translation=20", "data.test_length=24"]
    misses.main(["--data", "s2d", "--stages", "test", "--", *overrides])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("classical on s2d")
    cells = lines[2][18:].split()
    n, rot, half, near, wrong, xy = (int(v) for v in cells[:6])
    assert cells[6:8] == ["-", "-"]  # turn|truth: phase 2's check only
    assert all(0.0 <= float(v) <= 100.0 for v in cells[8:]) and len(cells) == 12
    assert float(cells[10]) == pytest.approx(100.0 * (n - rot) / n, abs=0.05)  # rot@1
    assert lines[2].startswith("held-out scene")
    assert n == 24 and rot == half + near + wrong and 0 <= xy <= n - rot


def test_wrong_turn_at_truth_compares_the_two_turns_at_the_true_pose(misses, tmp_path):
    matcher = misses.load_matcher(_checkpoint(tmp_path / "a.ckpt", 0))
    model = matcher.model.eval()
    generator = torch.Generator().manual_seed(0)
    template = torch.rand(3, 1, 96, 96, generator=generator)
    pose = torch.tensor([[4.0, -3.0, 30.0, 1.1], [0.0, 0.0, -120.0, 0.9], [2.0, 5.0, 170.0, 1.0]])
    source = torch.rand(3, 1, 96, 96, generator=generator)
    flags = misses.wrong_turn_at_truth(model, template, source, pose)
    angle, scale = pose[:, 2], pose[:, 3]
    unwarped = misses.unwarp_rotation_scale(source, angle, scale)
    (upright, turned), _, _ = model.translation_turns(template, unwarped, angle, scale)
    assert flags.dtype == torch.bool and flags.shape == (3,)
    assert torch.equal(flags, turned.confidence >= upright.confidence)
    # Identical extractors and a source that is the template itself, upright: a perfect
    # upright match, which the check must keep.
    model.t_source.load_state_dict(model.t_template.state_dict())
    same = misses.wrong_turn_at_truth(model, template, template, torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 3))
    assert not same.any()


def test_checkpoint_rows_count_wrong_turns_at_the_truth(misses, tmp_path, capsys):
    root = make_dataset(tmp_path / "maps", n_scenes=3, seed=3, size=(720, 720), gap=0)
    target = _checkpoint(tmp_path / "a.ckpt", 0)
    overrides = [f"data.root={root}", "image_size=96", "data.dataset.translation=20", "data.test_length=16"]
    misses.main(["--data", "s2d", "--checkpoint", str(target), "--stages", "test", "--", *overrides])
    cells = capsys.readouterr().out.splitlines()[2][18:].split()
    n, rot, half = (int(v) for v in cells[:3])
    at_truth, of_them = int(cells[6]), int(cells[7])
    assert n == 16 and 0 <= of_them <= min(at_truth, half) and at_truth <= n


def test_shared_misses_of_a_checkpoint_with_itself_are_all_of_them(misses, tmp_path, capsys):
    root = make_dataset(tmp_path / "maps", n_scenes=3, seed=3, size=(720, 720), gap=0)
    target = _checkpoint(tmp_path / "a.ckpt", 0)
    overrides = [f"data.root={root}", "image_size=96", "data.dataset.translation=20", "data.test_length=16"]
    misses.main(["--data", "s2d", "--stages", "test", "--shared-with", str(target), "--", *overrides])
    classical = capsys.readouterr().out.splitlines()
    rot_classical = int(classical[2][18:].split()[1])
    misses.main(
        ["--data", "s2d", "--checkpoint", str(target), "--shared-with", str(target), "--stages", "test"]
        + ["--", *overrides]
    )
    lines = capsys.readouterr().out.splitlines()
    rot = int(lines[2][18:].split()[1])
    assert rot > 0 and lines[3].split() == [
        "rotation",
        "misses",
        "shared",
        "with",
        "a.ckpt:",
        str(rot),
        "(it",
        "misses",
        f"{rot})",
    ]
    shared_with_classical = int(classical[3].split()[5])
    assert classical[3].split()[-1] == f"{rot})" and shared_with_classical <= min(rot, rot_classical)
    with pytest.raises(SystemExit, match="checkpoint not found: /nonexistent.ckpt"):
        misses.main(["--checkpoint", str(target), "--shared-with", "/nonexistent.ckpt"])


def test_phase2_swap_takes_only_the_translation_unets(misses, tmp_path):
    target = _checkpoint(tmp_path / "a.ckpt", 0)
    donor = _checkpoint(tmp_path / "b.ckpt", 1)
    matcher = misses.load_matcher(target)
    before = {k: v.clone() for k, v in matcher.model.state_dict().items()}
    misses._swap_phase2(matcher, str(donor), str(target))
    after, donated = matcher.model.state_dict(), misses.load_matcher(donor).model.state_dict()
    for key, value in after.items():
        expected = donated[key] if key.startswith(("t_template.", "t_source.")) else before[key]
        assert torch.equal(value, expected), key
    assert any(not torch.equal(after[k], before[k]) for k in after if k.startswith("t_source."))  # seeds differ


def test_bad_arguments_are_refused(misses, tmp_path):
    with pytest.raises(SystemExit):
        misses.main(["--stages", "fit"])
    with pytest.raises(SystemExit):
        misses.main(["--phase2-from", "x.ckpt"])  # no --checkpoint
    with pytest.raises(SystemExit, match="checkpoint not found: /nonexistent.ckpt"):
        misses.main(["--checkpoint", "/nonexistent.ckpt"])
    target = _checkpoint(tmp_path / "a.ckpt", 0)
    wider = _checkpoint(tmp_path / "wide.ckpt", 0, "model.net.base_channels=8")
    with pytest.raises(SystemExit, match="phase 2 of .*wide.ckpt does not fit"):
        misses.main(["--checkpoint", str(target), "--phase2-from", str(wider)])


def test_simulated_pairs_are_not_labelled_as_map_regions(misses, capsys):
    overrides = ["image_size=64", "data.val_length=4", "data.test_length=4", "data.num_workers=0"]
    misses.main(["--data", "sim_heterogeneous", "--stages", "validate,test", "--", *overrides])
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].startswith("validation pairs") and lines[3].startswith("test pairs")
    assert not any("held-out" in line for line in lines)
