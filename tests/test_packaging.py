"""A built wheel holds every module and every config, and its ``python -m dpcn`` runs outside
the checkout (``pip install .`` rather than the README's editable install)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np

from .conftest import angle_error, cv2_warp, photo

ROOT = Path(__file__).resolve().parents[1]


def _build_wheel(tmp_path: Path) -> Path:
    """The wheel of a copy of the checkout (setuptools writes build/ and egg-info beside the
    sources, which must not land in the repository)."""
    tree = tmp_path / "tree"
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    shutil.copytree(ROOT / "src", tree / "src", ignore=ignore)
    shutil.copytree(ROOT / "conf", tree / "conf", ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, tree / name)
    dist = tmp_path / "dist"
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", str(tree), "-w", str(dist)],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    (wheel,) = dist.glob("dpcn-*.whl")
    return wheel


def test_wheel_carries_every_module_and_config_and_its_cli_runs(tmp_path):
    wheel = _build_wheel(tmp_path)
    names = set(zipfile.ZipFile(wheel).namelist())
    modules = {f"dpcn/{p.relative_to(ROOT / 'src' / 'dpcn').as_posix()}" for p in (ROOT / "src" / "dpcn").rglob("*.py")}
    configs = {f"dpcn/conf/{p.relative_to(ROOT / 'conf').as_posix()}" for p in (ROOT / "conf").rglob("*.yaml")}
    assert "dpcn/conf/config.yaml" in configs and "dpcn/conf/data/l2sat.yaml" in configs
    assert modules - names == set() and configs - names == set()

    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    run = tmp_path / "run"  # outside the checkout: only the wheel's files can be found
    run.mkdir()
    template = photo("camera")
    cv2.imwrite(str(run / "t.png"), (template * 255).round().astype(np.uint8))
    cv2.imwrite(str(run / "s.png"), (cv2_warp(template, 6.0, -9.0, 37.0, 1.1) * 255).round().astype(np.uint8))
    env = {**{k: v for k, v in os.environ.items() if k != "DPCN_DEBUG"}, "PYTHONPATH": str(site)}

    def dpcn(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=run, env=env)

    where = dpcn("-c", "import dpcn.cli; print(dpcn.cli.__file__); print(dpcn.cli.config_dir())")
    assert where.returncode == 0, where.stderr
    assert where.stdout.split() == [str(site / "dpcn" / "cli.py"), str(site / "dpcn" / "conf")]
    out = dpcn("-m", "dpcn", "predict", "template=t.png", "source=s.png")
    assert out.returncode == 0, out.stderr
    pose = json.loads(out.stdout)
    assert abs(pose["tx"] - 6.0) < 0.5 and abs(pose["ty"] + 9.0) < 0.5
    assert angle_error(pose["angle"], 37.0) < 0.3 and abs(pose["scale"] - 1.1) < 0.01
    assert sorted(p.name for p in run.iterdir()) == ["s.png", "t.png"]
