"""The notebook runs headless against a checkpoint from a real (tiny) training run."""

import os
import subprocess
import sys
from pathlib import Path

import nbformat
from nbclient import NotebookClient

from .test_training_cli import SMALL

REPO = Path(__file__).resolve().parents[1]


def execute(cwd: Path, ckpt: Path | None) -> str:
    """Run the notebook in ``cwd`` (with ``DPCN_CKPT=ckpt`` if given): the text it printed;
    checks that it drew its two figures."""
    nb = nbformat.read(REPO / "notebooks" / "match_pair.ipynb", as_version=4)
    if ckpt is not None:
        os.environ["DPCN_CKPT"] = str(ckpt)
    try:
        NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}).execute()
    finally:
        os.environ.pop("DPCN_CKPT", None)
    images = [o for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert len(images) == 2
    return "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))


def test_match_pair_notebook_executes(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DPCN_DEBUG", "DPCN_COMMAND", "DPCN_CKPT")}
    # the default run directory, outputs/fit/<time>/, as `python -m dpcn fit` makes it
    fit = [sys.executable, "-m", "dpcn", "fit", *SMALL]
    subprocess.run(fit, check=True, capture_output=True, cwd=tmp_path, env=env)
    (ckpt,) = tmp_path.glob("outputs/fit/*/checkpoints/last.ckpt")
    text = execute(tmp_path, ckpt)
    assert "estimated" in text and "model built for (32, 32)" in text
    # Without DPCN_CKPT, from notebooks/ as Jupyter runs it: the newest run one folder up
    # (it looked for outputs/fit/latest/, which nothing writes).
    (tmp_path / "notebooks").mkdir()
    text = execute(tmp_path / "notebooks", None)
    assert f"checkpoint: ../outputs/fit/{ckpt.parents[1].name}/checkpoints/last.ckpt" in text
    assert "estimated" in text and "model built for (32, 32)" in text
