"""The sim-ceiling benchmark leans on private parts of dpcn.data.simulation: keep it honest."""

import importlib.util
from pathlib import Path

import pytest
import torch

import dpcn.data.simulation as sim


@pytest.fixture(scope="module")
def ceiling():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_sim_ceiling.py"
    spec = importlib.util.spec_from_file_location("bench_sim_ceiling", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
