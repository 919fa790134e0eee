"""The data configs composed for real: map pairs (own folders and built-in), CSV pairs, make-data."""

from __future__ import annotations

import csv as csv_module
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from dpcn.data.aeroground import DataError
from dpcn.data.scene import make_dataset

from .conftest import compose_config, cv2_warp, photo
from .test_training_cli import dpcn


@pytest.fixture(scope="module")
def maps_root(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("maps"), n_scenes=3, seed=3, size=(720, 720), gap=0)


@pytest.mark.parametrize("pair", ["l2d", "l2sat", "s2d", "s2sat"])
def test_map_pair_configs_read_a_root(maps_root, pair):
    cfg = compose_config(f"data={pair}", f"data.root={maps_root}", "image_size=96", "data.dataset.translation=20")
    dm = instantiate(cfg.data)
    dm.setup("fit")
    dm.setup("test")
    item = dm.datasets["train"][0]
    assert item["template"].shape == (1, 96, 96) and item["source"].shape == (1, 96, 96)
    assert dm.translation_threshold == 10.0
    assert len(dm.datasets["test"]) == 500
    # The paper's protocol: the test scene is held out of training and validation.
    assert [s.name for s in dm.datasets["train"].scenes] == ["scene_a", "scene_b"]
    assert [s.name for s in dm.datasets["val"].scenes] == ["scene_a", "scene_b"]
    assert [s.name for s in dm.datasets["test"].scenes] == ["scene_c"]


def test_map_pairs_geometry_follows_the_pose_convention(tmp_path):
    """Same raster under two modality names: the source must be cv2.warpAffine of the template."""
    image = (photo("astronaut", (400, 400)) * 255).astype(np.uint8)
    for name in ("lidar", "drone"):
        folder = tmp_path / "scene"
        folder.mkdir(exist_ok=True)
        cv2.imwrite(str(folder / f"{name}.png"), image)
    cfg = compose_config("data=l2d", f"data.root={tmp_path}", "image_size=96", "data.dataset.translation=10",
                       "data.dataset.scale=[0.9,1.1]", "data.test_scenes=null")  # fmt: skip
    dm = instantiate(cfg.data)
    dm.setup("fit")
    for i in range(3):
        item = dm.datasets["train"][i]
        tx, ty, angle, scale = item["pose"].tolist()
        expected = cv2_warp(item["template"][0].numpy(), tx, ty, angle, scale)
        valid = cv2_warp(np.ones((96, 96), np.float32), tx, ty, angle, scale) > 0.999
        assert np.abs(expected - item["source"][0].numpy())[valid].mean() < 0.02


def test_builtin_scene_when_no_root(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("DPCN_CACHE", str(tmp_path))
    import dpcn.data.maps as maps

    monkeypatch.setattr(maps, "_announced", False)
    # Three scenes: scene_c is the test scene, a and b train (the default is 8, generated the same way).
    cfg = compose_config("data=l2sat", "image_size=64", "data.dataset.translation=10", "data.builtin_scenes=3")
    dm = instantiate(cfg.data)
    with caplog.at_level(logging.INFO, logger="dpcn"):
        dm.setup("fit")
    assert any("3 built-in procedural scenes" in r.getMessage() for r in caplog.records)
    root = tmp_path / f"builtin-scenes-{maps.BUILTIN_VERSION}-3"
    assert sorted(p.name for p in root.iterdir() if p.is_dir()) == ["scene_a", "scene_b", "scene_c"]
    assert [s.name for s in dm.datasets["train"].scenes] == ["scene_a", "scene_b"]
    assert dm.datasets["train"][0]["template"].shape == (1, 64, 64)


def test_builtin_scene_count_is_checked(tmp_path, monkeypatch):
    monkeypatch.setenv("DPCN_CACHE", str(tmp_path))
    for bad in (0, "many"):
        dm = instantiate(compose_config("data=l2d", f"data.builtin_scenes={bad}").data)
        with pytest.raises(DataError, match="data.builtin_scenes must be an integer >= 1"):
            dm.setup("fit")
    assert not any(tmp_path.iterdir())  # nothing generated


def test_missing_root_is_a_clear_error(tmp_path):
    cfg = compose_config("data=l2sat", f"data.root={tmp_path / 'nope'}")
    dm = instantiate(cfg.data)
    with pytest.raises(DataError, match="data.root does not exist"):
        dm.setup("fit")


@pytest.mark.parametrize(
    "args,epochs",
    [
        ([], 16),  # the simulated pairs: the trainer config's length
        (["data=l2d"], 5),  # the map pairs set their own (within 30 min on 2 CPU cores)
        (["data=l2sat", "trainer=gpu"], 5),
        (["data=s2sat"], 7),
        (["data=s2d", "trainer.max_epochs=3"], 3),  # the command line wins
        (["data=l2sat", "experiment=quick"], 2),  # and so does an experiment
        (["data=s2d", "experiment=finetune_translation"], 2),
    ],
)
def test_training_length_per_data_config(args, epochs):
    assert compose_config(*args).trainer.max_epochs == epochs


@pytest.mark.parametrize("data", ["sim_heterogeneous", "sim_dynamic"])
def test_paper_difficulty_experiment_sets_the_appearance_change(data):
    assert compose_config(f"data={data}").data.dataset.appearance_change == 1.0  # the default: full change
    dm = instantiate(compose_config(f"data={data}", "experiment=paper_difficulty").data)
    dm.setup("test")
    assert dm.datasets["test"].appearance_change == 0.3
    assert dm.datasets["test"].kind == data.removeprefix("sim_")


def test_paper_table1_experiment_is_the_measured_recipe():
    """experiment=paper_table1 spells the README's Table 1 recipe: the same config as its
    measured command line; a data= on the command line still wins."""
    measured = compose_config(
        "data=sim_dynamic",
        "data.dataset.appearance_change=0.3",
        "model.net.log_spectrum=true",
        "rotation_views=4",
        "model.net.rotation_hypotheses=1",  # measured when tiny checked one stage-1 peak
        "model.net.hypothesis_ratio=0",
    )
    assert compose_config("experiment=paper_table1") == measured
    hetero = compose_config("experiment=paper_table1", "data=sim_heterogeneous")
    assert hetero.data.name == "sim_heterogeneous" and hetero.data.dataset.appearance_change == 0.3


@pytest.mark.parametrize(
    "args,hypotheses",
    [
        ([], (2, 0.7)),  # tiny: a second stage-1 peak for the ambiguous pairs
        (["data=sim_dynamic"], (2, 0.7)),
        (["experiment=paper_table1"], (1, 0.0)),  # the recipe as measured
        (["data=l2sat"], (1, 0.0)),  # the map models (tiny_full) as measured
        (["data=s2d"], (1, 0.0)),
        (["data=s2sat", "model.net.rotation_hypotheses=3"], (3, 0.0)),
        (["model=paper"], (1, 0.0)),
    ],
)
def test_stage1_hypotheses_per_config(args, hypotheses):
    net = compose_config(*args).model.net
    assert (net.rotation_hypotheses, net.hypothesis_ratio) == hypotheses


@pytest.mark.parametrize(
    "args,fraction",
    [
        ([], 0.25),  # tiny's share
        (["data=l2d"], 0.25),
        (["data=s2sat"], 0.25),
        (["data=s2d"], 0.5),  # s2d's default model trains phase 2 on half of each batch
        (["data=s2d", "model=tiny_full"], 0.25),  # a model named on the command line wins
        (["data=s2d", "model.translation_fraction=1"], 1),  # and so does the setting
    ],
)
def test_phase2_share_per_data_config(args, fraction):
    assert compose_config(*args).model.translation_fraction == fraction
    if not any(a.startswith("model") for a in args):  # a data config sets no model key of its own
        assert compose_config(*args, "model=classical").model._target_.endswith("ClassicalModule")


@pytest.mark.parametrize(
    "args,expected",
    [
        (["model=classical"], True),  # the classical estimator windows stage 1's log-radius axis
        (["model=classical", "registration.radius_window=false"], False),  # the paper's stage 1
        ([], False),  # DPCN trained worse with it: off
        (["model=paper"], False),
    ],
)
def test_radius_window_default_per_model(args, expected):
    model = instantiate(compose_config(*args).model, _convert_="all")
    if "model=classical" in args:
        assert model.estimator.rotation_scale_options["radius_window"] is expected
    else:
        assert model.model.radius_window is expected


@pytest.mark.parametrize(
    "args,radii",
    [
        ([], (256, 128)),  # tiny trains on 256 log-polar radii and infers on 128
        (["data=l2d"], (256, None)),  # the map pairs' models keep 256 at inference too
        (["data=s2d"], (256, None)),
        (["data=s2sat", "model=tiny"], (256, 128)),
        (["model=paper"], (256, None)),
    ],
)
def test_log_polar_radii_per_model_config(args, radii):
    net = compose_config(*args).model.net
    assert (net.n_radii, net.get("inference_radii")) == radii


@pytest.mark.parametrize(
    ("args", "sigmas"),
    [
        ([], (2.0, 3.0)),  # tiny blurs phase 2's surfaces more at inference than in training
        (["data=l2d"], (2.0, None)),  # the map pairs' and paper's models as trained (not measured)
        (["model=paper"], (2.0, None)),
    ],
)
def test_phase_2_blur_per_model_config(args, sigmas):
    net = compose_config(*args).model.net
    assert (net.sigma, net.get("inference_sigma")) == sigmas


def test_a_bad_dataset_value_names_its_key(tmp_path):
    dm = instantiate(compose_config("data=l2sat", f"data.root={tmp_path}", "data.dataset.min_valid=2").data)
    with pytest.raises(ValueError, match=r"^data\.dataset: min_valid must be in \[0, 1\], got 2"):
        dm.setup("fit")


def test_csv_config(tmp_path):
    template = photo("camera", (64, 64))
    (tmp_path / "template").mkdir()
    (tmp_path / "source").mkdir()
    rows = ["name,rotation,shift_x,shift_y,scale"]
    for i, (angle, tx, ty) in enumerate([(10.0, 3.0, -2.0), (-40.0, 0.5, 4.0)]):
        cv2.imwrite(str(tmp_path / "template" / f"p{i}.png"), (template * 255).astype(np.uint8))
        cv2.imwrite(
            str(tmp_path / "source" / f"p{i}.png"), (cv2_warp(template, tx, ty, angle, 1.0) * 255).astype(np.uint8)
        )
        rows.append(f"p{i},{angle},{tx},{ty},1.0")
    (tmp_path / "gt.csv").write_text("\n".join(rows) + "\n")
    csv = str(tmp_path / "gt.csv")
    cfg = compose_config("data=csv", f"data.train_csv={csv}", f"data.val_csv={csv}", f"data.test_csv={csv}")
    dm = instantiate(cfg.data)
    dm.setup("fit")
    item = dm.datasets["val"][1]
    torch.testing.assert_close(item["pose"], torch.tensor([0.5, 4.0, -40.0, 1.0]))
    small = instantiate(compose_config("data=csv", f"data.train_csv={csv}", f"data.val_csv={csv}").data)
    small.setup("fit")  # 2 pairs, batches of 8: Lightning trained 0 steps, and the CLI named a last.ckpt never written
    with pytest.raises(DataError, match=r"gives 2 pair\(s\) per epoch, fewer than one batch of data.batch_size=8"):
        small.train_dataloader()
    assert len(small.val_dataloader()) == 1  # evaluation keeps its partial batch
    cfg = compose_config("data=csv")
    with pytest.raises(DataError, match="needs the ground-truth CSV of each split .* data.test_csv to test"):
        instantiate(cfg.data).setup("fit")
    # `test` on them writes each pair's pose under its name, with the errors.
    out = dpcn("test", "model=classical", "data=csv", f"data.test_csv={csv}", "data.num_workers=0",
               "trainer.enable_progress_bar=false", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)  # fmt: skip
    assert "pairs_test.csv" in out.stdout
    with (tmp_path / "run" / "pairs_test.csv").open() as f:
        pairs = list(csv_module.DictReader(f))
    assert [(p["pair"], p["name"]) for p in pairs] == [("0", "p0"), ("1", "p1")]
    assert float(pairs[1]["angle"]) == pytest.approx(-40.0) and float(pairs[1]["err_rot"]) < 0.5


def test_csv_pairs_of_mixed_sizes_fail_in_one_line_also_from_loader_workers(tmp_path):
    rng = np.random.default_rng(0)
    for name, t_size, s_size in (("a", 64, 64), ("b", 96, 96), ("c", 64, 80)):
        for folder, size in (("template", t_size), ("source", s_size)):
            (tmp_path / folder).mkdir(exist_ok=True)
            cv2.imwrite(str(tmp_path / folder / f"{name}.png"), (rng.random((size, size)) * 255).astype(np.uint8))
    (tmp_path / "mixed.csv").write_text("name,rotation,shift_x,shift_y\na,1,0,0\nb,1,0,0\n")
    (tmp_path / "unequal.csv").write_text("name,rotation,shift_x,shift_y\nc,1,0,0\n")
    cases = [
        ("mixed.csv", "a batch mixes pairs of different sizes (64x64, 96x96, H x W): a data set's pairs must share"),
        ("unequal.csv", "unequal.csv: 'c': template"),  # the pair's own check, raised in __getitem__
    ]
    for name, message in cases:
        for workers in ("0", "2"):  # 2, the configs' default: torch re-raises with the worker's traceback
            out = dpcn("test", "model=classical", "data=csv", f"data.test_csv={name}", f"data.num_workers={workers}",
                       "trainer.enable_progress_bar=false", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path,
                       check=False)  # fmt: skip
            lines = [line for line in out.stderr.splitlines() if line.startswith("dpcn test: error: ")]
            assert out.returncode == 2 and len(lines) == 1 and message in lines[0], out.stderr[-2000:]
            assert "Traceback" not in lines[0] and "stack expects" not in out.stderr


def test_make_data_cli(tmp_path):
    out = dpcn("make-data", f"out={tmp_path / 'maps'}", "n_scenes=1", "scene_size=640", "split_gap=0", cwd=tmp_path)
    assert "wrote 1 scenes (scene_a)" in out.stdout
    files = sorted(p.name for p in (tmp_path / "maps" / "scene_a").iterdir())
    assert files == [
        "drone.png",
        "lidar.png",
        "lidar_mask.png",
        "regions.json",
        "satellite.png",
        "stereo.png",
        "stereo_mask.png",
    ]
    again = dpcn("make-data", f"out={tmp_path / 'maps'}", cwd=tmp_path, check=False)
    assert again.returncode == 2 and "not empty" in again.stderr
    narrow = dpcn("make-data", f"out={tmp_path / 'narrow'}", "scene_size=640", cwd=tmp_path, check=False)
    assert narrow.returncode == 2 and "split gap (630 px)" in narrow.stderr and "Traceback" not in narrow.stderr
    bad = dpcn("make-data", f"out={tmp_path / 'bad'}", "scene_size=[100]", cwd=tmp_path, check=False)
    assert bad.returncode == 2 and "scene_size must be one positive integer or [H, W]" in bad.stderr
    assert "Traceback" not in bad.stderr and "HYDRA_FULL_ERROR" not in bad.stderr


def test_finetune_experiment_trains_phase2_alone_with_the_half_turn_term():
    cfg = compose_config("data=s2d", "experiment=finetune_translation", "init_from=x.ckpt")
    assert list(cfg.model.freeze) == ["rotation_scale"] and cfg.model.translation_fraction == 1
    assert cfg.model.loss.kl_half_turn == 1 and cfg.model.warmup_epochs == 0 and cfg.init_from == "x.ckpt"
    assert cfg.model.net.rotation_scale_downsample == 1  # s2d's own model (tiny_full) underneath
    assert list(compose_config().model.freeze) == []  # nothing frozen by default
