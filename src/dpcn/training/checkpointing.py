"""Checkpoint writing that never leaves a half-written file behind, and that data workers dying
with a stopped run cannot abort."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import Callback
from lightning.pytorch.plugins.io import TorchCheckpointIO

__all__ = ["AtomicCheckpointIO", "StopQuietsWorkersFirst", "stop_quiets_worker_deaths"]


def _sigchld_settable() -> bool:
    """Whether this thread may change SIGCHLD's handler (POSIX, main thread)."""
    return hasattr(signal, "SIGCHLD") and threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def _sigchld_ignored() -> Iterator[None]:
    """Ignore SIGCHLD for the duration, if a Python handler is set (main thread, POSIX).

    PyTorch's DataLoader installs a SIGCHLD handler that raises in the main process when a
    worker dies. A SIGTERM sent to a run's whole process group (a job scheduler,
    ``kill -- -PGID``, ``timeout``) stops the workers too, and their SIGCHLD would then abort the
    very checkpoint that saves the interrupted run. A worker lost during an ordinary save is
    still noticed afterwards, by the loader's own liveness checks.
    """
    if not _sigchld_settable() or not callable(signal.getsignal(signal.SIGCHLD)):  # no Python handler: nothing raises
        yield
        return
    previous = signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    try:
        yield
    finally:
        signal.signal(signal.SIGCHLD, previous)


_STOPS = (signal.SIGTERM, signal.SIGINT)


def _sigchld_off_then(handler: object) -> Callable[[int, object], None]:
    """A stop handler that turns PyTorch's SIGCHLD handler off, then runs ``handler`` if it is
    Python's (e.g. KeyboardInterrupt for Ctrl-C; a SIGTERM is Lightning's to handle)."""

    def on_stop(signum: int, frame: object) -> None:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        if callable(handler):
            handler(signum, frame)

    on_stop._dpcn_sigchld_off = True  # type: ignore[attr-defined]
    return on_stop


@contextlib.contextmanager
def stop_quiets_worker_deaths() -> Iterator[None]:
    """For the duration: a SIGTERM or Ctrl-C reaching this process first turns PyTorch's SIGCHLD
    handler off, then goes on as before (Lightning's SIGTERM handling, KeyboardInterrupt).

    A signal to the whole process group kills the data workers with the run, and each death
    makes that handler raise "DataLoader worker ... is killed" wherever the main thread is,
    also inside Lightning's handling of the stop, before it has written the interrupted run's
    last.ckpt (a SIGTERM once left no checkpoint in CI that way). Python runs pending signal
    handlers in signal-number order, so SIGINT (2) and SIGTERM (15) come before the workers'
    SIGCHLD (17). The stop still ends the run: Lightning raises at the next step for SIGTERM,
    and the loader notices dead workers by itself. Main thread, POSIX; a no-op elsewhere.
    """
    if not _sigchld_settable():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in _STOPS}
    for signum, handler in previous.items():
        signal.signal(signum, _sigchld_off_then(handler))
    try:
        yield
    finally:  # SIGCHLD stays as it is: the loader's handler, or off after a stop that ends the run
        for signum, handler in previous.items():
            if handler is not None:  # None: set from outside Python, cannot be restored from here
                signal.signal(signum, handler)


def _put_sigchld_off_first() -> None:
    """Wrap the SIGTERM and SIGINT handlers now set (callable ones) so that each first turns
    PyTorch's SIGCHLD handler off, then runs as before; already wrapped ones stay as they are."""
    if not _sigchld_settable():
        return
    for signum in _STOPS:
        handler = signal.getsignal(signum)
        if callable(handler) and not getattr(handler, "_dpcn_sigchld_off", False):
            signal.signal(signum, _sigchld_off_then(handler))  # SIG_DFL / SIG_IGN act in C: left so


class StopQuietsWorkersFirst(Callback):
    """Keeps :func:`stop_quiets_worker_deaths`'s switch-off of SIGCHLD the first thing a stop does.

    Lightning installs its own SIGTERM handler when a run starts (after ``on_fit_start``), in
    front of the handlers already set: it logs the signal, then records it
    (``trainer.received_sigterm``). A data worker's SIGCHLD during that log raised "DataLoader
    worker ... is killed" with the stop not yet recorded, and a stopped run ended as a crash
    (once in CI). At the start of each loop, after Lightning's handlers are in, this wraps them
    so that SIGCHLD goes off first. Main thread, POSIX; a no-op elsewhere."""

    def on_sanity_check_start(self, trainer: Any, pl_module: Any) -> None:
        _put_sigchld_off_first()

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        _put_sigchld_off_first()

    def on_validation_start(self, trainer: Any, pl_module: Any) -> None:
        _put_sigchld_off_first()

    def on_test_start(self, trainer: Any, pl_module: Any) -> None:
        _put_sigchld_off_first()

    def on_predict_start(self, trainer: Any, pl_module: Any) -> None:
        _put_sigchld_off_first()


class AtomicCheckpointIO(TorchCheckpointIO):
    """Writes each checkpoint to a temporary file in the same folder, then renames it into
    place (atomic on POSIX and Windows): a crash mid-write leaves the previous file intact, and
    data workers dying meanwhile (stopped with the run) cannot interrupt the write."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: str | Path, storage_options: Any = None) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        try:
            with _sigchld_ignored():
                super().save_checkpoint(checkpoint, tmp, storage_options)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
