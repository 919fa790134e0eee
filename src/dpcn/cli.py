"""Command line: ``python -m dpcn <command> [key=value ...] [-m]`` (Hydra overrides).

Commands: ``fit`` (train DPCN), ``validate``/``test`` (the paper's metrics of a checkpoint or
of ``model=classical``), ``predict`` (one pair -> JSON pose; ``pairs=CSV`` -> a CSV of poses). The configuration tree is
``conf/`` at the repository root (``conf/config.yaml``; a wheel carries it as ``dpcn/conf``); every
value there can be overridden.
This module only parses, builds (``hydra.utils.instantiate``) and reports: the work is done
by :mod:`dpcn.training`, :mod:`dpcn.data` and :mod:`dpcn.registration`.
"""

from __future__ import annotations

import io
import logging
import os
import signal
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import hydra
from omegaconf import DictConfig, OmegaConf

from ._validate import check_int
from .checkpoint import INFERENCE_SETTINGS

if TYPE_CHECKING:
    from torch import Tensor

    from .pose import Pose

log = logging.getLogger("dpcn")

COMMANDS = ("fit", "validate", "test", "predict", "make-data")

USAGE = """usage: python -m dpcn <command> [key=value ...] [-m] [--cfg job]

commands: {commands}
  fit [data={data}]
      [model={model}] [loss={loss}] [trainer={trainer}]
      [experiment={experiment}] [ckpt_path=.../last.ckpt to resume]
      [init_from=model.ckpt to start from its weights] [model.freeze=[rotation_scale]]
      trains DPCN; run directory outputs/fit/<time>/ (checkpoints/, metrics.csv, .hydra/)
  validate|test ckpt_path=model.ckpt [data=...]     (or model=classical, no checkpoint)
      prints the paper's metrics table and writes metrics_<stage>.csv in the run directory
  predict template=A.png source=B.png [out=pose.json] [ckpt_path=model.ckpt]
      prints {{"tx", "ty", "angle", "scale", "confidence"}} as JSON (stdout, or out=FILE)
  predict pairs=DIR/pairs.csv [out=poses.csv] [ckpt_path=model.ckpt]
      the pose of every pair the CSV names (images DIR/template/<name>.png, DIR/source/<name>.png),
      as CSV rows name,tx,ty,angle,scale,confidence (stdout, or out=FILE)
  make-data out=DIR [n_scenes=8] [scene_size=[1280,2560]] [split_gap=630] [seed=0]
      writes procedural scenes (lidar, stereo, drone, satellite + masks + regions.json) in
      the layout that data=l2d|l2sat|s2d|s2sat data.root=DIR reads
  -m key=a,b ...   a Hydra multirun sweep (runs under multirun/<time>/<n>/)

Any key of conf/config.yaml can be overridden with key=value (Hydra syntax); `<command> --cfg job`
prints the composed configuration, --hydra-help Hydra's own flags.
Errors are one line on stderr (exit status 2); DPCN_DEBUG=1 shows the traceback."""
GROUPS = ("data", "model", "loss", "trainer", "experiment")  # the config groups the usage lists


def usage() -> str:
    """The help text, each config group's options read from ``conf/`` (the default first), so
    that a new data, model or experiment config appears in it."""
    try:
        conf = config_dir()
    except CliError:
        return USAGE.format(commands=", ".join(COMMANDS), **{group: "..." for group in GROUPS})
    defaults: dict[str, str] = {}
    for entry in OmegaConf.load(conf / "config.yaml").get("defaults", []):
        if isinstance(entry, DictConfig):
            defaults.update({str(k): str(v) for k, v in entry.items()})
    options = {}
    for group in GROUPS:
        # model=classical is not trained: it is validate/test/predict's classical estimator
        names = sorted(p.stem for p in (conf / group).glob("*.yaml") if (group, p.stem) != ("model", "classical"))
        first = [name for name in names if name == defaults.get(group)]
        options[group] = "|".join(first + [name for name in names if name not in first])
    return USAGE.format(commands=", ".join(COMMANDS), **options)


class CliError(Exception):
    """An error reported to the user as one line on stderr."""


class RunInterrupted(Exception):
    """A run stopped from outside (SIGTERM, Ctrl-C): one line on stderr saying what it left
    (for ``fit``, what ``last.ckpt`` holds and how to resume), and the shell's exit status for
    that signal."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def config_dir() -> Path:
    """The ``conf/`` tree: the repository's (source checkout, editable install), else the copy
    that a built wheel carries as ``dpcn/conf`` (``pip install .``)."""
    here = Path(__file__).resolve()
    for candidate in (here.parents[2] / "conf", here.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise CliError(
        f"cannot find the configuration tree: neither {here.parents[2] / 'conf'} nor {here.parent / 'conf'} "
        "holds config.yaml (reinstall dpcn: `pip install -e .` in a checkout, or `pip install .`)"
    )


def _resolve_device(name: str) -> str:
    import torch

    from ._validate import check_device

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        check_device("device", name)
    except ValueError as error:
        raise CliError(str(error)) from None
    return name


# Top-level keys that override a checkpoint's inference settings (validate/test/predict; fit
# ignores them): the loaders' own list, so that a new setting reaches the command line once.
INFERENCE_KEYS = INFERENCE_SETTINGS


# The classical estimator's settings of the same name, where it has one.
CLASSICAL_EQUIVALENTS = {
    "inference_sigma": "registration.sigma",
    "rotation_range": "registration.rotation_range",
    "scale_range": "registration.scale_range",
    "spectrum_window_grid": "registration.spectrum_window_grid",
}


def inference_settings(cfg: DictConfig) -> dict[str, int | str | None]:
    """The top-level overrides of a checkpoint's inference settings (``None``: keep)."""
    return {key: cfg.get(key) for key in INFERENCE_KEYS}


def check_no_inference_overrides(command_line: list[str]) -> None:
    """Without a checkpoint the classical estimator runs, which the top-level inference keys do
    not reach: one given on the command line (``predict ... rotation_range=[0,180]``) is a
    :class:`CliError` naming the setting that would apply, not a silently ignored value. Keys
    an ``experiment=`` sets are meant for a checkpoint and stay unused."""
    given = [o.split("=", 1)[0].lstrip("+~") for o in command_line]
    for key in (k for k in INFERENCE_KEYS if k in given):
        instead = CLASSICAL_EQUIVALENTS.get(key)
        runs = "without one the classical estimator runs"
        what = f"{runs}: set {instead}= instead" if instead else f"{runs}, which has no such setting"
        raise CliError(f"{key}= applies to a checkpoint (ckpt_path=PATH); {what}")


def _command_line() -> list[str]:
    """This run's overrides as given on the command line (one job's values under -m)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task)


def _pair_matcher(
    cfg: DictConfig, device: str
) -> tuple[Callable[[Tensor, Tensor], Pose], Callable[[object, object], tuple[Tensor, Tensor]]]:
    """``predict``'s matcher of ``(B, C, H, W)`` pairs, and what turns two loaded images into its
    checked input (raises ``ValueError`` naming the problem): the checkpoint's DPCN, its images
    converted to the model's channels as the data sets convert them, or without ``ckpt_path``
    the classical estimator with the ``registration`` settings. Neither needs Lightning, whose
    import would double the command's start-up."""
    from .io import flag_featureless, prepare_pair

    if cfg.ckpt_path:
        from .checkpoint import load_model

        model = load_model(cfg.ckpt_path, device, **inference_settings(cfg))
        match, check, channels = model.match, model.check_inputs, model.in_channels
    else:
        import torch

        from .estimator import PhaseCorrelationEstimator

        check_no_inference_overrides(_command_line())
        estimator = PhaseCorrelationEstimator(**OmegaConf.to_container(cfg.registration, resolve=True)).to(device)

        @torch.no_grad()
        def match(template: Tensor, source: Tensor) -> Pose:
            return flag_featureless(estimator(template, source), template, source)

        check, channels = estimator.check_inputs, None

    def prepare(template: object, source: object) -> tuple[Tensor, Tensor]:
        pair = prepare_pair(template, source, device, channels)
        check(*pair)
        return pair

    return match, prepare


def run_predict(cfg: DictConfig) -> None:
    from .io import load_image

    if cfg.get("pairs"):
        if cfg.template or cfg.source:
            raise CliError("predict takes template=PATH and source=PATH, or pairs=CSV, not both")
        _predict_pairs(cfg)
        return
    if not cfg.template or not cfg.source:
        raise CliError("predict needs template=PATH and source=PATH (or pairs=CSV)")
    out = _output_file(cfg)
    device = _resolve_device(str(cfg.device))
    template, source = load_image(cfg.template), load_image(cfg.source)
    match, prepare = _pair_matcher(cfg, device)
    pose = match(*prepare(template, source)).to_json()
    if out is None:
        print(pose)
    else:
        _write_whole(out, pose + "\n")
        print(f"pose written to {out}", file=sys.stderr)


def _output_file(cfg: DictConfig) -> Path | None:
    """``predict``'s ``out=FILE`` (``None``: stdout), its folder checked before any work."""
    out = Path(cfg.out) if cfg.out else None
    if out is not None and not out.parent.is_dir():
        raise CliError(f"out={out}: folder {out.parent} does not exist")
    return out


def _write_whole(out: Path, text: str) -> None:
    """``text`` into ``out``, written whole or not at all (a partial file, then a rename)."""
    partial = out.with_name(f".{out.name}.partial")
    partial.write_text(text)
    os.replace(partial, out)


def _predict_pairs(cfg: DictConfig) -> None:
    """``predict pairs=CSV``: the pose of every listed pair, as CSV rows ``name, tx, ty, angle,
    scale, confidence`` in the CSV's order, on stdout or atomically into ``out=FILE``.
    Consecutive pairs of one size are matched ``predict_batch_size`` at a time."""
    import csv

    import torch

    from .data.aeroground import CsvPairs
    from .io import load_image

    size = check_int("predict_batch_size", cfg.predict_batch_size, 1)
    device = _resolve_device(str(cfg.device))
    rows = CsvPairs(cfg.pairs, poses=False).rows  # names and image paths, checked up front
    match, prepare = _pair_matcher(cfg, device)
    out = _output_file(cfg)
    stream = io.StringIO() if out is not None else sys.stdout
    writer = csv.writer(stream, lineterminator="\n")
    writer.writerow(["name", "tx", "ty", "angle", "scale", "confidence"])
    batch: list[tuple[str, Tensor, Tensor]] = []

    def flush() -> None:
        pose = match(torch.cat([t for _, t, _ in batch]), torch.cat([s for _, _, s in batch]))
        for i, (name, _, _) in enumerate(batch):
            values = pose[i].to_dict()
            writer.writerow([name, *(f"{values[k]:.6g}" for k in ("tx", "ty", "angle", "scale", "confidence"))])
        batch.clear()

    for row in rows:
        try:
            # checked before its batch: the error names this pair
            template, source = prepare(load_image(row["template"]), load_image(row["source"]))
        except ValueError as error:  # DpcnInputError included
            raise CliError(f"{cfg.pairs}: pair {row['name']!r}: {error}") from None
        if batch and (template.shape != batch[0][1].shape or source.shape != batch[0][2].shape):
            flush()
        batch.append((row["name"], template, source))
        if len(batch) == size:
            flush()
    if batch:
        flush()
    if out is not None:
        _write_whole(out, stream.getvalue())
        print(f"poses of {len(rows)} pairs written to {out}", file=sys.stderr)


def _seed(cfg: DictConfig) -> int:
    """``cfg.seed``, an integer in ``[0, 2**32)`` (numpy's range), checked by name: Lightning's
    own errors say ``invalid literal for int()`` or ``-1 is not in bounds``."""
    seed = check_int("seed", cfg.seed, low=0)
    if seed >= 2**32:
        raise ValueError(f"seed must be an integer < 2**32, got {seed}")
    return seed


def _run_dir() -> Path:
    from hydra.core.hydra_config import HydraConfig

    return Path(HydraConfig.get().runtime.output_dir)


def _check_ckpt(path: str | None) -> Path | None:
    if not path:
        return None
    from .checkpoint import checkpoint_file

    return checkpoint_file(path)


# Trainer settings checked here: Lightning rejects a string with a bare assertion.
_TRAINER_INTS = {"max_epochs": -1, "min_epochs": 0, "max_steps": -1, "num_nodes": 1, "log_every_n_steps": 1,
                 "check_val_every_n_epoch": 1, "accumulate_grad_batches": 1}  # fmt: skip


def _usable_cores() -> int:
    """CPU cores this process may run on (its affinity where the OS tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _check_trainer(cfg: DictConfig) -> None:
    import torch

    from ._validate import check_number
    from .training.precision import AUTO, LIGHTNING_PRECISIONS

    accelerator = str(cfg.trainer.get("accelerator", "auto"))
    if accelerator in ("gpu", "cuda") and not (torch.cuda.is_available() or torch.backends.mps.is_available()):
        raise ValueError(
            f"trainer.accelerator={accelerator}: this machine has no GPU that torch can use "
            f"(torch {torch.__version__}); use trainer=auto or trainer=cpu"
        )

    for key, low in _TRAINER_INTS.items():
        if cfg.trainer.get(key) is not None:
            check_int(f"trainer.{key}", cfg.trainer[key], low=low)
    devices, cores = cfg.trainer.get("devices"), _usable_cores()
    if accelerator == "cpu" and isinstance(devices, int) and devices > cores:
        # Lightning runs it, but the processes share the cores: slower than `devices=<cores>`.
        log.warning(
            "trainer.devices=%d CPU processes on %d usable cores: they share the cores, which is slower "
            "than trainer.devices=%d",
            devices,
            cores,
            cores,
        )
    if cfg.trainer.get("gradient_clip_val") is not None:
        check_number("trainer.gradient_clip_val", cfg.trainer.gradient_clip_val, low=0.0)
    precision = cfg.trainer.get("precision")
    if precision is not None and str(precision) not in (AUTO, *LIGHTNING_PRECISIONS):
        raise ValueError(
            f"trainer.precision must be auto or one of Lightning's {', '.join(LIGHTNING_PRECISIONS[:6])}, "
            f"got {precision!r}"
        )
    if cfg.get("checkpoint_every_n_steps") is not None:
        check_int("checkpoint_every_n_steps", cfg.checkpoint_every_n_steps, low=1)
    decay = cfg.get("ema_decay")
    if decay is not None and not (isinstance(decay, float | int) and not isinstance(decay, bool) and 0 < decay < 1):
        raise ValueError(f"ema_decay must be a number in (0, 1) or null, got {decay!r}")


def _precision(cfg: DictConfig, fit: bool) -> str | int:
    """``trainer.precision``, with ``auto`` resolved: by the hardware for training, float32 for
    evaluation (whose numbers the README reports in float32; ``unet_dtype=bfloat16`` is the
    low-precision inference setting)."""
    from .training.precision import AUTO, FP32, auto_precision

    precision = cfg.trainer.get("precision", AUTO)  # checked by _check_trainer
    if str(precision) != AUTO:
        return precision
    if not fit:
        return FP32
    chosen, why = auto_precision(cfg.trainer.get("accelerator", AUTO))
    log.info("training precision %s (trainer.precision=auto: %s); trainer.precision=32-true: float32", chosen, why)
    return chosen


def _drop_records_starting(logger_name: str, prefix: str) -> None:
    """Filter the log records of ``logger_name`` whose message starts with ``prefix`` (once)."""
    logger = logging.getLogger(logger_name)
    if any(getattr(f, "_dpcn_prefix", None) == prefix for f in logger.filters):
        return

    def keep(record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(prefix)

    keep._dpcn_prefix = prefix  # type: ignore[attr-defined]
    logger.addFilter(keep)


def _trainer(cfg: DictConfig, run_dir: Path, fit: bool):
    import importlib.util

    from hydra.utils import instantiate
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    from .training.checkpointing import AtomicCheckpointIO, StopQuietsWorkersFirst

    _check_trainer(cfg)
    # metrics.csv goes straight into the run directory, beside Hydra's files (hence the filter:
    # the logger would warn that the directory is not empty).
    warnings.filterwarnings("ignore", message="Experiment logs directory .* exists and is not empty")
    # The model summary sizes bf16-mixed weights as float32, which they are (autocast, not casting).
    warnings.filterwarnings("ignore", message="Precision bf16-mixed is not supported by the model summary")
    # Lightning 2.6 with torch 2.13 warns about its own pytree code, and advertises cloud
    # services on every run: nothing the user can act on, so neither reaches the output.
    warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated")
    _drop_records_starting("lightning.pytorch.utilities.rank_zero", "💡 Tip:")
    loggers = [CSVLogger(save_dir=str(run_dir), name="", version="")]
    if importlib.util.find_spec("tensorboard") is not None:
        loggers.append(TensorBoardLogger(save_dir=str(run_dir), name="", version="tb"))
    callbacks = [StopQuietsWorkersFirst()]  # a stop records itself before dying workers can raise
    if fit:
        ckpt_dir = run_dir / "checkpoints"
        every = cfg.checkpoint_every_n_steps
        callbacks += [
            # last.ckpt: the latest state, every epoch (or every N steps) and whenever the run
            # stops on an exception, Ctrl-C or SIGTERM; `fit ckpt_path=.../last.ckpt` resumes it.
            ModelCheckpoint(
                dirpath=ckpt_dir,
                filename="last",
                monitor=None,
                save_top_k=1,
                enable_version_counter=False,
                every_n_train_steps=every,
                every_n_epochs=None if every else 1,
                save_on_exception=True,
            ),
            # best-*.ckpt: the best validation score so far (mean of the strict accuracies).
            ModelCheckpoint(
                dirpath=ckpt_dir,
                filename="best-epoch{epoch:03d}-score{val/score:.2f}",
                auto_insert_metric_name=False,
                monitor="val/score",
                mode="max",
                save_top_k=1,
            ),
            LearningRateMonitor(logging_interval="step"),
        ]
        if cfg.get("ema_decay") is not None:
            try:
                from lightning.pytorch.callbacks import EMAWeightAveraging
            except ImportError:  # Lightning 2.6+; pyproject allows older
                raise CliError(
                    "ema_decay needs lightning>=2.6 (EMAWeightAveraging): pip install -U lightning"
                ) from None

            # Validation, the checkpoints' weights and the trained model are the moving
            # average; the raw weights travel in the checkpoint too, so a resume is exact.
            callbacks.append(EMAWeightAveraging(decay=float(cfg.ema_decay)))
    return instantiate(
        cfg.trainer,
        precision=_precision(cfg, fit),
        default_root_dir=str(run_dir),
        logger=loggers,
        callbacks=callbacks,
        plugins=[AtomicCheckpointIO()],
        enable_checkpointing=fit,
    )


def _is_worker_shutdown_noise(unraisable: sys.UnraisableHookArgs) -> bool:
    """Whether an exception Python could not raise (``sys.unraisablehook``'s argument) is a
    DataLoader worker's death reported from inside the loader's ``__del__``.

    A signal to the whole process group (a scheduler, ``kill -- -PGID``, Ctrl-C) kills the
    data workers with the run. PyTorch's SIGCHLD handler reports a dead worker by raising
    wherever the main thread is; when that is the loader's own ``__del__`` (shutting the
    workers down), Python can only print the traceback. The run has then already reported the
    stop (or, for a worker that crashed on its own, raised the same error where it could).
    Also CPython's report of a SIGCHLD that came just as the handler was turned off for a stop
    or a checkpoint write (:mod:`dpcn.training.checkpointing`): it is dropped, as intended."""
    where = getattr(getattr(unraisable, "object", None), "__qualname__", "")
    error = getattr(unraisable, "exc_value", None)
    if isinstance(error, OSError) and hasattr(signal, "SIGCHLD"):
        # A worker's SIGCHLD that arrived just as its handler was turned off (after a stop,
        # and while a checkpoint is written): CPython reports it instead of running a handler.
        return str(error) == f"Signal {int(signal.SIGCHLD)} ignored due to race condition"
    return (
        where.endswith("DataLoaderIter.__del__")
        and isinstance(error, RuntimeError)
        and str(error).startswith("DataLoader worker")
    )


def quiet_worker_shutdown() -> None:
    """Keep the worker-death tracebacks of :func:`_is_worker_shutdown_noise` off stderr (they
    go to the debug log) for the rest of the process; every other unraisable exception is
    printed as before. A no-op if already installed."""
    previous = sys.unraisablehook
    if getattr(previous, "_dpcn_quiet_workers", False):
        return

    def hook(unraisable: sys.UnraisableHookArgs) -> None:
        if _is_worker_shutdown_noise(unraisable):
            log.debug("data worker shutdown after a stop: %s", unraisable.exc_value)
            return
        previous(unraisable)

    hook._dpcn_quiet_workers = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook


def _stop_signal(trainer, error: BaseException) -> str | None:
    """``"SIGTERM"`` or ``"Ctrl-C"`` when ``error`` ended a Lightning run because of that
    signal, else ``None``. Lightning turns a Ctrl-C's KeyboardInterrupt into SystemExit; a
    SIGTERM surfaces as Lightning's SIGTERMException or as the DataLoader's "worker killed"
    error (the workers got it too)."""
    if trainer.received_sigterm:
        return "SIGTERM"
    return "Ctrl-C" if isinstance(error, SystemExit) and trainer.interrupted else None


def _exit_code(signal_name: str) -> int:
    return 143 if signal_name == "SIGTERM" else 130  # 128 + the signal's number, as shells report it


def _interrupted(run_dir: Path, signal_name: str) -> RunInterrupted:
    """What an interrupted run left behind, for the one line the user sees."""
    import torch

    last = run_dir / "checkpoints" / "last.ckpt"
    code = _exit_code(signal_name)
    try:
        step = torch.load(last, map_location="cpu", weights_only=True)["global_step"]
    except Exception:  # none written yet (stopped before the first step), or unreadable
        return RunInterrupted(f"stopped by {signal_name}; no checkpoint to resume from in {last.parent}", code)
    return RunInterrupted(
        f"stopped by {signal_name}; {last} holds the run after {step} training steps: "
        f"the same command with ckpt_path={last} resumes it",
        code,
    )


def _start_lightning(cfg: DictConfig) -> None:
    """What ``fit``, ``validate`` and ``test`` do first: Lightning's lines printed once, then
    the seed. Lightning's package logger has its own stderr handler besides the root's that
    Hydra sets up (the console and the run's log file), so every Lightning line (the model
    summary too) was printed twice; the root's handlers stay, the log file keeps the lines."""
    import lightning as L  # importing it adds the handler

    if logging.getLogger().handlers:  # without Hydra's logging (hydra/job_logging=none), Lightning's stays
        logger = logging.getLogger("lightning")
        for handler in list(logger.handlers):
            if type(handler) is logging.StreamHandler:
                logger.removeHandler(handler)
    L.seed_everything(_seed(cfg), workers=True)


def run_fit(cfg: DictConfig) -> None:
    from hydra.utils import instantiate

    from .training.checkpointing import stop_quiets_worker_deaths
    from .training.module import DPCNModule, load_weights

    ckpt = _check_ckpt(cfg.ckpt_path)
    _start_lightning(cfg)
    run_dir = _run_dir()
    datamodule = instantiate(cfg.data)
    module = instantiate(cfg.model, _convert_="all")
    if not isinstance(module, DPCNModule):
        raise CliError(f"fit trains a DPCN model; model={cfg.model._target_} has nothing to train")
    if cfg.ckpt_path:
        from .training.module import check_resumable, load_matcher

        load_matcher(ckpt)  # a clear error now rather than a traceback from inside Lightning
        check_resumable(module, ckpt)
    if cfg.get("init_from"):  # a resumed run (ckpt_path) then restores its own weights over these
        load_weights(module, cfg.init_from)
        log.info("starting from the weights of %s", cfg.init_from)
    log.info("data: %s, run directory: %s", datamodule.name, run_dir)
    trainer = _trainer(cfg, run_dir, fit=True)
    quiet_worker_shutdown()
    try:
        with stop_quiets_worker_deaths():
            trainer.fit(module, datamodule=datamodule, ckpt_path=str(ckpt) if ckpt else None)
    except BaseException as error:
        # Lightning has already written last.ckpt (save_on_exception; nothing before the first step).
        signal_name = _stop_signal(trainer, error)
        if signal_name is None or trainer.global_rank != 0:
            raise
        raise _interrupted(run_dir, signal_name) from None
    if trainer.global_rank == 0:
        best = next((c.best_model_path for c in trainer.checkpoint_callbacks if c.monitor), "")
        last = "last.ckpt" if (run_dir / "checkpoints" / "last.ckpt").is_file() else "-"  # none after 0 steps
        print(f"checkpoints: {run_dir / 'checkpoints'} (best: {Path(best).name if best else '-'}, last: {last})")
        table = module.report("val", f"{datamodule.name} (val, last epoch)", run_dir)
        if table:
            print(table)


def _run_evaluation(cfg: DictConfig, stage: str) -> None:
    from hydra.utils import instantiate

    from .training.module import ClassicalModule, load_matcher

    _start_lightning(cfg)
    run_dir = _run_dir()
    datamodule = instantiate(cfg.data)
    ckpt = _check_ckpt(cfg.ckpt_path)
    if ckpt is not None:
        module = load_matcher(ckpt, **inference_settings(cfg))
        module.translation_threshold = float(cfg.data.translation_threshold)
        name = f"DPCN {ckpt.name}"
        built, cut = module.model.image_size, OmegaConf.select(cfg, "data.dataset.size")
        square = built is not None and built[0] == built[1]
        if square and cut == cfg.image_size and built != (cut, cut):  # data cut at image_size: say which to set
            raise CliError(
                f"{ckpt}: this model was built for {built[0]}x{built[1]} images, got {cut}x{cut} "
                f"(data={datamodule.name} cuts its pairs at image_size={cut}): add image_size={built[0]}"
            )
    else:
        module = _classical_module(cfg) if _is_classical(cfg) else instantiate(cfg.model, _convert_="all")
        if not isinstance(module, ClassicalModule):
            raise CliError(
                f"{stage} of a DPCN model needs ckpt_path=PATH (or model=classical for the classical estimator)"
            )
        check_no_inference_overrides(_command_line())
        name = "classical"
    trainer = _trainer(cfg, run_dir, fit=False)
    quiet_worker_shutdown()
    try:
        getattr(trainer, stage)(module, datamodule=datamodule)
    except BaseException as error:
        signal_name = _stop_signal(trainer, error)
        if signal_name is None or trainer.global_rank != 0:
            raise
        done = trainer.test_loop.batch_progress if stage == "test" else trainer.validate_loop.batch_progress
        raise RunInterrupted(
            f"stopped by {signal_name} after {done.current.completed} batches; no metrics written "
            "(they need every pair): run the command again",
            _exit_code(signal_name),
        ) from None
    if trainer.global_rank == 0:
        dataset = datamodule.datasets.get("test" if stage == "test" else "val")
        rows = getattr(dataset, "rows", None)  # pre-cut CSV pairs have names
        names = [row["name"] for row in rows] if rows else None
        print(module.report(stage, f"{name} on {datamodule.name}", run_dir, names))
        print(
            f"metrics written to {run_dir / f'metrics_{stage}.csv'} "
            f"(every pair: pairs_{stage}.csv; accuracy against threshold: accuracy_{stage}.csv)"
        )


def _is_classical(cfg: DictConfig) -> bool:
    return str(cfg.model.get("_target_", "")).endswith(".ClassicalModule")


def _classical_module(cfg: DictConfig):
    """``model=classical`` as composed, less the DPCN settings that an ``experiment=`` merges
    into ``model`` (``model.net``... of ``paper_table1``), which the classical estimator does
    not take: one log line names them, so that ``test model=classical experiment=...`` gives
    the classical row on the experiment's pairs."""
    import inspect

    from hydra.utils import instantiate

    from .estimator import PhaseCorrelationEstimator

    takes = {"_target_", "translation_threshold", *inspect.signature(PhaseCorrelationEstimator).parameters}
    options = OmegaConf.to_container(cfg.model, resolve=True)
    left_out = sorted(key for key in options if key not in takes)
    if left_out:
        log.info("model=classical leaves out %s: DPCN settings", ", ".join(f"model.{key}" for key in left_out))
    return instantiate({key: value for key, value in options.items() if key in takes}, _convert_="all")


def run_make_data(cfg: DictConfig) -> None:
    from .data.scene import make_dataset

    if not cfg.out:
        raise CliError("make-data needs out=DIR")
    out = Path(cfg.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"out={out} is a file, not a folder")
    if out.exists() and any(out.iterdir()):
        raise CliError(f"{out} exists and is not empty; choose a new folder")
    try:  # before minutes of rendering, not after
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CliError(f"cannot create out={out}: {error.strerror or error}") from None
    size = cfg.scene_size
    size = [size, size] if isinstance(size, (int, float)) else list(size)
    if len(size) != 2 or not all(isinstance(v, int) and v > 0 for v in size):
        raise CliError(f"scene_size must be one positive integer or [H, W], got {cfg.scene_size}")
    h, w = size
    n_scenes, gap = check_int("n_scenes", cfg.n_scenes, low=1), check_int("split_gap", cfg.split_gap, low=0)
    root = make_dataset(out, n_scenes=n_scenes, seed=_seed(cfg), size=(h, w), gap=gap)
    scenes = sorted(p.name for p in root.iterdir() if p.is_dir())
    print(f"wrote {len(scenes)} scenes ({', '.join(scenes)}) of {h}x{w} px (H x W) to {root}")


def run_validate(cfg: DictConfig) -> None:
    _run_evaluation(cfg, "validate")


def run_test(cfg: DictConfig) -> None:
    _run_evaluation(cfg, "test")


RUNNERS = {
    "fit": run_fit,
    "validate": run_validate,
    "test": run_test,
    "predict": run_predict,
    "make-data": run_make_data,
}


def one_line(error: BaseException) -> str:
    """An error as the one line the command line prints (also the benchmarks' scripts)."""
    from hydra.errors import InstantiationException

    if isinstance(error, InstantiationException) and error.__cause__ is not None:
        error = error.__cause__  # the constructor's own message, not Hydra's wrapper
    text = str(error).split("Config search path:")[0]  # Hydra's lookup details: noise here
    if text.startswith("Caught ") and "Original Traceback" in text:
        # Raised in a DataLoader worker: torch re-raises it with the worker's whole traceback
        # as its message; the error's own message is the traceback's last line, after its type.
        text = text.rstrip().splitlines()[-1].partition(": ")[2] or text
    return " ".join(text.split()) or type(error).__name__


def _task(cfg: DictConfig) -> None:
    from hydra.errors import InstantiationException

    from .io import DpcnInputError

    command = os.environ["DPCN_COMMAND"]
    try:
        RUNNERS[command](cfg)
    except RunInterrupted as stop:
        print(f"dpcn {command}: {stop}", file=sys.stderr)
        sys.exit(stop.exit_code)
    except (CliError, DpcnInputError, FileNotFoundError, ValueError, TypeError, InstantiationException) as error:
        if os.environ.get("DPCN_DEBUG"):
            raise
        print(f"dpcn {command}: error: {one_line(error)}", file=sys.stderr)
        sys.exit(2)


# Hydra's command-line flags that take a value (``--cfg job``); the others stand alone (``-m``).
_FLAGS_WITH_VALUE = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                     "--config-dir", "-cd", "--experimental-rerun", "--info", "-i"}  # fmt: skip


def _split_hydra_flags(args: list[str]) -> tuple[list[str], list[str]]:
    """Separate Hydra's flags from ``key=value`` overrides, so that flags may come anywhere
    (``fit data=l2d -m model.temperature=1,10``): Hydra's own parser wants them first."""
    flags, overrides = [], []
    i = 0
    while i < len(args):
        arg = args[i]
        if arg.startswith("-"):  # overrides never start with "-" (keys, "+key", "~key")
            flags.append(arg)
            takes_value = arg in _FLAGS_WITH_VALUE and i + 1 < len(args) and not args[i + 1].startswith("-")
            if takes_value and (arg not in ("--info", "-i") or "=" not in args[i + 1]):
                flags.append(args[i + 1])
                i += 1
        else:
            overrides.append(arg)
        i += 1
    return flags, overrides


def _check_overrides(conf: Path, overrides: list[str]) -> None:
    """Compose the configuration once with the user's overrides (the first value of each
    sweep) so that an unknown key, group or option is one clear line, not Hydra's report."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = [o for o in OverridesParser.create().parse_overrides(overrides) if not _is_hydra_key(o.get_key_element())]
    # Each sweep value is tried once, the other sweeps at their first value.
    choices = [
        [f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()] if o.is_sweep_override() else [o.input_line]
        for o in parsed
    ]
    first = [c[0] for c in choices if c]
    trials = [first] + [[*first[:i], v, *first[i + 1 :]] for i, c in enumerate(choices) for v in c[1:]]
    try:
        with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
            for trial in trials:
                compose("config", overrides=trial)
    finally:
        GlobalHydra.instance().clear()


def _is_hydra_key(key: str) -> bool:
    """Hydra's own settings (``hydra.run.dir``, ``hydra/launcher``) are Hydra's to check."""
    return key.lstrip("+~").startswith("hydra")


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return
    if (
        argv[0] not in COMMANDS
        and os.environ.get("DPCN_COMMAND") in COMMANDS
        and ("=" in argv[0] or argv[0].startswith("-"))
    ):
        # A DDP worker re-launched by Lightning with only the Hydra overrides.
        argv = [os.environ["DPCN_COMMAND"], *argv]
    command, overrides = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"dpcn: error: unknown command {command!r}; choose one of: {', '.join(COMMANDS)}", file=sys.stderr)
        sys.exit(2)
    if any(arg in ("-h", "--help") for arg in overrides):  # Hydra's --help would dump the whole config
        print(usage())
        return
    try:
        conf = config_dir()
    except CliError as error:
        print(f"dpcn: error: {error}", file=sys.stderr)
        sys.exit(2)
    if command in ("predict", "make-data"):
        # A query, not a run: no run directory, no log files, only the JSON on stdout.
        overrides = [
            "hydra.run.dir=.",
            "hydra.output_subdir=null",
            "hydra/job_logging=none",
            "hydra/hydra_logging=none",
            *overrides,
        ]
    os.environ["DPCN_COMMAND"] = command
    flags, overrides = _split_hydra_flags(overrides)
    try:
        _check_overrides(conf, overrides)
    except Exception as error:  # Hydra's parse/composition errors have several types
        if os.environ.get("DPCN_DEBUG"):
            raise
        print(f"dpcn {command}: error: {one_line(error)}", file=sys.stderr)
        sys.exit(2)
    sys.argv = [sys.argv[0], *flags, f"hydra.job.name={command}", *overrides]
    try:
        hydra.main(version_base="1.3", config_path=str(conf), config_name="config")(_task)()
    except ValueError as error:  # Hydra's check of its own flags ("only one of --run, --multirun ...")
        if os.environ.get("DPCN_DEBUG"):
            raise
        print(f"dpcn {command}: error: {one_line(error)}", file=sys.stderr)
        sys.exit(2)
