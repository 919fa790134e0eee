"""Learned models: the U-Net feature extractor and DPCN."""

from .dpcn import DPCN, DPCNOutput, half_turn
from .unet import UNet

__all__ = ["DPCN", "DPCNOutput", "UNet", "half_turn"]
