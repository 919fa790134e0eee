"""The notebook runs headless against a checkpoint from a real (tiny) training run."""

import os
import subprocess
import sys
from pathlib import Path

import nbformat
from nbclient import NotebookClient

from .test_training_cli import SMALL

REPO = Path(__file__).resolve().parents[1]


def test_match_pair_notebook_executes(tmp_path):
    run = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if k not in ("DPCN_DEBUG", "DPCN_COMMAND")}
    subprocess.run(
        [sys.executable, "-m", "dpcn", "fit", *SMALL, f"hydra.run.dir={run}"],
        check=True,
        capture_output=True,
        cwd=tmp_path,
        env=env,
    )
    nb = nbformat.read(REPO / "notebooks" / "match_pair.ipynb", as_version=4)
    os.environ["DPCN_CKPT"] = str(run / "checkpoints" / "last.ckpt")
    try:
        NotebookClient(
            nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
        ).execute()
    finally:
        os.environ.pop("DPCN_CKPT", None)
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
    assert "estimated" in text and "model built for (32, 32)" in text
    images = [o for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert len(images) == 2
