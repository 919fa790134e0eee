"""Real Lightning runs through the real CLI and the real Hydra configs, on tiny settings."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from dpcn.pose import Pose
from dpcn.training.module import DPCNModule, load_matcher

from .conftest import compose_config

# A DPCN small enough to train a few steps in seconds on a CPU.
SMALL = [
    "image_size=32",
    "model.net.base_channels=2",
    "model.net.depth=1",
    "model.net.rotation_scale_base_channels=2",
    "model.net.rotation_scale_depth=1",
    "model.net.n_angles=32",
    "model.net.n_radii=32",
    "data.dataset.translation=4",
    "data.epoch_size=8",
    "data.batch_size=4",
    "data.val_length=4",
    "data.test_length=4",
    "data.num_workers=0",
    "trainer=cpu",
    "trainer.max_epochs=1",
    "trainer.enable_progress_bar=false",
    "trainer.enable_model_summary=false",
    "trainer.log_every_n_steps=1",
]


# The same without the DPCN architecture keys (for model=classical).
SMALL_DATA = [a for a in SMALL if not a.startswith("model.")]


def dpcn(*args: str, cwd: Path, check: bool = True, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("DPCN_DEBUG", "DPCN_COMMAND")} | (env or {})
    out = subprocess.run([sys.executable, "-m", "dpcn", *args], capture_output=True, text=True, cwd=cwd, env=env)
    if check and out.returncode != 0:
        raise AssertionError(f"dpcn {' '.join(args)} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return out


def fit(run_dir: Path, *extra: str, cwd: Path) -> subprocess.CompletedProcess:
    return dpcn("fit", *SMALL, f"hydra.run.dir={run_dir}", *extra, cwd=cwd)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """One short training run; its directory."""
    root = tmp_path_factory.mktemp("train")
    fit(root / "run", cwd=root)
    return root / "run"


def test_more_cpu_processes_than_cores_are_warned_about(caplog):
    from dpcn.cli import _check_trainer, _usable_cores

    cores = _usable_cores()
    ddp = ["trainer=ddp", "trainer.accelerator=cpu"]
    with caplog.at_level("WARNING", logger="dpcn"):
        _check_trainer(compose_config(*ddp, f"trainer.devices={cores}"))
        assert not caplog.records
        _check_trainer(compose_config(*ddp, f"trainer.devices={cores + 1}"))
    (record,) = caplog.records
    assert record.getMessage().startswith(f"trainer.devices={cores + 1} CPU processes on {cores} usable cores")


def test_fit_writes_a_run_directory(trained):
    assert (trained / "checkpoints" / "last.ckpt").is_file()
    assert (trained / ".hydra" / "config.yaml").is_file()
    rows = list(csv.DictReader((trained / "metrics.csv").open()))
    assert any(r.get("train/loss") for r in rows) and any(r.get("val/score") for r in rows)
    assert not list((trained / "checkpoints").glob(".*tmp*"))  # no half-written files left


def test_checkpoint_reloads_without_configs(trained):
    ckpt = trained / "checkpoints" / "last.ckpt"
    module = DPCNModule.load_from_checkpoint(ckpt, map_location="cpu")
    pose = module.match(torch.rand(2, 1, 32, 32), torch.rand(2, 1, 32, 32))
    assert isinstance(pose, Pose) and len(pose) == 2
    matcher = load_matcher(ckpt)
    assert not matcher.training
    with pytest.warns(UserWarning, match="constant template or source"):
        blank = matcher.match(torch.ones(1, 1, 32, 32), torch.ones(1, 1, 32, 32))
    torch.testing.assert_close(blank.as_tensor().isfinite(), torch.ones(1, 4, dtype=torch.bool))
    assert blank.confidence.tolist() == [0.0]  # a pose, finite, flagged as holding nothing


def _crashing_run(run_dir: Path, crash_after_step: int, *extra: str) -> None:
    """Train in this process with the real configs and trainer, crashing after a given step."""
    import lightning as L
    from hydra.utils import instantiate

    from dpcn import cli

    class Crash(L.Callback):
        def on_train_batch_end(self, trainer, *args):
            if trainer.global_step == crash_after_step:
                raise RuntimeError("simulated crash")

    cfg = compose_config(*SMALL, *extra)
    L.seed_everything(cfg.seed, workers=True)
    module = instantiate(cfg.model, _convert_="all")
    datamodule = instantiate(cfg.data)
    trainer = cli._trainer(cfg, run_dir, fit=True)
    trainer.callbacks.append(Crash())
    with pytest.raises(RuntimeError, match="simulated crash"):
        trainer.fit(module, datamodule=datamodule)


def _weights(ckpt: Path) -> dict[str, torch.Tensor]:
    return torch.load(ckpt, weights_only=False)["state_dict"]


def _check_resume(tmp_path: Path, crash_after_step: int, *extra: str) -> None:
    epochs = ["trainer.max_epochs=2", "model.warmup_epochs=0", "model.teacher_forcing=0.5", *extra]
    fit(tmp_path / "straight", *epochs, cwd=tmp_path)
    _crashing_run(tmp_path / "crashed", crash_after_step, *epochs)
    saved = tmp_path / "crashed" / "checkpoints" / "last.ckpt"
    assert torch.load(saved, weights_only=False)["global_step"] == crash_after_step
    fit(tmp_path / "resumed", *epochs, f"ckpt_path={saved}", cwd=tmp_path)
    straight = torch.load(tmp_path / "straight/checkpoints/last.ckpt", weights_only=False)
    resumed = torch.load(tmp_path / "resumed/checkpoints/last.ckpt", weights_only=False)
    assert resumed["global_step"] == 4
    # the weights (with ema_decay, the average) and, with ema_decay, the raw weights too
    for part in ["state_dict", "current_model_state"][: 1 + ("current_model_state" in straight)]:
        for key, value in straight[part].items():
            torch.testing.assert_close(resumed[part][key], value, rtol=1e-5, atol=1e-6, msg=f"{part}: {key}")
    # ... and the interruption mattered: the crashed run's weights are not the final ones
    crashed = _weights(saved)
    assert any(not torch.allclose(crashed[k], v) for k, v in straight["state_dict"].items() if v.is_floating_point())


@pytest.mark.parametrize("crash_after_step", [2, 3], ids=["at-epoch-end", "mid-epoch"])
def test_interrupted_run_resumes_exactly(tmp_path, crash_after_step):
    """A crash leaves last.ckpt with the state at the crash; `fit ckpt_path=` from it
    ends with the very weights of the run that was never interrupted: same data, same
    teacher-forcing draws, same learning-rate schedule."""
    _check_resume(tmp_path, crash_after_step)


def test_interrupted_run_with_weight_averaging_resumes_exactly(tmp_path):
    """With ema_decay the checkpoint holds the average and the raw weights; both resume."""
    _check_resume(tmp_path, 3, "ema_decay=0.5")
    assert "averaging_state" in torch.load(tmp_path / "resumed/checkpoints/last.ckpt", weights_only=False)


def _logged_steps(metrics: Path) -> int:
    """The highest training step with a logged loss in a run's metrics.csv so far (-1: none)."""
    try:
        rows = list(csv.DictReader(metrics.open()))
    except (OSError, csv.Error):  # not written yet, or caught mid-write
        return -1
    return max((int(r["step"]) for r in rows if r.get("train/loss") and (r.get("step") or "").isdigit()), default=-1)


# A stop from outside, as the shell reports it: (signal, its name in the message, exit status).
STOP_SIGNALS = pytest.mark.parametrize(
    ("signum", "name", "status"),
    [(signal.SIGTERM, "SIGTERM", 143), (signal.SIGINT, "Ctrl-C", 130)],
    ids=["term", "int"],
)


def _stopped_midway(tmp_path: Path, args: list[str], signum: int, ready, settle: float = 0.0) -> tuple[int, str]:
    """Run ``python -m dpcn *args`` in its own process group (stdout to ``tmp_path/stdout.txt``),
    send ``signum`` to the whole group (the data workers too) once ``ready()`` holds and
    ``settle`` more seconds have passed, and return its exit status and stderr."""
    env = {k: v for k, v in os.environ.items() if k not in ("DPCN_DEBUG", "DPCN_COMMAND")}
    out, log = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
    with out.open("w") as stdout, log.open("w") as stderr:
        proc = subprocess.Popen(
            [sys.executable, "-m", "dpcn", *args],
            cwd=tmp_path, env=env, stdout=stdout, stderr=stderr, start_new_session=True,
        )  # fmt: skip
        try:
            deadline = time.monotonic() + 120
            while not ready():
                assert proc.poll() is None, log.read_text()[-3000:]
                assert time.monotonic() < deadline, f"dpcn {args[0]} did not get going"
                time.sleep(0.2)
            time.sleep(settle)
            os.killpg(proc.pid, signum)
            proc.wait(timeout=120)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode, log.read_text()


def _child_exits() -> None:
    """Start a child process that exits at once and reap it: one SIGCHLD to this process."""
    subprocess.run([sys.executable, "-c", "pass"], check=True)


class _WorkerKilled(RuntimeError):
    pass


def _raise_like_the_loader(signum, frame):  # what PyTorch's DataLoader SIGCHLD handler does
    raise _WorkerKilled("DataLoader worker (pid 1) is killed by signal: Terminated.")


@pytest.mark.skipif(not hasattr(signal, "SIGCHLD"), reason="SIGCHLD is POSIX")
@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT], ids=["term", "int"])
def test_a_stop_turns_the_loaders_sigchld_handler_off_first(stop):
    """During fit, a SIGTERM or Ctrl-C turns off the SIGCHLD handler that would raise for each
    dead data worker, so a stop to the whole process group cannot abort Lightning's handling
    of it (and the interrupted run's checkpoint) midway."""
    from dpcn.training.checkpointing import stop_quiets_worker_deaths

    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGCHLD)}
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # as in a fresh process: SIGTERM would end it
    try:
        with stop_quiets_worker_deaths():
            signal.signal(signal.SIGCHLD, _raise_like_the_loader)  # the loader installs it inside fit
            with pytest.raises(_WorkerKilled):  # before a stop, a dead child raises
                _child_exits()
                time.sleep(0.1)
            if stop == signal.SIGINT:
                with pytest.raises(KeyboardInterrupt):  # Ctrl-C still interrupts
                    os.kill(os.getpid(), stop)
                    time.sleep(0.1)
            else:
                os.kill(os.getpid(), stop)  # survived: SIGTERM is left to Lightning's handler
                time.sleep(0.1)
            assert signal.getsignal(signal.SIGCHLD) == signal.SIG_DFL
            _child_exits()  # no longer raises
            time.sleep(0.1)
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # the handlers of before
        assert signal.getsignal(signal.SIGINT) == before[signal.SIGINT]
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


@pytest.mark.skipif(not hasattr(signal, "SIGCHLD"), reason="SIGCHLD is POSIX")
def test_a_stop_handler_installed_later_still_turns_sigchld_off_first():
    """Lightning installs its SIGTERM handler when the run starts, in front of the stop guard:
    it logs the signal, then records it. A worker that died meanwhile raised inside it, the
    stop unrecorded, and the stopped run ended as a crash (CI, once). The trainer's callback
    wraps that handler again at each loop's start, so SIGCHLD goes off first."""
    from dpcn.training.checkpointing import StopQuietsWorkersFirst

    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGCHLD)}
    recorded = []

    def logs_then_records(signum, frame):  # Lightning's notifier, with a worker dying as it logs
        _child_exits()
        time.sleep(0.1)
        recorded.append(signum)

    try:
        signal.signal(signal.SIGCHLD, _raise_like_the_loader)
        signal.signal(signal.SIGTERM, logs_then_records)
        with pytest.raises(_WorkerKilled):  # the race, without the callback
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.1)
        assert recorded == []
        callback = StopQuietsWorkersFirst()
        callback.on_train_start(None, None)
        wrapped = signal.getsignal(signal.SIGTERM)
        callback.on_validation_start(None, None)  # each loop's start: wrapped once only
        assert signal.getsignal(signal.SIGTERM) is wrapped is not logs_then_records
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.2)
        assert recorded == [signal.SIGTERM]
        assert signal.getsignal(signal.SIGCHLD) == signal.SIG_DFL
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="process groups are POSIX")
@STOP_SIGNALS
def test_a_run_stopped_with_its_data_workers_keeps_its_place(tmp_path, signum, name, status):
    """A signal to the run's whole process group (a scheduler, `kill -- -PGID`, Ctrl-C in a
    terminal) stops the data workers too. The run still writes last.ckpt at the step it
    reached, mid-epoch, and says in one line how to resume, with the shell's exit status."""
    # 1000 steps per epoch, no periodic checkpoint: a last.ckpt can only be the interrupt's.
    args = ["fit", *SMALL, "data.num_workers=2", "data.epoch_size=4000", f"hydra.run.dir={tmp_path / 'run'}"]
    # Stopped once an optimiser step has been taken.
    returncode, err = _stopped_midway(
        tmp_path, args, signum, lambda: _logged_steps(tmp_path / "run" / "metrics.csv") >= 2
    )
    assert returncode == status, err[-3000:]
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    message = err.strip().splitlines()[-1]
    assert message.startswith(f"dpcn fit: stopped by {name}; {last} holds the run after "), message
    assert message.endswith(f"ckpt_path={last} resumes it")
    assert "Traceback" not in err
    step = torch.load(last, weights_only=False)["global_step"]
    assert 2 <= step < 1000  # the interrupted epoch's place, not an epoch end
    assert f"after {step} training steps" in message
    assert load_matcher(last) is not None


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="process groups are POSIX")
@STOP_SIGNALS
def test_an_evaluation_stopped_by_a_signal_says_so_in_one_line(tmp_path, signum, name, status):
    """`test` stopped with its data workers (a signal to the process group) ends with one line
    saying how far it got and that no metrics were written, the shell's exit status, and no
    traceback or partial metrics file."""
    args = [
        "test",
        "model=classical",
        "data.num_workers=2",
        "data.test_length=40000",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]

    def testing() -> bool:  # the progress bar counts the 5000 test batches
        text = (tmp_path / "stdout.txt").read_text()
        return "Testing DataLoader 0:" in text and "/5000 [" in text

    returncode, err = _stopped_midway(tmp_path, args, signum, testing, settle=1.0)
    assert returncode == status, err[-3000:]
    message = err.strip().splitlines()[-1]
    assert re.fullmatch(
        rf"dpcn test: stopped by {name} after \d+ batches; "
        r"no metrics written \(they need every pair\): run the command again",
        message,
    ), message
    assert "Traceback" not in err
    assert not (tmp_path / "run" / "metrics_test.csv").exists()


@pytest.mark.skipif(not hasattr(signal, "SIGCHLD"), reason="SIGCHLD is POSIX")
def test_a_sigchld_that_came_as_its_handler_was_turned_off_is_not_printed():
    """Under load a worker's SIGCHLD can trip just before a stop turns the loader's handler
    off; CPython then reports "Signal 17 ignored due to race condition" as unraisable (seen in
    a stress run of the test above). That is what the stop intends, so it is dropped; other
    OSErrors are not."""
    from types import SimpleNamespace

    from dpcn.cli import _is_worker_shutdown_noise

    def unraisable(error: BaseException) -> SimpleNamespace:
        return SimpleNamespace(exc_type=type(error), exc_value=error, exc_traceback=None, err_msg=None, object=None)

    race = OSError(f"Signal {int(signal.SIGCHLD)} ignored due to race condition")
    assert _is_worker_shutdown_noise(unraisable(race))
    assert not _is_worker_shutdown_noise(
        unraisable(OSError(f"Signal {int(signal.SIGUSR1)} ignored due to race condition"))
    )
    assert not _is_worker_shutdown_noise(unraisable(OSError("No space left on device")))


_WORKER_DEATH_IN_DEL = """
import sys
from torch.utils.data import DataLoader
from torch.utils.data.dataloader import _MultiProcessingDataLoaderIter
from dpcn.cli import quiet_worker_shutdown

if sys.argv[1] == "quiet":
    quiet_worker_shutdown()
shutdown = _MultiProcessingDataLoaderIter._shutdown_workers

def shutdown_then_report(self):  # what PyTorch's SIGCHLD handler does when a worker died
    shutdown(self)
    raise RuntimeError("DataLoader worker (pid(s) 12345) exited unexpectedly")

_MultiProcessingDataLoaderIter._shutdown_workers = shutdown_then_report
batches = iter(DataLoader(range(4), num_workers=1))
next(batches)
del batches  # the loader's own __del__ raises: Python can only print it

class Other:
    def __del__(self):
        raise ValueError("another unraisable error")

other = Other()
del other
print("finished")
"""


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="the race it guards is a signal to a process group (POSIX)")
def test_a_worker_death_inside_the_loaders_del_is_not_printed(tmp_path):
    """The race that a signal to the process group can hit (the test above, now and then): a
    worker's death reported while the loader shuts its workers down in ``__del__``. ``fit``
    keeps that traceback off stderr; any other unraisable error is still printed."""
    script = tmp_path / "worker_death.py"
    script.write_text(_WORKER_DEATH_IN_DEL)
    runs = {}
    for mode in ("quiet", "plain"):
        done = subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0 and "finished" in done.stdout, done.stderr[-2000:]
        runs[mode] = done.stderr
    assert "DataLoader worker (pid(s) 12345) exited unexpectedly" in runs["plain"]  # what it hides
    assert "DataLoader worker" not in runs["quiet"] and "Traceback" in runs["quiet"]
    assert "ValueError: another unraisable error" in runs["quiet"]


def test_weight_averaging_is_what_validates_and_reloads(tmp_path):
    """ema_decay: validation and the checkpoint's weights are the moving average of the
    steps' weights. With a decay near 0 the average is the last step's weights; with 0.5
    it lags behind them; load_matcher gives the average."""
    for decay in ("1e-12", "0.5"):
        fit(tmp_path / decay, "trainer.max_epochs=2", f"ema_decay={decay}", cwd=tmp_path)
    near_zero = torch.load(tmp_path / "1e-12/checkpoints/last.ckpt", weights_only=False)
    for key, value in near_zero["current_model_state"].items():
        torch.testing.assert_close(near_zero["state_dict"][key], value, msg=key)
    half = torch.load(tmp_path / "0.5/checkpoints/last.ckpt", weights_only=False)
    raw, average = half["current_model_state"], half["state_dict"]
    assert raw.keys() == average.keys()
    assert any(not torch.allclose(average[k], v) for k, v in raw.items())
    matcher = load_matcher(tmp_path / "0.5/checkpoints/last.ckpt")
    for key, value in matcher.state_dict().items():
        torch.testing.assert_close(value, average[key], msg=key)


def test_resume_with_more_epochs_stretches_the_schedule(tmp_path):
    fit(tmp_path / "first", cwd=tmp_path)
    fit(
        tmp_path / "more", "trainer.max_epochs=3", f"ckpt_path={tmp_path / 'first/checkpoints/last.ckpt'}", cwd=tmp_path
    )
    assert torch.load(tmp_path / "more/checkpoints/last.ckpt", weights_only=False)["global_step"] == 6


def test_validate_and_test_print_the_paper_table(trained, tmp_path):
    ckpt = trained / "checkpoints" / "last.ckpt"
    out = dpcn("test", *SMALL, f"ckpt_path={ckpt}", f"hydra.run.dir={tmp_path / 't'}", cwd=tmp_path)
    assert "acc_x@5" in out.stdout and "acc_rot@0.5" in out.stdout
    rows = list(csv.DictReader((tmp_path / "t" / "metrics_test.csv").open()))
    assert rows[0]["n"] == "4.0" and 0.0 <= float(rows[0]["acc_scale@0.2"]) <= 100.0
    # inference settings replace the checkpoint's
    inference = [
        "rotation_hypotheses=3",
        "hypothesis_ratio=0.7",
        "spectrum_window_grid=3",
        "rotation_views=4",
        "unet_dtype=bfloat16",
        "inference_radii=16",
        "inference_sigma=2.5",
        "scale_range=[0.8,1.25]",
        "half_turn_pass=winner",
    ]
    out = dpcn("test", *SMALL, f"ckpt_path={ckpt}", *inference, f"hydra.run.dir={tmp_path / 'k'}", cwd=tmp_path)
    assert "acc_rot@1" in out.stdout and (tmp_path / "k" / "metrics_test.csv").is_file()
    out = dpcn(
        "test", *SMALL, f"ckpt_path={ckpt}", "inference_radii=trained", f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path
    )
    assert "acc_rot@1" in out.stdout
    matcher = load_matcher(
        ckpt,
        rotation_hypotheses=3,
        hypothesis_ratio=0.5,
        spectrum_window_grid=5,
        rotation_views=8,
        unet_dtype="bfloat16",
        inference_radii=24,
        inference_sigma=4.5,
        scale_range=(0.75, 1.5),
        half_turn_pass="winner",
    )
    model = matcher.model
    assert (model.rotation_hypotheses, model.spectrum_window_grid, model.rotation_views) == (3, 5, 8)
    stored = load_matcher(ckpt).model  # tiny's gated second peak
    assert (model.hypothesis_ratio, stored.rotation_hypotheses, stored.hypothesis_ratio) == (0.5, 2, 0.7)
    assert model.unet_dtype == "bfloat16" and load_matcher(ckpt).model.unet_dtype == "float32"
    assert model.inference_radii == 24 and load_matcher(ckpt).model.inference_radii == 128  # tiny's, stored
    assert model.inference_sigma == 4.5 and load_matcher(ckpt).model.inference_sigma == 3.0  # tiny's, stored
    assert model.scale_range == (0.75, 1.5) and load_matcher(ckpt).model.scale_range == (0.5, 2.0)  # tiny's, stored
    assert model.half_turn_pass == "winner" and load_matcher(ckpt).model.half_turn_pass == "every"  # tiny's, stored
    assert load_matcher(ckpt, inference_radii="trained").model.inference_radii is None  # n_radii
    with pytest.raises(ValueError, match="inference_radii must be an integer >= 2 or 'trained', got 'all'"):
        load_matcher(ckpt, inference_radii="all")
    for setting, message in [
        ("rotation_hypotheses=0", "rotation_hypotheses must be an integer >= 1, got 0"),
        ("hypothesis_ratio=1.5", "hypothesis_ratio must be a finite number in [0, 1], got 1.5"),
        ("spectrum_window_grid=2", "spectrum_window_grid must be an odd integer >= 1, got 2"),
        ("rotation_views=9", "rotation_views must be an integer from 1 to 8, got 9"),
        ("unet_dtype=float16", "unet_dtype must be one of float32, bfloat16, got 'float16'"),
        ("inference_radii=1", "inference_radii must be an integer >= 2 or None, got 1"),
        ("inference_radii=all", "inference_radii must be an integer >= 2 or 'trained', got 'all'"),
        ("inference_sigma=-1", "inference_sigma must be a finite number >= 0, got -1"),
        ("rotation_range=[180,0]", "rotation_range must be [low, high] in degrees with 0 < high - low <= 360"),
        ("scale_range=[1.2,2]", "scale_range must be [low, high] with 0 < low <= 1 <= high, got [1.2, 2]"),
        ("half_turn_pass=some", "half_turn_pass must be one of winner, every, got 'some'"),
    ]:
        run = tmp_path / setting.split("=")[0]
        bad = dpcn("test", *SMALL, f"ckpt_path={ckpt}", setting, f"hydra.run.dir={run}", cwd=tmp_path, check=False)
        assert bad.returncode == 2 and message in bad.stderr and "Traceback" not in bad.stderr
    out = dpcn("validate", *SMALL_DATA, "model=classical", f"hydra.run.dir={tmp_path / 'v'}", cwd=tmp_path)
    assert "classical on sim_heterogeneous" in out.stdout
    assert (tmp_path / "v" / "metrics_validate.csv").is_file()
    # Every pair's truth, estimate, confidence and errors, which give the table's numbers.
    with (tmp_path / "v" / "pairs_validate.csv").open() as f:
        pairs = list(csv.DictReader(f))
    with (tmp_path / "v" / "metrics_validate.csv").open() as f:
        table = next(csv.DictReader(f))
    assert [int(p["pair"]) for p in pairs] == list(range(4)) and float(table["n"]) == 4
    checks = [("acc_x@5", "err_x", 5.0), ("acc_rot@1", "err_rot", 1.0), ("acc_scale@0.2", "err_scale", 0.2)]
    for key, column, limit in checks:
        assert float(table[key]) == pytest.approx(100 * sum(float(p[column]) <= limit for p in pairs) / 4)
    assert float(table["mse_y"]) == pytest.approx(sum(float(p["err_y"]) ** 2 for p in pairs) / 4, rel=1e-4)
    first = pairs[0]
    assert float(first["err_x"]) == pytest.approx(abs(float(first["pred_tx"]) - float(first["tx"])), abs=1e-4)
    assert 0 < float(first["confidence"]) <= 1
    # Accuracy against threshold, the paper's appendix plots, from the same pairs.
    with (tmp_path / "v" / "accuracy_validate.csv").open() as f:
        curve = {(row["component"], float(row["threshold"])): float(row["acc"]) for row in csv.DictReader(f)}
    assert len(curve) == 82 and curve[("x", 19.0)] >= curve[("x", 5.0)] >= curve[("x", 0.0)]
    for (name, limit), acc in curve.items():
        column = {"x": "err_x", "y": "err_y", "rot": "err_rot", "scale": "err_scale"}[name]
        assert acc == pytest.approx(100 * sum(float(p[column]) <= limit for p in pairs) / 4, abs=1e-3)
    # Lightning's adverts and its warning about its own code stay out of the output.
    assert "Tip:" not in out.stderr + out.stdout and "LeafSpec" not in out.stderr, out.stderr


def test_fine_tuning_starts_from_the_weights_and_keeps_the_frozen_phase(trained, tmp_path):
    init = trained / "checkpoints" / "last.ckpt"
    fit(tmp_path / "ft", f"init_from={init}", "model.freeze=[rotation_scale]", "data.seeds.train=5", cwd=tmp_path)
    before = torch.load(init, weights_only=False)
    after = torch.load(tmp_path / "ft" / "checkpoints" / "last.ckpt", weights_only=False)
    weights = [k for k in before["state_dict"] if k.startswith("model.") and k.endswith("weight")]
    phase1 = [k for k in weights if k.startswith("model.rs_")]
    phase2 = [k for k in weights if k.startswith("model.t_")]
    # Phase 1 is the trained run's (not this run's own initialisation), unchanged by training;
    # phase 2 started there and moved; the run itself is a fresh one (its first epoch, step 2).
    assert phase1 and all(torch.equal(before["state_dict"][k], after["state_dict"][k]) for k in phase1)
    assert any(not torch.equal(before["state_dict"][k], after["state_dict"][k]) for k in phase2)
    assert after["epoch"] == 0 and after["global_step"] == 2
    assert after["hyper_parameters"]["freeze"] == ["rotation_scale"]
    # Resuming the fine-tuning run restores its own weights, not init_from's.
    fit(tmp_path / "ft", f"init_from={init}", f"ckpt_path={tmp_path / 'ft/checkpoints/last.ckpt'}",
        "model.freeze=[rotation_scale]", "data.seeds.train=5", "trainer.max_epochs=2", cwd=tmp_path)  # fmt: skip
    resumed = torch.load(tmp_path / "ft" / "checkpoints" / "last.ckpt", weights_only=False)
    assert resumed["epoch"] == 1 and resumed["global_step"] == 4
    # Another architecture is refused with what differs.
    out = dpcn("fit", *SMALL, "model.net.feature_channels=2", f"init_from={init}",
               f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path, check=False)  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert f"init_from={init}: its network is not this model's (" in out.stderr
    assert "rs_template.head.weight is (4, 2, 1, 1) there, (2, 2, 1, 1) here" in out.stderr
    assert "Settings that differ: model.net.feature_channels 4 there, 2 here" in out.stderr
    # So is resuming a run with another architecture (was Lightning's load_state_dict traceback).
    last = tmp_path / "ft" / "checkpoints" / "last.ckpt"
    out = dpcn("fit", *SMALL, "model.net.feature_channels=2", f"ckpt_path={last}", "trainer.max_epochs=3",
               f"hydra.run.dir={tmp_path / 'bad2'}", cwd=tmp_path, check=False)  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr and "HYDRA_FULL_ERROR" not in out.stderr
    assert f"ckpt_path={last}: its network is not this model's (" in out.stderr
    assert "model.net.feature_channels 4 there, 2 here. A run resumes with the settings it started with" in out.stderr


def test_predict_with_a_checkpoint(trained, tmp_path):
    import cv2
    import numpy as np

    ckpt = f"ckpt_path={trained / 'checkpoints/last.ckpt'}"
    rng = np.random.default_rng(0)
    for folder in ("template", "source"):
        (tmp_path / folder).mkdir()
    for name in ("p0", "p1", "p2"):
        for folder in ("template", "source"):
            cv2.imwrite(str(tmp_path / folder / f"{name}.png"), (rng.random((32, 32)) * 255).astype(np.uint8))
    out = dpcn("predict", "template=template/p1.png", "source=source/p1.png", ckpt, cwd=tmp_path)
    single = json.loads(out.stdout)
    assert set(single) == {"tx", "ty", "angle", "scale", "confidence"}
    # The whole CSV in batches of two: the same pose for p1 as alone.
    (tmp_path / "pairs.csv").write_text("name\np0\np1\np2\n")
    out = dpcn("predict", "pairs=pairs.csv", "predict_batch_size=2", ckpt, cwd=tmp_path)
    rows = list(csv.DictReader(io.StringIO(out.stdout)))
    assert [r["name"] for r in rows] == ["p0", "p1", "p2"]
    for key, value in single.items():
        assert float(rows[1][key]) == pytest.approx(value, rel=1e-4, abs=1e-4), key
    # Colour files of the same pair on this grey model are converted to grey, as the data
    # sets convert them (they failed with "this model takes 1-channel images, got 3 channels")
    for folder in ("template", "source"):
        grey = cv2.imread(str(tmp_path / folder / "p1.png"), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(tmp_path / folder / "c1.png"), np.repeat(grey[..., None], 3, axis=2))
    out = dpcn("predict", "template=template/c1.png", "source=source/c1.png", ckpt, cwd=tmp_path)
    assert json.loads(out.stdout) == pytest.approx(single, rel=1e-4, abs=1e-4)
    # A pair of another size than the model's is named, and nothing is written.
    for folder in ("template", "source"):
        cv2.imwrite(str(tmp_path / folder / "big.png"), (rng.random((48, 48)) * 255).astype(np.uint8))
    (tmp_path / "pairs.csv").write_text("name\np0\nbig\np2\n")
    out = dpcn("predict", "pairs=pairs.csv", "out=poses.csv", ckpt, cwd=tmp_path, check=False)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "pair 'big': this model was built for 32x32 images, got 48x48" in out.stderr
    assert not (tmp_path / "poses.csv").exists()


@pytest.mark.parametrize(
    "args,message",
    [
        (["test", "ckpt_path=missing.ckpt"], "checkpoint not found: missing.ckpt"),
        (["test", "ckpt_path=corrupt.ckpt"], "corrupt or not a torch file"),
        (["test", "ckpt_path=."], ". is a folder, not a checkpoint file; it holds corrupt.ckpt, foreign.ckpt"),
        (["fit", "init_from=run"], "init_from: run is a folder, not a checkpoint file; it holds run/checkpoints/last"),
        (["test", "ckpt_path=run/checkpoints/empty"], "it holds no .ckpt file (nor does a checkpoints/ folder in it)"),
        (["test", "ckpt_path=foreign.ckpt"], "not a Lightning checkpoint of a dpcn model"),
        (["test"], "needs ckpt_path=PATH"),
        (["fit", "model=classical"], "nothing to train"),
        (["fit", "model=classical", "model.net.depth=2"], "Could not override 'model.net.depth'"),
        (["fit", "data.batch_size=0"], "batch_size"),
        (["fit", "model.net.norm=layer"], "unknown norm 'layer'"),
        (["fit", "model.lr=abc"], "model.lr must be a finite number > 0, got 'abc'"),
        (["fit", "model.net.sigma=abc"], "model.net.sigma must be a finite number >= 0, got 'abc'"),
        (["fit", "trainer.max_epochs=abc"], "trainer.max_epochs must be an integer >= -1, got 'abc'"),
        (["fit", "+data.dataset.bogus=1"], "data.dataset: SimulatedPairs.__init__() got an unexpected keyword"),
        (["fit", "+data.split_kwargs={train:{obstacles:-1}}"], "data.split_kwargs.train: obstacles must be an integer"),
        (["fit", "+data.split_kwargs={trian:{obstacles:6}}"], "data.split_kwargs has unknown split(s) 'trian'; the"),
        (["fit", "+data.split_kwargs={train:6}"], "data.split_kwargs.train must be a mapping of data set"),
        (["fit", "+data.seeds.tset=3"], "data.seeds has unknown split(s) 'tset'; the splits are train, val, test"),
        (["fit", "data.seeds.test=abc"], "data.seeds.test must be an integer >= 0, got 'abc'"),
        (["fit", "data.seeds=5"], "data.seeds must map splits (train, val, test) to values, got 5"),
        (["fit", "ema_decay=1"], "ema_decay must be a number in (0, 1) or null, got 1"),
        (["fit", "ema_decay=abc"], "ema_decay must be a number in (0, 1) or null, got 'abc'"),
        (["fit", "init_from=missing.ckpt"], "init_from: checkpoint not found: missing.ckpt"),
        (["fit", "init_from=corrupt.ckpt"], "corrupt or not a torch file"),
        (["fit", "init_from=foreign.ckpt"], "not a Lightning checkpoint of a dpcn model"),
        (["fit", "model.freeze=[rotation]"], "model.freeze takes a list of rotation_scale, translation"),
        (["fit", "model.net.rotation_scale_correlation=1d"], "rotation_scale_correlation must be one of joint"),
        (["fit", "model.net.rotation_range=[0,400]"], "rotation_range must be [low, high] in degrees with 0 < high"),
        (["test", "model=classical", "registration.rotation_range=[90]"], "rotation_range must be [low, high] in"),
        (["test", "model=classical", "spectrum_window_grid=3"], "set registration.spectrum_window_grid= instead"),
        (["test", "-m", "model=classical", "inference_radii=64"], "inference_radii= applies to a checkpoint"),
        (["fit", "trainer.precision=bf32"], "trainer.precision must be auto or one of Lightning's 32-true, bf16-mixed"),
        (["fit", "seed=abc"], "seed must be an integer >= 0, got 'abc'"),
        (["test", "model=classical", "seed=4294967296"], "seed must be an integer < 2**32, got 4294967296"),
        (["fit", "model.net.highpass=maybe"], "model.net.highpass must be true or false, got 'maybe'"),
        (["test", "model=classical", "registration.resolve_180=1"], "resolve_180 must be true or false, got 1"),
        (["test", "model=classical", "registration.refine=abc"], "refine must be an integer >= 0, got 'abc'"),
        (["make-data", "out=scenes", "n_scenes=abc"], "n_scenes must be an integer >= 1, got 'abc'"),
        (["make-data", "out=corrupt.ckpt"], "out=corrupt.ckpt is a file, not a folder"),  # not NotADirectoryError
        (["make-data", "out=corrupt.ckpt/maps"], "cannot create out=corrupt.ckpt/maps: Not a directory"),
        (["fit", "trainer=gpu"], "trainer.accelerator=gpu: this machine has no GPU that torch can use"),
    ],
)
def test_bad_runs_fail_in_one_line(tmp_path, args, message):
    if "trainer=gpu" in args and (torch.cuda.is_available() or torch.backends.mps.is_available()):
        pytest.skip("this machine has a GPU to train on")
    (tmp_path / "corrupt.ckpt").write_bytes(b"\x00\x01 not a checkpoint")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.ckpt")
    (tmp_path / "run" / "checkpoints" / "empty").mkdir(parents=True)  # a run's folder given for its checkpoint
    (tmp_path / "run" / "checkpoints" / "last.ckpt").write_bytes(b"\x00")
    small = SMALL_DATA if "model=classical" in args else SMALL
    out = dpcn(*args[:1], *small, *args[1:], f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path, check=False)
    assert out.returncode == 2, out.stderr[-2000:]
    lines = [line for line in out.stderr.splitlines() if line.startswith("dpcn ")]
    assert len(lines) == 1 and message in lines[0], out.stderr[-2000:]
    assert "Traceback" not in out.stderr


def test_evaluating_a_checkpoint_on_pairs_of_another_size_names_the_setting(trained, tmp_path):
    ckpt = trained / "checkpoints" / "last.ckpt"
    out = dpcn("test", f"ckpt_path={ckpt}", "data.test_length=4", "data.num_workers=0",
               f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path, check=False)  # fmt: skip
    # the data config's own 256 x 256 pairs: the model's "resize or crop" did not say what to set
    message = (
        f"{ckpt}: this model was built for 32x32 images, got 256x256 "
        "(data=sim_heterogeneous cuts its pairs at image_size=256): add image_size=32"
    )
    assert out.returncode == 2 and message in out.stderr and "Traceback" not in out.stderr


def test_lightning_lines_are_printed_once_and_kept_in_the_run_log(tmp_path):
    out = dpcn("fit", *SMALL, "trainer.enable_model_summary=true", f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path)
    printed = out.stdout + out.stderr
    # Lightning's own stderr handler printed each of its lines a second time, the summary table too
    assert printed.count("Seed set to 42") == 1 and printed.count("Total params") == 1, printed[-3000:]
    log = (tmp_path / "r" / "fit.log").read_text()
    assert "Seed set to 42" in log and "Total params" in log


def test_a_fit_of_no_steps_names_no_checkpoint(tmp_path):
    out = dpcn("fit", *SMALL, "+trainer.limit_train_batches=0", f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path)
    assert "(best: -, last: -)" in out.stdout  # it named a last.ckpt that was never written
    assert not (tmp_path / "r" / "checkpoints" / "last.ckpt").exists()


def test_runs_started_together_get_their_own_run_directories(tmp_path):
    """Two runs launched at once (one per GPU from a shell loop) in the default run directory,
    outputs/<command>/<time>: with a time to the second they shared one folder and overwrote
    each other's files."""
    env = {k: v for k, v in os.environ.items() if k not in ("DPCN_DEBUG", "DPCN_COMMAND")}
    command = [sys.executable, "-m", "dpcn", "test", "model=classical", *SMALL_DATA]
    runs = [
        subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in "ab"
    ]
    for run in runs:
        _, err = run.communicate(timeout=300)
        assert run.returncode == 0, err.decode()[-2000:]
    folders = sorted((tmp_path / "outputs" / "test").iterdir())
    assert len(folders) == 2 and all((f / "metrics_test.csv").is_file() for f in folders)
    assert all(re.fullmatch(r"\d{4}-\d{2}-\d{2}_\d{2}-\d{2}-\d{2}_\d{6}", f.name) for f in folders), folders


def test_the_classical_estimator_on_an_experiments_pairs(tmp_path):
    """experiment=paper_table1 merges DPCN settings into `model` (model.net...) and sets a
    checkpoint's rotation_views; the classical estimator leaves them out, in one log line,
    and tests on the experiment's pairs."""
    run = tmp_path / "c"
    out = dpcn("test", "model=classical", "experiment=paper_table1", *SMALL_DATA, f"hydra.run.dir={run}", cwd=tmp_path)
    assert "model=classical leaves out model.net: DPCN settings" in out.stdout + out.stderr
    assert "classical on sim_dynamic" in out.stdout
    composed = OmegaConf.load(run / ".hydra" / "config.yaml")
    assert composed.data.dataset.appearance_change == 0.3 and composed.rotation_views == 4
    assert (run / "metrics_test.csv").is_file()


def test_checkpoint_for_another_image_size(trained, tmp_path):
    ckpt = trained / "checkpoints" / "last.ckpt"
    args = [a for a in SMALL if not a.startswith("image_size")]
    out = dpcn(
        "test", *args, "image_size=48", f"ckpt_path={ckpt}", f"hydra.run.dir={tmp_path}", cwd=tmp_path, check=False
    )
    assert out.returncode == 2 and "built for 32x32 images, got 48x48" in out.stderr


def test_unknown_config_group_or_key(tmp_path):
    out = dpcn("fit", "data=nope", cwd=tmp_path, check=False)
    assert out.returncode != 0 and "nope" in out.stderr and "Traceback" not in out.stderr
    out = dpcn("fit", "model.tempreature=1", cwd=tmp_path, check=False)
    assert out.returncode != 0 and "tempreature" in out.stderr and "Traceback" not in out.stderr


def test_multirun_sweep(tmp_path):
    dpcn("fit", *SMALL, "-m", "model.temperature=0.01,0.05", "loss=l1,kl", f"hydra.sweep.dir={tmp_path}", cwd=tmp_path)
    runs = sorted(p for p in tmp_path.iterdir() if p.is_dir() and (p / "checkpoints" / "last.ckpt").is_file())
    assert len(runs) == 4
    temperatures = set()
    for run in runs:
        hp = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["hyper_parameters"]
        temperatures.add(hp["temperature"])
    assert temperatures == {0.01, 0.05}


def test_ddp_with_two_cpu_processes(tmp_path):
    fit(tmp_path / "ddp", "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2", cwd=tmp_path)
    ckpt = torch.load(tmp_path / "ddp/checkpoints/last.ckpt", weights_only=False)
    # 8 pairs per epoch, batch 4, split over 2 ranks: one optimiser step per rank
    assert ckpt["global_step"] == 1


def test_an_evaluation_split_over_ranks_counts_every_pair_once(tmp_path):
    """9 test pairs over 2 DDP ranks (5 and 4): the same per-pair table, in data-set order,
    and the same metrics as one process; no pair counted twice or read from padding."""
    args = [*SMALL_DATA, "model=classical", "data.test_length=9"]
    # One thread in both runs: float32 reductions split over threads round differently (Lightning
    # gives each CPU rank its share of the cores), and this compares the split, not the threads.
    one_thread = {"OMP_NUM_THREADS": "1"}
    dpcn("test", *args, f"hydra.run.dir={tmp_path / 'one'}", cwd=tmp_path, env=one_thread)
    ddp = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"]
    dpcn("test", *args, *ddp, f"hydra.run.dir={tmp_path / 'two'}", cwd=tmp_path, env=one_thread)
    one, two = (tmp_path / run / "pairs_test.csv" for run in ("one", "two"))
    assert len(one.read_text().splitlines()) == 10  # the header and 9 pairs
    assert two.read_text() == one.read_text()
    metrics = [(tmp_path / run / "metrics_test.csv").read_text() for run in ("one", "two")]
    assert metrics[0] == metrics[1]


@pytest.mark.parametrize(
    ("preset", "downsample", "inputs", "width", "depth"), [("tiny", 2, 1, 8, 4), ("tiny_full", 1, 1, 4, 3)]
)
def test_model_presets_compose_and_build(preset, downsample, inputs, width, depth):
    from hydra.utils import instantiate

    cfg = compose_config(f"model={preset}")
    module = instantiate(cfg.model, _convert_="all")
    net = module.model
    assert net.rotation_scale_downsample == downsample
    assert net.rs_template.stem[0].in_channels == inputs  # box-averaged input (rotation_scale_pooling)
    assert net.rs_template.stem[0].out_channels == width and net.rs_template.depth == depth
    assert net.t_template.stem[0].out_channels == 4 and net.t_template.depth == 3
    assert net.image_size == (256, 256)


def test_phase1_pooling_is_a_config_override():
    from hydra.utils import instantiate

    cfg = compose_config("model.net.rotation_scale_pooling=space_to_depth")
    net = instantiate(cfg.model, _convert_="all").model
    assert net.rotation_scale_pooling == "space_to_depth"
    assert net.rs_template.stem[0].in_channels == 4 and net.t_template.stem[0].in_channels == 1


@pytest.mark.parametrize(
    ("overrides", "model"),
    [
        (["data=l2sat"], "tiny_full"),
        (["data=s2d"], "tiny_full_s2d"),  # tiny_full, phase 2 on half of each batch
        (["data=sim_heterogeneous"], "tiny"),
        (["data=l2d", "model=tiny"], "tiny"),  # the command line wins, in either order
        (["model=tiny", "data=l2d"], "tiny"),
        (["data=s2sat", "model=classical"], "classical"),
    ],
)
def test_map_pairs_default_to_tiny_full_unless_a_model_is_named(overrides, model):
    cfg = compose_config(*overrides, return_hydra_config=True)
    assert cfg.hydra.runtime.choices.model == model
    data = next(o for o in overrides if o.startswith("data=")).removeprefix("data=")
    assert cfg.data.name == data
