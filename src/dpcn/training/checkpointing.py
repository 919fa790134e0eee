"""Checkpoint writing that never leaves a half-written file behind."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from lightning.pytorch.plugins.io import TorchCheckpointIO

__all__ = ["AtomicCheckpointIO"]


@contextlib.contextmanager
def _sigchld_ignored() -> Iterator[None]:
    """Ignore SIGCHLD for the duration, if a Python handler is set (main thread, POSIX).

    PyTorch's DataLoader installs a SIGCHLD handler that raises in the main process when a
    worker dies. A SIGTERM sent to a run's whole process group (a job scheduler,
    ``kill -- -PGID``, ``timeout``) stops the workers too, and their SIGCHLD would then abort the
    very checkpoint that saves the interrupted run. A worker lost during an ordinary save is
    still noticed afterwards, by the loader's own liveness checks.
    """
    if (
        not hasattr(signal, "SIGCHLD")
        or threading.current_thread() is not threading.main_thread()
        or not callable(signal.getsignal(signal.SIGCHLD))  # no Python handler: nothing can raise
    ):
        yield
        return
    previous = signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    try:
        yield
    finally:
        signal.signal(signal.SIGCHLD, previous)


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
