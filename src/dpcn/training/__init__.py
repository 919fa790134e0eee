"""Training: losses, the Lightning modules, checkpoint writing."""

from .checkpointing import AtomicCheckpointIO
from .losses import DPCNLoss
from .module import CheckpointError, ClassicalModule, DPCNModule, load_matcher, load_weights

__all__ = [
    "AtomicCheckpointIO",
    "CheckpointError",
    "ClassicalModule",
    "DPCNLoss",
    "DPCNModule",
    "load_matcher",
    "load_weights",
]
