"""The map-ceiling benchmark: real scenes on disk, the real data configs, the classical estimator."""

import numpy as np
import pytest
import torch

from dpcn.data.aeroground import read_image
from dpcn.data.scene import STEREO_GROUND, generate_scene, make_dataset, scene_index, scene_seed, scene_truth

from .conftest import load_benchmark, write_checkpoint

SMALL = ["image_size=96", "data.dataset.translation=20", "data.test_length=16", "data.val_length=16"]


@pytest.fixture(scope="module")
def ceiling():
    return load_benchmark("bench_map_ceiling")


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("maps"), n_scenes=3, seed=3, size=(720, 720), gap=0)


def test_scene_truth_is_what_the_scene_renders(maps):
    assert [scene_index(n) for n in ("scene_a", "scene_z", "scene_aa", "scene_af")] == [0, 25, 26, 31]
    with pytest.raises(ValueError, match="not a scene name"):
        scene_index("meadow")
    seed = scene_seed(3, 1)
    stereo, _ = read_image(maps / "scene_b" / "stereo.png")
    assert np.array_equal(generate_scene(seed, (720, 720))["stereo"], stereo)  # make_dataset's seed
    truth = scene_truth(seed, (720, 720))
    valid = stereo > 0
    # the stereo map is these heights plus range noise: flat ground reads STEREO_GROUND where observed
    ground = valid & (truth["height"] == 0) & (truth["labels"] != 7)
    assert abs(float(np.median(stereo[ground])) - STEREO_GROUND) <= 3
    assert float(np.corrcoef(stereo[valid], truth["height"][valid])[0, 1]) > 0.8


def test_objects_are_the_raised_part_of_the_boundaries(ceiling):
    truth = scene_truth(scene_seed(3, 0), (720, 720))
    every, _ = ceiling.ideal_maps("boundaries", truth, "drone")
    objects, _ = ceiling.ideal_maps("objects", truth, "drone")
    assert objects.any() and not (objects & ~every).any()  # an outline of something raised is a class boundary
    assert objects.sum() < every.sum()  # the flat classes' boundaries are not among them
    raised, _ = ceiling.ideal_maps("raised", truth, "drone")
    assert not (raised & ~every).any()  # the raised outlines are class boundaries
    # and hold nearly every object outline (not those against a sidewalk, raised too)
    assert (objects & raised).astype(bool).sum() > 0.9 * objects.astype(bool).sum()
    kerbs = raised & ~objects
    assert kerbs.any() and (truth["labels"][kerbs > 0] == 2).mean() > 0.4  # mostly the sidewalks' own edges
    elevation, _ = ceiling.ideal_maps("elevation", truth, "drone")
    assert elevation[truth["height"] == 0].max() == STEREO_GROUND
    _, satellite = ceiling.ideal_maps("objects", truth, "satellite")
    assert not np.array_equal(objects, satellite)  # the satellite's own cars
    with pytest.raises(ValueError, match="unknown mode 'texture'"):
        ceiling.ideal_maps("texture", truth, "drone")


def test_ideal_pairs_are_the_real_pairs_and_the_boundaries_find_them(ceiling, maps, tmp_path, capsys):
    roots = ceiling.write_ideal_roots(maps, "s2d", tmp_path, dataset_seed=3)
    assert sorted(roots) == ["boundaries", "elevation", "objects", "raised"]
    real = ceiling._loader("s2d", [f"data.root={maps}", *SMALL], "test")
    ideal = ceiling._loader("s2d", [f"data.root={roots['boundaries']}", *SMALL], "test")
    for a, b in zip(real, ideal, strict=True):
        torch.testing.assert_close(a["pose"], b["pose"])
        torch.testing.assert_close(a["template_mask"], b["template_mask"])
        assert not b["template"][a["template_mask"] == 0].any()  # no data stays no data
        assert not torch.equal(a["source"], b["source"])

    ceiling.main(["--data", "s2d", "--dataset-seed", "3", "--stages", "test", "--", f"data.root={maps}", *SMALL])
    lines = capsys.readouterr().out.splitlines()
    rows = {line[:30].strip(): [float(v) for v in line[30:].split()] for line in lines if line.startswith("held-out")}
    pixels, boundaries = rows["held-out scene, pixels"], rows["held-out scene, boundaries"]
    assert rows["held-out scene, elevation"] and rows["held-out scene, objects"]
    assert boundaries[2] >= pixels[2] + 40  # rot@1: the shared geometry finds what the pixels do not


def test_stage1_sides_reports_every_pairing(ceiling, maps, tmp_path):
    checkpoint = write_checkpoint(tmp_path / "s2d.ckpt", "data=s2d", "image_size=96")
    roots = ceiling.write_ideal_roots(maps, "s2d", tmp_path / "ideal", dataset_seed=3)
    from dpcn.training.module import load_matcher

    model = load_matcher(checkpoint).model
    report = ceiling.stage1_sides(model, "s2d", [f"data.root={maps}", *SMALL], roots, "validate")
    assert list(report) == [
        "learned / learned",
        "learned / elevation",
        "elevation / learned",
        "learned / boundaries",
        "boundaries / learned",
        "learned / objects",
        "objects / learned",
        "learned / raised",
        "raised / learned",
    ]
    assert all(0.0 <= v <= 100.0 for v in report.values())


def test_bad_input_is_refused(ceiling, maps, tmp_path, capsys):
    with pytest.raises(SystemExit, match=r"scene_a/stereo.png is not scene scene_a of make_dataset\(seed=4\)"):
        ceiling.write_ideal_roots(maps, "s2d", tmp_path / "a", dataset_seed=4)
    odd = tmp_path / "odd" / "meadow"
    odd.mkdir(parents=True)
    (odd / "stereo.png").write_bytes((maps / "scene_a" / "stereo.png").read_bytes())
    (odd / "drone.png").write_bytes((maps / "scene_a" / "drone.png").read_bytes())
    with pytest.raises(SystemExit, match="'meadow' is not a scene name"):
        ceiling.write_ideal_roots(odd.parent, "s2d", tmp_path / "b")
    with pytest.raises(SystemExit):
        ceiling.main(["--data", "sim_heterogeneous"])
    with pytest.raises(SystemExit, match="checkpoint not found: /nonexistent.ckpt"):
        ceiling.main(["--checkpoint", "/nonexistent.ckpt"])
    with pytest.raises(SystemExit, match="bench_map_ceiling: scene 'scene_a': val region .* too small"):
        ceiling.main(["--dataset-seed", "3", "--", f"data.root={maps}"])  # 256 px crops in 720 px scenes
    checkpoint = write_checkpoint(tmp_path / "s2d.ckpt", "data=s2d", "image_size=96")
    with pytest.raises(SystemExit, match="bench_map_ceiling: this model was built for 96x96 images, got 128x128"):
        ceiling.main(["--checkpoint", str(checkpoint), "--", f"data.root={maps}", "image_size=128"])
    capsys.readouterr()
    with pytest.raises(SystemExit):
        ceiling.main(["--", f"data.root={tmp_path / 'missing'}"])
    assert f"data.root {tmp_path / 'missing'} does not exist" in capsys.readouterr().err
