"""Training: losses, the Lightning modules, checkpoint writing, the precision to train in."""

from .checkpointing import AtomicCheckpointIO
from .losses import DPCNLoss
from .module import CheckpointError, ClassicalModule, DPCNModule, load_matcher, load_weights
from .precision import auto_precision

__all__ = [
    "AtomicCheckpointIO",
    "CheckpointError",
    "ClassicalModule",
    "DPCNLoss",
    "DPCNModule",
    "auto_precision",
    "load_matcher",
    "load_weights",
]
