"""trainer.precision=auto: bfloat16 mixed precision where the hardware computes it, else float32."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import pytest
import torch

from dpcn import cli
from dpcn.training.precision import auto_precision, cpu_computes_bfloat16

from .conftest import compose_config
from .test_training_cli import SMALL, fit


def _cpu_flags() -> set[str]:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the kernel's /proc/cpuinfo")
def test_the_cpu_probe_agrees_with_the_kernel():
    """PyTorch's private probes against the kernel's own list of the CPU's features."""
    flags = _cpu_flags()
    assert cpu_computes_bfloat16() == bool({"avx512_bf16", "amx_bf16"} & flags)


@pytest.mark.parametrize("native", [True, False])
def test_cpu_training_is_bfloat16_exactly_where_the_cpu_computes_it(monkeypatch, native):
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: native, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for accelerator in ("cpu", "auto"):
        precision, why = auto_precision(accelerator)
        assert precision == ("bf16-mixed" if native else "32-true")
        assert "CPU" in why


def test_gpu_training_without_a_gpu_or_on_other_accelerators_is_float32(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert auto_precision("gpu")[0] == "32-true"
    precision, why = auto_precision("mps")
    assert precision == "32-true" and "mps" in why


def test_a_gpu_that_computes_bfloat16_trains_in_it(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for supported in (True, False):
        monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True, s=supported: s)
        assert auto_precision("gpu")[0] == auto_precision("auto")[0] == ("bf16-mixed" if supported else "32-true")


@pytest.mark.parametrize("trainer", ["cpu", "auto", "ddp", "gpu"])
def test_every_trainer_config_asks_for_auto(trainer):
    assert compose_config(f"trainer={trainer}").trainer.precision == "auto"


@pytest.mark.parametrize("fit_run", [True, False], ids=["fit", "evaluation"])
def test_the_trainer_gets_the_resolved_precision(tmp_path, fit_run):
    trainer = cli._trainer(compose_config(*SMALL), tmp_path, fit=fit_run)
    assert trainer.precision == (auto_precision("cpu")[0] if fit_run else "32-true")
    explicit = cli._trainer(compose_config(*SMALL, "trainer.precision=32-true"), tmp_path, fit=fit_run)
    assert explicit.precision == "32-true"


def test_a_bfloat16_run_trains_float32_weights_and_says_so(tmp_path):
    """Whatever the CPU (emulated where it has no bfloat16): the run trains with finite losses,
    its checkpoint holds finite float32 weights, and `auto` says what it chose."""
    out = fit(tmp_path / "run", "trainer.precision=bf16-mixed", cwd=tmp_path)
    ckpt = torch.load(tmp_path / "run/checkpoints/last.ckpt", weights_only=False)
    weights = {k: v for k, v in ckpt["state_dict"].items() if v.is_floating_point()}
    assert all(v.dtype == torch.float32 and v.isfinite().all() for v in weights.values())
    assert ckpt["global_step"] == 2
    rows = csv.DictReader((tmp_path / "run/metrics.csv").open())
    losses = [float(r["train/loss"]) for r in rows if r.get("train/loss")]
    assert losses and all(math.isfinite(v) for v in losses)
    auto = fit(tmp_path / "auto", cwd=tmp_path)
    assert f"training precision {auto_precision('cpu')[0]} (trainer.precision=auto" in auto.stdout + auto.stderr
    assert "training precision" not in out.stdout + out.stderr  # an explicit precision is not announced
