"""Phase correlation: the normalised cross-power spectrum and its correlation surface."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from ._checks import check_pair, copies_of_one, full_precision

__all__ = [
    "cross_power_spectrum",
    "correlation_surface",
    "phase_correlation",
    "phase_correlation_1d",
    "PhaseCorrelation",
]


def _gaussian_transfer(height: int, width: int, sigma: float, device: torch.device, dtype: torch.dtype) -> Tensor:
    """rfft2-layout ``(H, W // 2 + 1)`` transfer function of a Gaussian blur of ``sigma`` pixels."""
    fy = torch.fft.fftfreq(height, device=device, dtype=dtype)
    fx = torch.fft.rfftfreq(width, device=device, dtype=dtype)
    return torch.exp(-2.0 * math.pi**2 * sigma**2 * (fy[:, None] ** 2 + fx[None, :] ** 2))


@full_precision
def cross_power_spectrum(a: Tensor, b: Tensor) -> Tensor:
    """Channel-pooled cross-power spectrum ``sum_c B_c conj(A_c)`` in rfft2 layout.

    ``(B, C, H, W) x 2 -> (B, H, W // 2 + 1)`` complex. If ``b(p) = a(p - d)`` its phase is
    ``-2 pi k . d``. The spectrum of ``b`` point-mirrored about the centre (``b(-p)``
    circularly, a half-turn about ``(W / 2, H / 2)``) is ``conj(B)``, so the cross-power of
    that mirrored ``b`` is ``conj(B * A)`` at no extra DFT.

    ``b`` may carry extra leading dimensions, ``(..., B, C, H, W) -> (..., B, H, W // 2 + 1)``:
    several ``b`` against one ``a``, whose DFT is then computed once. So is the DFT of an
    ``a`` expanded from one map (stride 0 along the batch: one template, many sources).
    """
    if isinstance(b, Tensor) and b.ndim > 4:
        check_pair(a, b[(0,) * (b.ndim - 4)], ("a", "b"))
    else:
        check_pair(a, b, ("a", "b"))
    fa = torch.fft.rfft2(a[:1]) if copies_of_one(a) else torch.fft.rfft2(a)
    return (torch.fft.rfft2(b) * fa.conj()).sum(dim=-3)


def correlation_surface(cross: Tensor, size: tuple[int, int], sigma: float = 0.0, eps: float = 1e-6) -> Tensor:
    """Normalise a cross-power spectrum to unit magnitude and return its centred inverse DFT.

    Args:
        cross: ``(B, H, W // 2 + 1)`` complex, from :func:`cross_power_spectrum`.
        size: ``(H, W)``.
        sigma, eps: as in :func:`phase_correlation`.

    Returns:
        ``(B, H, W)`` real surface; index ``(H // 2 + dy, W // 2 + dx)`` is the shift ``(dy, dx)``.
    """
    height, width = size
    power = cross.real**2 + cross.imag**2
    # The absolute floor keeps gradients finite (not just values) when the inputs carry no signal.
    floor = (eps**2) * power.mean(dim=(-2, -1), keepdim=True) + torch.finfo(power.dtype).eps ** 2
    normalised = cross / torch.sqrt(power + floor)
    if sigma > 0:
        transfer = _gaussian_transfer(height, width, sigma, power.device, power.dtype)
        # Divide by the blurred delta's own peak so that a perfect match still scores 1.
        kernel_peak = torch.fft.irfft2(transfer.to(normalised.dtype), s=(height, width))[0, 0]
        normalised = normalised * (transfer / kernel_peak)
    surface = torch.fft.irfft2(normalised, s=(height, width))
    return torch.roll(surface, shifts=(height // 2, width // 2), dims=(-2, -1))


def phase_correlation(a: Tensor, b: Tensor, sigma: float = 0.0, eps: float = 1e-6) -> Tensor:
    """Phase-correlation surface of two image batches (channels are pooled).

    The cross-power spectra of all channels are summed and normalised to unit magnitude,
    so only phase (position) information remains; its inverse DFT peaks at the shift.

    Args:
        a, b: ``(B, C, H, W)`` real images or feature maps of the same shape.
        sigma: standard deviation, in pixels, of a Gaussian blur applied to the surface (done
            in the Fourier domain, at no extra cost). A blur of about one pixel turns the
            sinc-shaped peak of a sub-pixel shift into a smooth bump whose centre a
            soft-argmax locates without bias.
        eps: relative floor of the normaliser. Coefficients where the cross-power is
            below ``eps`` times its RMS are attenuated instead of amplified, and all-zero or
            constant inputs give an all-zero surface (no NaN, no inf).

    Returns:
        ``(B, H, W)`` surface, circularly centred: index ``(H // 2 + dy, W // 2 + dx)`` is the
        shift ``(dy, dx)``. If ``b(p) = a(p - d)`` (``b`` is ``a`` moved by ``d`` pixels) the
        peak is at ``d``, with height 1 for a perfect integer circular shift (the blur is
        normalised so this holds for any ``sigma``).
    """
    return correlation_surface(cross_power_spectrum(a, b), a.shape[-2:], sigma, eps)


def phase_correlation_1d(a: Tensor, b: Tensor, sigma: float = 0.0, eps: float = 1e-6) -> Tensor:
    """Phase correlation of 1-D signals, channels pooled: ``(..., C, L) x 2 -> (..., L)``.

    The same normalisation, blur and centring as :func:`phase_correlation`: index ``L // 2 + d``
    is the circular shift ``d`` of ``b`` relative to ``a``. Leading dimensions of ``a`` and
    ``b`` broadcast.
    """
    cross = (torch.fft.rfft(b) * torch.fft.rfft(a).conj()).sum(dim=-2)
    surface = correlation_surface(cross.reshape(-1, 1, cross.shape[-1]), (1, a.shape[-1]), sigma, eps)
    return surface.view(*cross.shape[:-1], a.shape[-1])


class PhaseCorrelation(nn.Module):
    """Module form of :func:`phase_correlation`. ``(B, C, H, W) x 2 -> (B, H, W)``."""

    def __init__(self, sigma: float = 0.0, eps: float = 1e-6) -> None:
        super().__init__()
        self.sigma, self.eps = sigma, eps

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        return phase_correlation(a, b, self.sigma, self.eps)

    def extra_repr(self) -> str:
        return f"sigma={self.sigma}, eps={self.eps}"
