"""Learned models: the U-Net feature extractor and DPCN."""

from .dpcn import DPCN, DPCNOutput, TemplateFeatures, half_turn
from .unet import UNet

__all__ = ["DPCN", "DPCNOutput", "TemplateFeatures", "UNet", "half_turn"]
