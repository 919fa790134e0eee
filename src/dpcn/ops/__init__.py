"""Differentiable building blocks of phase correlation (torch + kornia, batched)."""

from .correlation import PhaseCorrelation, phase_correlation
from .logpolar import LogPolar, log_polar, log_polar_grid, log_radius_step
from .soft_argmax import SoftArgmax2d, local_maxima2d, soft_argmax2d, spatial_softmax2d
from .spectrum import MagnitudeSpectrum, apodization_window, highpass_filter, magnitude_spectrum

__all__ = [
    "LogPolar",
    "MagnitudeSpectrum",
    "PhaseCorrelation",
    "SoftArgmax2d",
    "apodization_window",
    "highpass_filter",
    "local_maxima2d",
    "log_polar",
    "log_polar_grid",
    "log_radius_step",
    "magnitude_spectrum",
    "phase_correlation",
    "soft_argmax2d",
    "spatial_softmax2d",
]
