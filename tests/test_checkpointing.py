"""Checkpoint files: written atomically, and not aborted by the run's data workers dying."""

from __future__ import annotations

import os
import signal

import pytest
import torch

from dpcn.training.checkpointing import AtomicCheckpointIO

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGCHLD"), reason="SIGCHLD is POSIX")


class _WorkerDiesWhilePickled:
    """Sends this process a SIGCHLD while the checkpoint is being pickled, as a data worker
    stopped with the run (a SIGTERM to its process group) does."""

    def __reduce__(self):
        os.kill(os.getpid(), signal.SIGCHLD)
        return (int, (0,))


def _raise_like_torch(signum, frame):  # what PyTorch's DataLoader handler does for a dead worker
    raise RuntimeError("DataLoader worker (pid 1) is killed by signal: Terminated.")


def test_a_dying_worker_cannot_abort_a_checkpoint_write(tmp_path):
    previous = signal.signal(signal.SIGCHLD, _raise_like_torch)
    try:
        # The hazard: a plain save is aborted by the handler.
        with pytest.raises(RuntimeError, match="is killed by signal"):
            torch.save({"state": _WorkerDiesWhilePickled()}, tmp_path / "plain.pt")
        AtomicCheckpointIO().save_checkpoint(
            {"state": _WorkerDiesWhilePickled(), "global_step": 3}, tmp_path / "last.ckpt"
        )
        assert signal.getsignal(signal.SIGCHLD) is _raise_like_torch  # the handler is back afterwards
    finally:
        signal.signal(signal.SIGCHLD, previous)
    assert torch.load(tmp_path / "last.ckpt", weights_only=False)["global_step"] == 3
    assert not list(tmp_path.glob(".last.ckpt.tmp-*"))


def test_a_failed_write_keeps_the_previous_file(tmp_path):
    io = AtomicCheckpointIO()
    io.save_checkpoint({"global_step": 1}, tmp_path / "last.ckpt")

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        io.save_checkpoint({"global_step": 2, "x": Unpicklable()}, tmp_path / "last.ckpt")
    assert torch.load(tmp_path / "last.ckpt", weights_only=False)["global_step"] == 1
    assert not list(tmp_path.glob(".last.ckpt.tmp-*"))


def test_the_signal_disposition_is_left_as_found(tmp_path):
    previous = signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    try:
        AtomicCheckpointIO().save_checkpoint({"global_step": 1}, tmp_path / "last.ckpt")
        assert signal.getsignal(signal.SIGCHLD) == signal.SIG_DFL
    finally:
        signal.signal(signal.SIGCHLD, previous)
