"""Fourier magnitude spectrum, apodization window and the Reddy high-pass filter.

The magnitude of the Fourier transform is invariant to translation and rotates/scales
with the image (Reddy & Chatterji 1996), which is what decouples rotation and scale from
translation in Fourier-Mellin registration.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .._validate import check_ints
from ._checks import check_image, full_precision

__all__ = [
    "apodization_window",
    "highpass_filter",
    "magnitude_spectrum",
    "MagnitudeSpectrum",
]


def apodization_window(
    height: int, width: int, device: torch.device | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Separable periodic Hann window of shape ``(H, W)``: 0 on the first row/column, largest
    at index ``(H // 2, W // 2)`` (exactly 1 for even sizes), and symmetric under ``p -> -p`` about that centre, so a
    half-turn about the pose centre ``(W / 2, H / 2)`` leaves it unchanged.

    Multiplying an image by it before the DFT suppresses the spectral cross that the
    image borders would otherwise create (a cross does not rotate with the content).
    """
    check_ints("apodization_window ", ("height", height, 1), ("width", width, 1))
    wy = (
        torch.hann_window(height, periodic=True, device=device, dtype=dtype)
        if height > 1
        else torch.ones(1, device=device, dtype=dtype)
    )
    wx = (
        torch.hann_window(width, periodic=True, device=device, dtype=dtype)
        if width > 1
        else torch.ones(1, device=device, dtype=dtype)
    )
    return wy[:, None] * wx[None, :]


def highpass_filter(
    height: int,
    width: int,
    device: torch.device | None = None,
    dtype: torch.dtype = torch.float32,
    half: bool = False,
) -> Tensor:
    """The Reddy & Chatterji high-pass filter for an fftshifted ``(H, W)`` spectrum.

    ``H(u, v) = (1 - X) (2 - X)`` with ``X = cos(pi u) cos(pi v)`` and ``u, v`` the
    frequencies in cycles per pixel (``[-0.5, 0.5]``). Zero at DC, 2 at Nyquist; it
    de-emphasises the low frequencies that dominate every natural image. ``half=True`` gives
    the ``(H, W // 2 + 1)`` filter for a half spectrum (see :func:`magnitude_spectrum`).
    """
    check_ints("highpass_filter ", ("height", height, 1), ("width", width, 1))
    fy = torch.fft.fftshift(torch.fft.fftfreq(height, device=device, dtype=dtype))
    if half:
        fx = torch.fft.rfftfreq(width, device=device, dtype=dtype)
    else:
        fx = torch.fft.fftshift(torch.fft.fftfreq(width, device=device, dtype=dtype))
    x = torch.cos(torch.pi * fy)[:, None] * torch.cos(torch.pi * fx)[None, :]
    return (1.0 - x) * (2.0 - x)


@full_precision
def magnitude_spectrum(
    image: Tensor, window: bool = True, highpass: bool = False, log: bool = False, half: bool = False
) -> Tensor:
    """Centred (fftshifted) magnitude of the 2-D DFT of each channel.

    Args:
        image: ``(B, C, H, W)`` real images.
        window: multiply by :func:`apodization_window` first (after removing the mean).
        highpass: multiply the magnitude by :func:`highpass_filter`.
        log: return ``log1p`` of the magnitude (for display).
        half: return only the non-negative horizontal frequencies, ``(B, C, H, W // 2 + 1)``
            with DC at ``(H // 2, 0)`` (the rfft2 layout, rows shifted). The magnitude of a
            real image is point-symmetric, so this half holds everything, at half the cost.

    Returns:
        ``(B, C, H, W)`` magnitudes, DC at index ``(H // 2, W // 2)``. Frequency index
        ``(i, j)`` is ``((i - H // 2) / H, (j - W // 2) / W)`` cycles per pixel.
    """
    check_image(image)
    _, _, height, width = image.shape
    x = image - image.mean(dim=(-2, -1), keepdim=True)
    if window:
        x = x * apodization_window(height, width, image.device, image.dtype)
    if half:
        magnitude = torch.fft.fftshift(torch.fft.rfft2(x, norm="ortho").abs(), dim=-2)
    else:
        magnitude = torch.fft.fftshift(torch.fft.fft2(x, norm="ortho").abs(), dim=(-2, -1))
    # (|z| has a zero sub-gradient at z = 0 in torch: no NaN for all-zero inputs.)
    if highpass:
        magnitude = magnitude * highpass_filter(height, width, image.device, image.dtype, half)
    return torch.log1p(magnitude) if log else magnitude


class MagnitudeSpectrum(nn.Module):
    """Module form of :func:`magnitude_spectrum`. ``(B, C, H, W) -> (B, C, H, W)``."""

    def __init__(self, window: bool = True, highpass: bool = True) -> None:
        super().__init__()
        self.window = window
        self.highpass = highpass

    def forward(self, image: Tensor) -> Tensor:
        return magnitude_spectrum(image, window=self.window, highpass=self.highpass)

    def extra_repr(self) -> str:
        return f"window={self.window}, highpass={self.highpass}"
