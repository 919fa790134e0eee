"""Command line: ``python -m dpcn <command> [key=value ...] [-m]`` (Hydra overrides).

Commands: ``predict`` (one pair -> JSON pose). The configuration tree is ``conf/`` at the
repository root (``conf/config.yaml``); every value there can be overridden.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("dpcn")

COMMANDS = ("predict",)

USAGE = f"""usage: python -m dpcn <command> [key=value ...] [-m] [--cfg job]

commands: {", ".join(COMMANDS)}
  predict template=A.png source=B.png [ckpt_path=model.ckpt]
      prints {{"tx", "ty", "angle", "scale", "confidence"}} as JSON

Any key of conf/config.yaml can be overridden with key=value (Hydra syntax).
Errors are one line on stderr (exit status 2); DPCN_DEBUG=1 shows the traceback."""


class CliError(Exception):
    """An error reported to the user as one line on stderr."""


def config_dir() -> Path:
    """The ``conf/`` tree: the repository's (source checkout, editable install)."""
    here = Path(__file__).resolve()
    for candidate in (here.parents[2] / "conf", here.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise CliError("cannot find the configuration tree conf/config.yaml (install dpcn with `pip install -e .`)")


def _resolve_device(name: str) -> str:
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise CliError(f"device={name} requested but CUDA is not available")
    return name


def run_predict(cfg: DictConfig) -> None:
    from .io import load_image, prepare_pair
    from .registration import register

    if not cfg.template or not cfg.source:
        raise CliError("predict needs template=PATH and source=PATH")
    device = _resolve_device(str(cfg.device))
    template, source = load_image(cfg.template), load_image(cfg.source)
    if cfg.ckpt_path:
        from .training.module import load_matcher

        matcher = load_matcher(cfg.ckpt_path, map_location=device)
        t, s = prepare_pair(template, source, device)
        pose = matcher.match(t, s)
    else:
        options = OmegaConf.to_container(cfg.registration, resolve=True)
        pose = register(template, source, device=device, **options)
    print(pose.to_json())


RUNNERS = {"predict": run_predict}


def _task(cfg: DictConfig) -> None:
    from .io import DpcnInputError

    command = _task.command  # type: ignore[attr-defined]
    try:
        RUNNERS[command](cfg)
    except (CliError, DpcnInputError, FileNotFoundError, ValueError, TypeError) as error:
        if os.environ.get("DPCN_DEBUG"):
            raise
        print(f"dpcn {command}: error: {error}", file=sys.stderr)
        sys.exit(2)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    command, overrides = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"dpcn: error: unknown command {command!r}; choose one of: {', '.join(COMMANDS)}", file=sys.stderr)
        sys.exit(2)
    try:
        conf = config_dir()
    except CliError as error:
        print(f"dpcn: error: {error}", file=sys.stderr)
        sys.exit(2)
    if command == "predict":
        # A query, not a run: no run directory, no log files, only the JSON on stdout.
        overrides = [
            "hydra.run.dir=.",
            "hydra.output_subdir=null",
            "hydra/job_logging=none",
            "hydra/hydra_logging=none",
            *overrides,
        ]
    _task.command = command  # type: ignore[attr-defined]
    sys.argv = [f"dpcn {command}", *overrides]
    hydra.main(version_base="1.3", config_path=str(conf), config_name="config")(_task)()
