"""Differentiable arg-max: the expectation of a softmax over a correlation surface."""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["spatial_softmax2d", "soft_argmax2d", "SoftArgmax2d", "local_maxima2d"]


def _check_surface(surface: Tensor, temperature: float | Tensor) -> None:
    if not isinstance(surface, Tensor) or surface.ndim != 3:
        shape = tuple(surface.shape) if isinstance(surface, Tensor) else type(surface).__name__
        raise ValueError(f"surface must be a (B, H, W) tensor, got {shape}")
    if isinstance(temperature, Tensor):
        if (temperature <= 0).any():
            raise ValueError("temperature must be positive")
    elif not temperature > 0:
        raise ValueError(f"temperature must be positive, got {temperature}")


def spatial_softmax2d(surface: Tensor, temperature: float | Tensor = 1.0) -> Tensor:
    """Softmax over the last two dimensions: ``(B, H, W) -> (B, H, W)`` probabilities.

    ``p = exp(surface / temperature) / sum(...)``; a lower temperature gives a sharper peak.
    ``temperature`` may be a float or a tensor broadcastable to ``(B, 1, 1)``.
    """
    _check_surface(surface, temperature)
    batch, height, width = surface.shape
    logits = (surface / temperature).reshape(batch, height * width)
    return torch.softmax(logits, dim=-1).reshape(batch, height, width)


def _wrap(offset: Tensor, period: int) -> Tensor:
    return torch.remainder(offset + period // 2, period) - period // 2


def soft_argmax2d(
    surface: Tensor,
    temperature: float | Tensor = 1.0,
    window: int | None = None,
    circular: tuple[bool, bool] = (False, False),
    relative: bool = False,
    peak: Tensor | None = None,
) -> Tensor:
    """Sub-pixel location of the peak of each surface, as the softmax expectation.

    Args:
        surface: ``(B, H, W)`` scores (e.g. a phase-correlation surface).
        temperature: softmax temperature (float or tensor broadcastable to ``(B, 1, 1)``).
        window: if given, only the ``(2 * window + 1)``-square neighbourhood of the hard
            arg-max enters the softmax. This keeps far-away clutter out of the expectation;
            gradients still flow through every value inside the window.
        circular: per axis ``(rows, cols)``, whether it wraps around (e.g. an angle axis). The
            expectation is then taken over offsets from the hard arg-max wrapped into
            ``[-N/2, N/2)``, so a peak straddling the seam is not averaged across it.
        relative: divide the surface by its peak value first, so ``temperature`` is relative
            to the peak height. The softmax weights then form a bump of fixed width in
            pixels whatever the peak height; with ``temperature`` around 0.1-0.5 that bump
            is wide enough to be sampled without pulling the estimate towards the integer
            arg-max, which makes the expectation unbiased to about 0.01 pixel on smooth peaks.
        peak: ``(B, 2)`` integer ``(row, col)`` of the peak to refine instead of the hard
            arg-max (e.g. a secondary maximum from :func:`local_maxima2d`); needs ``window``.
            With ``relative`` the surface is then divided by its value there.

    Returns:
        ``(B, 2)`` float coordinates ``(row, col)`` in index units; circular axes are
        reduced into ``[0, N)``.
    """
    _check_surface(surface, temperature)
    batch, height, width = surface.shape
    if peak is None:
        flat_index = surface.detach().reshape(batch, -1).argmax(dim=-1)
        peak_row = torch.div(flat_index, width, rounding_mode="floor")
        peak_col = flat_index % width
    else:
        if window is None:
            raise ValueError("soft_argmax2d: a given peak needs a window")
        if peak.shape != (batch, 2) or peak.dtype.is_floating_point or peak.dtype == torch.bool:
            raise ValueError(
                f"peak must be a (B, 2) integer tensor of (row, col), got {tuple(peak.shape)} {peak.dtype}"
            )
        peak_row, peak_col = peak[:, 0].to(surface.device) % height, peak[:, 1].to(surface.device) % width
    if relative:
        peak_value = surface[torch.arange(batch, device=surface.device), peak_row, peak_col]
        # A surface with no positive peak (no signal) is left as it is rather than blown up.
        surface = surface / peak_value.clamp_min(1e-6)[:, None, None]
    if window is None:
        prob = spatial_softmax2d(surface, temperature)
        rows = torch.arange(height, device=surface.device)
        cols = torch.arange(width, device=surface.device)
        # offsets from the hard peak, (B, H) and (B, W)
        d_row = rows[None] - peak_row[:, None]
        d_col = cols[None] - peak_col[:, None]
        if circular[0]:
            d_row = _wrap(d_row, height)
        if circular[1]:
            d_col = _wrap(d_col, width)
        e_row = (prob.sum(dim=2) * d_row.to(surface.dtype)).sum(dim=1)
        e_col = (prob.sum(dim=1) * d_col.to(surface.dtype)).sum(dim=1)
    else:
        if window < 0:
            raise ValueError(f"window must be non-negative, got {window}")
        offsets = torch.arange(-window, window + 1, device=surface.device)
        row_idx = peak_row[:, None] + offsets[None]  # (B, K)
        col_idx = peak_col[:, None] + offsets[None]
        row_ok = torch.ones_like(row_idx, dtype=torch.bool) if circular[0] else (row_idx >= 0) & (row_idx < height)
        col_ok = torch.ones_like(col_idx, dtype=torch.bool) if circular[1] else (col_idx >= 0) & (col_idx < width)
        row_idx, col_idx = row_idx % height, col_idx % width
        batch_idx = torch.arange(batch, device=surface.device)[:, None, None]
        patch = surface[batch_idx, row_idx[:, :, None], col_idx[:, None, :]]  # (B, K, K)
        valid = row_ok[:, :, None] & col_ok[:, None, :]
        logits = torch.where(valid, patch / temperature, torch.full_like(patch, -torch.inf))
        prob = torch.softmax(logits.reshape(batch, -1), dim=-1).reshape_as(patch)
        off = offsets.to(surface.dtype)
        e_row = (prob.sum(dim=2) * off).sum(dim=1)
        e_col = (prob.sum(dim=1) * off).sum(dim=1)
    row = peak_row.to(surface.dtype) + e_row
    col = peak_col.to(surface.dtype) + e_col
    if circular[0]:
        row = torch.remainder(row, height)
    if circular[1]:
        col = torch.remainder(col, width)
    return torch.stack([row, col], dim=-1)


def _neighbourhood_max(surface: Tensor, radius: int, circular: tuple[bool, bool]) -> Tensor:
    """``(B, H, W)`` maximum over each bin's ``(2 * radius + 1)``-square neighbourhood."""
    for dim, wraps in zip((1, 2), circular, strict=True):
        size = surface.shape[dim]
        offsets = torch.arange(-radius, size + radius, device=surface.device)
        if wraps:  # index the wrapped bins: works for any radius
            padded = surface.index_select(dim, torch.remainder(offsets, size))
        else:
            pad = (0, 0, radius, radius) if dim == 1 else (radius, radius)
            padded = nn.functional.pad(surface, pad, value=-torch.inf)
        surface = padded.unfold(dim, 2 * radius + 1, 1).amax(dim=-1)
    return surface


def local_maxima2d(
    surface: Tensor, k: int, radius: int = 4, circular: tuple[bool, bool] = (False, False)
) -> tuple[Tensor, Tensor]:
    """The ``k`` highest peaks of each surface, at least ``radius`` bins apart on some axis.

    A peak is a bin that no bin of its ``(2 * radius + 1)``-square neighbourhood exceeds
    (wrapping on ``circular`` axes), so the flank of a broad peak is never taken for another
    one. Among those, greedy non-maximum suppression: take the highest, blank its
    neighbourhood (which settles ties on a plateau), repeat. Not differentiable (indices);
    refine each peak with ``soft_argmax2d(surface, ..., window=w, peak=indices[:, j])``.

    Args:
        surface: ``(B, H, W)`` scores.
        k: number of peaks (``1 <= k <= H * W``).
        radius: suppression half-size in bins.
        circular: per axis ``(rows, cols)``, whether it wraps around.

    Returns:
        ``values`` ``(B, k)`` (descending; ``-inf`` where the surface has fewer than ``k``
        peaks that far apart) and ``indices`` ``(B, k, 2)`` integer ``(row, col)``.
    """
    _check_surface(surface, 1.0)
    batch, height, width = surface.shape
    if not isinstance(k, int) or not 1 <= k <= height * width:
        raise ValueError(f"k must be an integer in [1, {height * width}], got {k!r}")
    if radius < 0:
        raise ValueError(f"radius must be non-negative, got {radius}")
    rows = torch.arange(height, device=surface.device)
    cols = torch.arange(width, device=surface.device)
    scores = surface.detach()
    scores = scores.masked_fill(scores < _neighbourhood_max(scores, radius, circular), -torch.inf)
    values, indices = [], []
    for _ in range(k):
        value, flat = scores.reshape(batch, -1).max(dim=-1)
        row, col = torch.div(flat, width, rounding_mode="floor"), flat % width
        found = surface[torch.arange(batch, device=surface.device), row, col]
        values.append(torch.where(value == -torch.inf, value, found))  # -inf: no peak left
        indices.append(torch.stack([row, col], dim=-1))
        d_row, d_col = rows[None] - row[:, None], cols[None] - col[:, None]
        if circular[0]:
            d_row = _wrap(d_row, height)
        if circular[1]:
            d_col = _wrap(d_col, width)
        near = (d_row.abs() <= radius)[:, :, None] & (d_col.abs() <= radius)[:, None, :]
        scores = scores.masked_fill(near, -torch.inf)
    return torch.stack(values, dim=1), torch.stack(indices, dim=1)


class SoftArgmax2d(nn.Module):
    """Module form of :func:`soft_argmax2d`, optionally with a learnable temperature.

    A learnable temperature is stored as its logarithm so it stays positive.
    """

    def __init__(
        self,
        temperature: float = 1.0,
        learnable: bool = False,
        window: int | None = None,
        circular: tuple[bool, bool] = (False, False),
        relative: bool = False,
    ) -> None:
        super().__init__()
        if not temperature > 0:
            raise ValueError(f"temperature must be positive, got {temperature}")
        log_t = torch.tensor(float(temperature)).log()
        if learnable:
            self.log_temperature = nn.Parameter(log_t)
        else:
            self.register_buffer("log_temperature", log_t)
        self.window = window
        self.circular = tuple(circular)
        self.relative = relative

    @property
    def temperature(self) -> Tensor:
        return self.log_temperature.exp()

    def forward(self, surface: Tensor) -> Tensor:
        return soft_argmax2d(surface, self.temperature.to(surface.dtype), self.window, self.circular, self.relative)

    def extra_repr(self) -> str:
        return f"window={self.window}, circular={self.circular}, relative={self.relative}"
