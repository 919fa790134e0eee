"""The sim-ceiling benchmark leans on private parts of dpcn.data.simulation: keep it honest."""

import re

import pytest
import torch

import dpcn.data.simulation as sim
from dpcn.models import DPCN
from dpcn.pose import wrap_angle

from .conftest import load_benchmark


@pytest.fixture(scope="module")
def ceiling():
    return load_benchmark("bench_sim_ceiling")


def test_ideal_boundaries_give_every_pose_and_pixels_match_the_dataset(ceiling):
    acc = ceiling.evaluate("all-boundaries", pairs=10)
    assert acc["rot@1"] == 100.0 and acc["x@1"] == 100.0 and acc["s@0.02"] == 100.0
    # pixels mode is the test set itself
    template, source, pose = next(ceiling.batches("pixels", pairs=3))
    item = sim.SimulatedPairs(kind="heterogeneous", length=3, seed=2)[1]
    torch.testing.assert_close(template[1], item["template"])
    torch.testing.assert_close(source[1], item["source"])
    torch.testing.assert_close(pose[1], item["pose"])


def test_rendering_restores_the_module_and_interleaved_streams_stay_apart(ceiling):
    render_a, render_b = sim._render_a, sim._render_b
    alone = [batch[0] for batch in ceiling.batches("all-boundaries", 4, batch=2)]
    streams = zip(ceiling.batches("all-boundaries", 4, batch=2), ceiling.batches("pixels", 4, batch=2), strict=True)
    for i, ((ideal, _, pose_a), (pixels, _, pose_b)) in enumerate(streams):
        torch.testing.assert_close(pose_a, pose_b)  # same scenes and poses
        torch.testing.assert_close(ideal, alone[i])  # not rendered by the other stream's styles
        assert not torch.allclose(ideal, pixels)
    assert (sim._render_a, sim._render_b) == (render_a, render_b)
    with pytest.raises(RuntimeError), ceiling.rendering("gradient"):
        raise RuntimeError("boom")
    assert (sim._render_a, sim._render_b) == (render_a, render_b)


def test_stage1_misses_counts_what_stage1_gets_wrong(ceiling):
    torch.manual_seed(0)
    # Untrained with the input skip: stage 1 is classical phase correlation of the pixels,
    # which misses most heterogeneous pairs (Table 1's classical row).
    model = DPCN(base_channels=2, depth=1, input_skip=True, rotation_scale_downsample=2, spectrum_window_grid=3)
    report = ceiling.stage1_misses(model, pairs=6, peaks=3)
    template, source, pose = next(ceiling.batches("pixels", pairs=6))
    with torch.no_grad():
        rs, _ = model.eval().rotation_scale(template, source, 1, 3)
    misses = int((wrap_angle(rs.angle - pose[:, 2], period=180.0).abs() > 1.0).sum())
    assert report["misses"] == misses > 0
    assert report["rotation mod 180 within 1 deg, %"] == pytest.approx(100.0 * (6 - misses) / 6)
    assert 0 <= report["misses with the true peak among the 3 strongest"] <= misses
    assert report["median peak score, misses"] > 0


def test_stage1_misses_splits_the_pairs_by_visible_template_boundaries(ceiling):
    torch.manual_seed(0)
    model = DPCN(base_channels=2, depth=1, input_skip=True, rotation_scale_downsample=2)

    def bins(report):
        counts = {}
        for key in report:
            if match := re.search(r"visible (.+) \((\d+) pairs\)", key):
                counts[match.group(1)] = int(match.group(2))
        return counts

    every = ceiling.stage1_misses(model, pairs=4, peaks=1, contrast=0.0)  # every boundary has some contrast
    assert bins(every) == {"< 70 %": 0, "70-90 %": 0, ">= 90 %": 4}
    none = ceiling.stage1_misses(model, pairs=4, peaks=1, contrast=1.0)  # grey levels differ by < 0.8
    assert bins(none) == {"< 70 %": 4, "70-90 %": 0, ">= 90 %": 0}
    medians = [v for k, v in every.items() if k.startswith("median share") and v == v]  # not NaN
    assert medians and all(v == pytest.approx(1.0) for v in medians)
    medians = [v for k, v in none.items() if k.startswith("median share") and v == v]
    assert medians and all(v == 0.0 for v in medians)


def test_the_grain_rows_add_boundaries_to_the_visible_template(ceiling):
    # With an impossible grey contrast the visible template is empty; a grain threshold of 0
    # brings back every boundary between classes of different texture amplitude (all of them:
    # the amplitudes are continuous draws), and it never removes a visible boundary.
    none, _, _ = next(ceiling.batches("visible", 2, contrast=1.0, batch=2))
    grain, _, _ = next(ceiling.batches("visible", 2, contrast=1.0, batch=2, grain=0.0))
    every, _, _ = next(ceiling.batches("all-boundaries", 2, batch=2))
    assert none.abs().max() == 0.0
    torch.testing.assert_close(grain, every)
    some, _, _ = next(ceiling.batches("visible", 2, contrast=0.1, batch=2))
    more, _, _ = next(ceiling.batches("visible", 2, contrast=0.1, batch=2, grain=0.03))
    assert (more >= some).all() and (more > some).any()
