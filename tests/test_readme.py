"""The README's Python examples run as written (on real photographs and a real checkpoint file)."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from dpcn import Pose
from dpcn.models.dpcn import DPCNOutput

from .conftest import angle_error, cv2_warp, photo, write_checkpoint

README = Path(__file__).resolve().parents[1] / "README.md"


def python_examples() -> list[str]:
    """The ```python blocks of the README's "Python" section, in order."""
    text = README.read_text()
    section = text[text.index("\n## Python\n") : text.index("\n## Command line\n")]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_the_python_section_has_its_three_examples():
    blocks = python_examples()
    assert len(blocks) == 3
    assert "dpcn.register(template, source)" in blocks[0]
    assert "DPCNModule.load_from_checkpoint(" in blocks[1]
    assert "dpcn.load_model(" in blocks[2]


def test_classical_example_recovers_an_opencv_pose():
    template = photo("camera")
    namespace = {"template": template, "source": cv2_warp(template, 12.0, -7.0, 30.0, 1.1)}
    exec(python_examples()[0], namespace)
    values = namespace["pose"].to_dict()
    assert set(values) == {"tx", "ty", "angle", "scale", "confidence"}
    assert abs(values["tx"] - 12.0) < 0.5 and abs(values["ty"] + 7.0) < 0.5
    assert angle_error(values["angle"], 30.0) < 0.5 and abs(values["scale"] - 1.1) < 0.01


def test_checkpoint_example_runs_on_a_checkpoint_file(tmp_path):
    path = write_checkpoint(tmp_path / "last.ckpt", "image_size=64")
    code = python_examples()[1]
    assert code.count('"outputs/fit/<time>/checkpoints/last.ckpt"') == 1
    template, other = photo("camera", (64, 64)), photo("astronaut", (64, 64))
    namespace = {
        "template": template,
        "source": cv2_warp(template, 3.0, 2.0, 20.0, 1.0),
        "template_batch": torch.from_numpy(template)[None, None].repeat(2, 1, 1, 1),
        "source_batch": torch.from_numpy(other)[None, None].repeat(2, 1, 1, 1),
    }
    exec(code.replace("outputs/fit/<time>/checkpoints/last.ckpt", str(path)), namespace)
    assert isinstance(namespace["pose"], Pose) and len(namespace["pose"]) == 1
    assert isinstance(namespace["out"], DPCNOutput) and namespace["out"].pose.tx.shape == (2,)


def test_load_model_example_matches_as_the_lightning_module_does(tmp_path):
    path = write_checkpoint(tmp_path / "last.ckpt", "image_size=64")
    code = python_examples()[2]
    assert code.count('"outputs/fit/<time>/checkpoints/last.ckpt"') == 1
    template = photo("camera", (64, 64))
    namespace = {"template": template, "source": cv2_warp(template, 3.0, 2.0, 20.0, 1.0)}
    exec(code.replace("outputs/fit/<time>/checkpoints/last.ckpt", str(path)), namespace)
    module = {"template": namespace["template"], "source": namespace["source"]}
    exec(python_examples()[1].replace("outputs/fit/<time>/checkpoints/last.ckpt", str(path)).split("out =")[0], module)
    torch.testing.assert_close(namespace["pose"].as_tensor(), module["pose"].as_tensor(), rtol=0, atol=0)
