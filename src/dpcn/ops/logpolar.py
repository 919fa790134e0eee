"""Log-polar resampling of a centred magnitude spectrum (kornia grid sampling).

In log-polar coordinates a rotation of the image becomes a circular shift along the angle
axis and a scaling becomes a shift along the log-radius axis, so both are found by one
phase correlation (the Fourier-Mellin trick).
"""

from __future__ import annotations

import math
from functools import lru_cache

import kornia
import torch
from torch import Tensor, nn

from ._checks import check_image

__all__ = ["log_polar_grid", "log_polar", "LogPolar", "log_radius_step"]


def log_radius_step(n_radii: int, min_radius: float, max_radius: float) -> float:
    """Natural-log radius increment per log-polar column; a scale ``s`` shifts by ``ln(s) / step`` columns."""
    return math.log(max_radius / min_radius) / (n_radii - 1)


def log_polar_grid(
    height: int,
    width: int,
    n_angles: int,
    n_radii: int,
    min_radius: float = 0.03,
    max_radius: float = 0.95,
    device: torch.device | None = None,
    dtype: torch.dtype = torch.float32,
    half: bool = False,
) -> tuple[Tensor, Tensor]:
    """Pixel coordinates ``(map_x, map_y)``, each ``(n_angles, n_radii)``, that sample an
    fftshifted ``(H, W)`` spectrum on a log-polar grid.

    Row ``k`` is the angle ``180 * k / n_angles`` degrees (``[0, 180)``: a magnitude spectrum
    is point-symmetric, so half a turn holds everything). Column ``j`` is the radius
    ``min_radius * (max_radius / min_radius) ** (j / (n_radii - 1))`` as a fraction of the
    Nyquist frequency. Radii are physical frequencies (cycles per pixel), so the grid is an
    ellipse in index space for non-square images and rotations stay rotations.

    With ``half=True`` the grid samples a half spectrum (``magnitude_spectrum(..., half=True)``,
    DC at ``(H // 2, 0)``) and row ``k`` is the angle ``-90 + 180 * k / n_angles``: the same
    circle, started a quarter turn earlier, so shifts between two maps are unchanged.
    """
    if n_angles < 2 or n_radii < 2:
        raise ValueError(f"n_angles and n_radii must be at least 2, got {n_angles} and {n_radii}")
    if not 0.0 < min_radius < max_radius <= 1.0:
        raise ValueError(
            f"need 0 < min_radius < max_radius <= 1 (fractions of Nyquist), got {min_radius}, {max_radius}"
        )
    angles = torch.arange(n_angles, device=device, dtype=dtype) * (math.pi / n_angles)
    if half:
        angles = angles - math.pi / 2
    step = log_radius_step(n_radii, min_radius, max_radius)
    radii = min_radius * torch.exp(torch.arange(n_radii, device=device, dtype=dtype) * step)
    # Nyquist (0.5 cycles / pixel) is W / 2 index steps away from DC along x, H / 2 along y.
    map_x = (0 if half else width // 2) + (0.5 * width) * radii[None, :] * torch.cos(angles)[:, None]
    map_y = height // 2 + (0.5 * height) * radii[None, :] * torch.sin(angles)[:, None]
    return map_x, map_y


def log_polar(
    spectrum: Tensor,
    n_angles: int = 256,
    n_radii: int = 256,
    min_radius: float = 0.03,
    max_radius: float = 0.95,
    half: bool = False,
    width: int | None = None,
) -> Tensor:
    """Resample centred spectra ``(B, C, H, W)`` to log-polar maps ``(B, C, n_angles, n_radii)``.

    Bilinear, differentiable with respect to the spectrum. See :func:`log_polar_grid` for the
    axes and ``half``; for a half spectrum ``width`` is the width of the image it came from
    (required: ``W // 2 + 1`` columns do not tell an odd width from an even one). A rotation
    of the image by ``a`` degrees shifts the map by ``-a * n_angles / 180``
    rows (circularly); a scaling by ``s`` shifts it by ``-ln(s) / log_radius_step`` columns.
    """
    check_image(spectrum, "spectrum")
    _, _, height, columns = spectrum.shape
    if half:
        if width is None or width // 2 + 1 != columns:
            raise ValueError(f"a half spectrum with {columns} columns needs the image width (got width={width})")
    else:
        width = columns
    map_x, map_y = _normalized_grid(
        height, width, columns, n_angles, n_radii, min_radius, max_radius, spectrum.device, spectrum.dtype, half
    )
    # One (1, n_angles, n_radii) grid broadcast over the batch: no per-call copies.
    return kornia.geometry.transform.remap(
        spectrum, map_x, map_y, mode="bilinear", padding_mode="zeros", align_corners=True, normalized_coordinates=True
    )


@lru_cache(maxsize=32)
def _normalized_grid(
    height: int,
    width: int,
    columns: int,
    n_angles: int,
    n_radii: int,
    min_radius: float,
    max_radius: float,
    device: torch.device,
    dtype: torch.dtype,
    half: bool,
) -> tuple[Tensor, Tensor]:
    """:func:`log_polar_grid` in grid-sample coordinates (``[-1, 1]``, corners aligned) for a
    spectrum of ``columns`` columns, ``(1, n_angles, n_radii)`` each; cached, since every
    call of a model uses the same few grids."""
    # Normal tensors even when first called under inference mode (a validation before
    # training): grid sampling saves its grid for the backward pass.
    with torch.inference_mode(False), torch.no_grad():
        pixels = torch.stack(
            log_polar_grid(height, width, n_angles, n_radii, min_radius, max_radius, device, dtype, half), dim=-1
        )
        normalized = kornia.geometry.conversions.normalize_pixel_coordinates(pixels, height, columns)
    return normalized[None, ..., 0], normalized[None, ..., 1]


class LogPolar(nn.Module):
    """Module form of :func:`log_polar`, caching the sampling grid per input size."""

    def __init__(
        self, n_angles: int = 256, n_radii: int = 256, min_radius: float = 0.03, max_radius: float = 0.95
    ) -> None:
        super().__init__()
        log_polar_grid(8, 8, n_angles, n_radii, min_radius, max_radius)  # validate early
        self.n_angles, self.n_radii = n_angles, n_radii
        self.min_radius, self.max_radius = min_radius, max_radius

    @property
    def radius_step(self) -> float:
        return log_radius_step(self.n_radii, self.min_radius, self.max_radius)

    def forward(self, spectrum: Tensor) -> Tensor:
        return log_polar(spectrum, self.n_angles, self.n_radii, self.min_radius, self.max_radius)

    def extra_repr(self) -> str:
        return (
            f"n_angles={self.n_angles}, n_radii={self.n_radii}, "
            f"min_radius={self.min_radius}, max_radius={self.max_radius}"
        )
