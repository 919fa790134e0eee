"""A small, configurable U-Net feature extractor (the paper's f1/f2 and g1/g2)."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .._validate import check_ints

__all__ = ["UNet", "upsample2x_bilinear"]

_MAX_WEIGHTS = 2**30  # 4 GiB of float32 weights for one U-Net; `paper`'s four hold 31 million in all


class _GroupNorm(nn.GroupNorm):
    """GroupNorm that takes narrow channels-last CPU inputs through the channels-first kernel.

    PyTorch's channels-last CPU GroupNorm vectorises over channels, so with the few channels
    of the full-resolution levels it is 5-10x slower (forward and backward) than the
    channels-first kernel plus two layout copies. Same parameters and state dict as
    ``nn.GroupNorm``.
    """

    def forward(self, x: Tensor) -> Tensor:
        if x.device.type == "cpu" and x.shape[1] < 16 and not x.is_contiguous():
            return super().forward(x.contiguous()).contiguous(memory_format=torch.channels_last)
        return super().forward(x)


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":
        return _GroupNorm(math.gcd(8, channels), channels)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"unknown norm {kind!r}; choose batch, group or none")


def _conv_concatenated(conv: nn.Conv2d, a: Tensor, b: Tensor) -> Tensor:
    """``conv(torch.cat([a, b], dim=1))`` as two convolutions by the weight's halves, summed.

    The same result without the concatenation, which for channels-last tensors is a strided
    interleave as slow as a convolution (U-Net forward 15-30 % faster on CPUs, backward ~15 %).
    """
    split = a.shape[1]
    first = F.conv2d(a, conv.weight[:, :split], None, conv.stride, conv.padding)
    return first + F.conv2d(b, conv.weight[:, split:], conv.bias, conv.stride, conv.padding)


def upsample2x_bilinear(x: Tensor) -> Tensor:
    """``F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)`` of a
    ``(B, C, H, W)`` tensor, from shifted copies: along each axis output ``2i`` is
    ``3/4 x[i] + 1/4 x[i-1]`` and ``2i+1`` is ``3/4 x[i] + 1/4 x[i+1]``, edges clamped.

    Same values (to rounding) and gradients; on CUDA PyTorch's channels-first bilinear kernel
    loops over batch and channels in each thread, which made it 42 % of a batched `paper`
    forward pass on an H200, while these are a few bandwidth-bound element-wise passes.
    """
    for dim, pad in ((-1, (1, 1, 0, 0)), (-2, (0, 0, 1, 1))):
        padded = F.pad(x, pad, mode="replicate")
        n = x.shape[dim]
        before, after = padded.narrow(dim, 0, n), padded.narrow(dim, 2, n)
        x = torch.stack([torch.lerp(x, before, 0.25), torch.lerp(x, after, 0.25)], dim=dim).flatten(dim - 1, dim)
    return x


def _block(in_ch: int, out_ch: int, norm: str) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_ch, out_ch, 3, padding=1, bias=norm == "none"),
        _norm(norm, out_ch),
        nn.SiLU(inplace=True),
        nn.Conv2d(out_ch, out_ch, 3, padding=1, bias=norm == "none"),
        _norm(norm, out_ch),
        nn.SiLU(inplace=True),
    )


class UNet(nn.Module):
    """U-Net: ``(B, in_channels, H, W) -> (B, out_channels, H, W)``, positive outputs.

    Args:
        in_channels: 1 (grey) or 3 (colour) usually.
        out_channels: feature channels fed to the phase correlation (pooled there).
        base_channels: width of the first level; doubled at each down-sampling.
        depth: number of down-sampling (and up-sampling) levels; the paper uses 4.
            ``H`` and ``W`` need not be multiples of ``2 ** depth`` (skips are resized).
        norm: ``group`` (a pair gives the same features alone or in any batch, and DDP needs no
            synchronisation), ``batch`` or ``none`` (no normalisation, cheapest).
        upsample: decoder upsampling, ``bilinear`` or ``nearest`` (cheaper backward pass).

    Outputs go through softplus: the paper keeps features positive so that the correlation
    has no negative peaks to confuse with matches.

    ``input_skip=True`` adds a 1x1 convolution from the input to the head and starts the head
    at zero, so an untrained U-Net is ``softplus(mean of the input channels)`` and an untrained
    DPCN *is* classical phase correlation. That helps when the two sensors already agree
    roughly; on strongly different ones (sensor-fixed texture and banding to be cancelled)
    it trained slower than a fresh extractor, hence off by default.
    """

    def __init__(
        self,
        in_channels: int = 1,
        out_channels: int = 1,
        base_channels: int = 16,
        depth: int = 4,
        norm: str = "group",
        input_skip: bool = False,
        upsample: str = "bilinear",
    ) -> None:
        super().__init__()
        if upsample not in ("bilinear", "nearest"):
            raise ValueError(f"unknown upsample {upsample!r}; choose bilinear or nearest")
        self.upsample = upsample
        check_ints(
            "U-Net ",
            ("in_channels", in_channels, 1),
            ("out_channels", out_channels, 1),
            ("base_channels", base_channels, 1),
            ("depth", depth, 0),
        )
        widths = [base_channels * 2**i for i in range(depth + 1)]
        # Two 3x3 convolutions per block: checked before allocating, as a typo (base_channels=4096)
        # would otherwise take the machine's memory, and the process with it, without a word.
        blocks = [(in_channels, widths[0])] + [(widths[i], widths[i + 1]) for i in range(depth)]
        blocks += [(widths[i + 1] + widths[i], widths[i]) for i in range(depth)]
        weights = sum(9 * (a * b + b * b) for a, b in blocks)
        if weights > _MAX_WEIGHTS:
            raise ValueError(
                f"a U-Net of base_channels={base_channels} and depth={depth} would hold {weights:.3g} weights "
                f"({4 * weights / 2**30:.0f} GiB in float32; at most {_MAX_WEIGHTS:.3g}): fewer channels or levels"
            )
        self.stem = _block(in_channels, widths[0], norm)
        self.down = nn.ModuleList(_block(widths[i], widths[i + 1], norm) for i in range(depth))
        self.up = nn.ModuleList(_block(widths[i + 1] + widths[i], widths[i], norm) for i in reversed(range(depth)))
        self.head = nn.Conv2d(widths[0], out_channels, 1)
        self.skip = nn.Conv2d(in_channels, out_channels, 1) if input_skip else None
        if self.skip is not None:
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)
            nn.init.constant_(self.skip.weight, 1.0 / in_channels)
            nn.init.zeros_(self.skip.bias)
        self.depth = depth
        self._set_layout()

    @staticmethod
    def layout(device: torch.device) -> torch.memory_format:
        """Channels-last on CPUs: with a few channels at full resolution, oneDNN's convolutions
        (above all their backward pass) run 3-5x faster in it. Channels-first elsewhere: CUDA's
        GroupNorm and bilinear kernels work channels-first, so channels-last there costs a
        layout copy per layer."""
        return torch.channels_last if device.type == "cpu" else torch.contiguous_format

    def _set_layout(self) -> None:
        layout = self.layout(self.head.weight.device)
        for module in self.modules():
            if isinstance(module, nn.Conv2d) and not module.weight.is_contiguous(memory_format=layout):
                module.weight.data = module.weight.data.contiguous(memory_format=layout)

    def _apply(self, fn, recurse: bool = True):  # .to(device), .cuda(), ...: keep the device's layout
        super()._apply(fn, recurse)
        self._set_layout()
        return self

    def forward(self, x: Tensor) -> Tensor:
        dtype = x.dtype  # features come back in the input's dtype whatever the weights' (bfloat16)
        x = x.to(self.head.weight.dtype).contiguous(memory_format=self.layout(x.device))
        skips = [self.stem(x)]
        for block in self.down:
            skips.append(block(F.max_pool2d(skips[-1], 2, ceil_mode=True)))
        y = skips.pop()
        corners = False if self.upsample == "bilinear" else None
        for block in self.up:
            skip = skips.pop()
            size = skip.shape[-2:]
            if self.upsample == "bilinear" and x.device.type != "cpu" and size == (2 * y.shape[-2], 2 * y.shape[-1]):
                y = upsample2x_bilinear(y)  # on CPUs F.interpolate is faster (1.2-3.5x, channels-last)
            else:
                y = F.interpolate(y, size=size, mode=self.upsample, align_corners=corners)
            y = block[1:](_conv_concatenated(block[0], y, skip))
        out = self.head(y) if self.skip is None else self.head(y) + self.skip(x)
        return F.softplus(out).to(dtype).contiguous()
