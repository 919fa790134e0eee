"""DPCN: four U-Nets feeding the differentiable phase correlation (paper section 2).

Phase 1 (rotation and scale): U-Nets ``f1``/``f2`` extract features of the template and the
source; magnitude spectra -> log-polar -> phase correlation -> rotation (mod 180 degrees)
and scale. Between the phases the source is un-rotated/un-scaled by that estimate with a
kornia warp. Phase 2 (translation): U-Nets ``g1``/``g2`` -> phase correlation -> shift.

The half-turn left open by phase 1 is settled in phase 2: the translation features are
computed for the un-warped source and for its half-turn, and the stronger peak wins. (The
conjugate-spectrum shortcut of the classical estimator does not apply here: a U-Net is not
equivariant to half-turns.) With ``half_turn_pass="winner"`` the turns are compared on the
upright features turned instead, which a U-Net's near-equivariance allows, and only a winner
that is turned gets its own pass on the turned source, which places its peak and must still
beat the strongest upright candidate. With ``rotation_hypotheses = K > 1`` phase 2 checks
the ``K`` strongest phase-1 peaks the same way: a wrong rotation leaves no translation peak,
so the strongest translation peak over the ``2 K`` candidates picks the pose; with
``hypothesis_ratio = r > 0`` only the pairs whose second phase-1 peak reaches ``r`` times
their first (the ambiguous ones) pay for that check, the others keep their first peak. With
``spectrum_window_grid = n > 1`` phase 1 also takes the source's spectrum under an ``n x n``
grid of shifted windows and keeps the best correlation per log-polar bin: a translated
source shares more content with the template under a window near its translated centre.
With ``rotation_views = V > 1`` phase 1 also runs on the turned and mirrored pair
(:func:`~dpcn.estimator.dihedral_views`) and averages the ``V`` log-polar surfaces: a U-Net is
not equivariant to turns or mirrors, so their clutter differs while the true peak is shared.
All three are inference settings; training uses one view, one centred window and one
hypothesis.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import kornia
import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .._validate import check_bool, check_int, check_ints, check_number, check_sequence
from ..estimator import (
    RotationScale,
    Translation,
    check_rotation_range,
    check_rotation_scale_correlation,
    check_scale_range,
    check_views,
    choose_half_turn,
    dihedral_views,
    estimate_rotation_scale,
    estimate_translation,
    outside_rotation_range,
    unwarp_rotation_scale,
    window_grid_shifts,
)
from ..io import flag_featureless, is_tensor_pair, prepare_pair
from ..ops._checks import check_pair, copies_of_one, full_precision, inputs_checked
from ..ops.logpolar import log_polar_grid, log_radius_step
from ..pose import Pose, wrap_angle
from .unet import UNet

__all__ = [
    "DPCN",
    "DPCNOutput",
    "HALF_TURN_PASSES",
    "PHASE_UNETS",
    "ROTATION_SCALE_POOLING",
    "TEXTURE_ENERGY",
    "TemplateFeatures",
    "UNET_DTYPES",
    "half_turn",
    "local_relief",
    "local_texture",
]

ROTATION_SCALE_POOLING = ("average", "space_to_depth")
UNET_DTYPES = ("float32", "bfloat16")  # inference settings of DPCN.unet_dtype
# Inference settings of DPCN.half_turn_pass: which candidates' half-turns get their own phase-2
# source U-Net pass ("winner": only a winner that is turned; "every": each candidate's, before choosing).
HALF_TURN_PASSES = ("winner", "every")
# Each phase's two U-Nets (template, source), by attribute name.
PHASE_UNETS = {"rotation_scale": ("rs_template", "rs_source"), "translation": ("t_template", "t_source")}


def half_turn(image: Tensor) -> Tensor:
    """Rotate ``(B, C, H, W)`` images by 180 degrees about ``(W / 2, H / 2)`` (circularly),
    exactly: pixel ``p`` goes to ``-p`` modulo the size."""
    return torch.roll(torch.flip(image, dims=(-2, -1)), shifts=(1, 1), dims=(-2, -1))


def _with_rows(values: Tensor, rows: Tensor, new: Tensor) -> Tensor:
    """A copy of ``values`` with ``values[rows] = new``."""
    merged = values.clone()
    merged[rows] = new
    return merged


_TRANSLATION_FIELDS = tuple(field.name for field in dataclasses.fields(Translation))


def _replace_rows(tr: Translation, rows: Tensor, new: Translation, pick: Tensor | slice = slice(None)) -> Translation:
    """``tr`` with its ``rows`` from ``new[pick]`` (field by field)."""
    return Translation(*(_with_rows(getattr(tr, f), rows, getattr(new, f)[pick]) for f in _TRANSLATION_FIELDS))


class _Pick(NamedTuple):
    """Phase 2's chosen candidate per pair (all ``(B, ...)``): its translation, source
    features, candidate index, whether it is the half-turned hypothesis, its un-warped source
    and its score (the confidence, ``-inf`` where no allowed candidate was left)."""

    tr: Translation
    t_source: Tensor
    choice: Tensor
    turned: Tensor
    unwarped: Tensor
    score: Tensor


def _pick_rows(pick: _Pick, rows: Tensor) -> _Pick:
    """The ``rows`` of ``pick``."""
    tr = Translation(*(getattr(pick.tr, f)[rows] for f in _TRANSLATION_FIELDS))
    return _Pick(tr, *(field[rows] for field in pick[1:]))


def _merge_picks(mine: _Pick, rows: Tensor, theirs: _Pick, take: Tensor) -> _Pick:
    """``mine`` with its ``rows`` from ``theirs[take]`` (``take``: ``(len(rows),)`` bool)."""
    won = rows[take]
    tr = _replace_rows(mine.tr, won, theirs.tr, take)
    fields = (_with_rows(a, won, b[take]) for a, b in zip(mine[1:], theirs[1:], strict=True))
    return _Pick(tr, *fields)


@full_precision  # under bf16 autocast the blur's rounding (~0.004 on 0-1 images) would pass the gain
def local_relief(image: Tensor, gain: float, sigma: float = 4.0) -> Tensor:
    """Local relief with a compressed range: ``asinh(gain * (x - G * x)) / asinh(gain)``.

    ``G * x`` is a Gaussian blur of standard deviation ``sigma`` pixels (reflected borders),
    so slow trends vanish and steps of any height become responses of comparable size: on an
    elevation map coded 0-1 a 0.15 m kerb (about 0.005) and a 10 m wall (about 0.4) differ
    by a factor of 80 in ``x`` and of about 16 at their edges here with ``gain = 100``
    (each edge keeps about half its step: ``asinh(0.25)`` against ``asinh(20)``). Differentiable.

    Args:
        image: ``(B, C, H, W)``.
        gain: positive; steps well under ``1 / gain`` pass linearly, bigger ones are compressed.
        sigma: the blur's standard deviation in pixels.

    Returns:
        ``(B, C, H, W)``, same device, in ``(-1, 1)`` for inputs in ``[0, 1]``; computed
        outside autocast, in float32 for float16/bfloat16 inputs (and returned so).
    """
    return torch.asinh(gain * (image - _gaussian_blur(image, sigma))) / math.asinh(gain)


def _gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of ``sigma`` pixels, ``2 ceil(3 sigma) + 1`` taps, reflected borders."""
    radius = max(1, int(math.ceil(3.0 * sigma)))
    return kornia.filters.gaussian_blur2d(image, (2 * radius + 1,) * 2, (sigma, sigma), border_type="reflect")


@full_precision  # grain of 0.01-0.1 is a few bfloat16 steps of a 0-1 image
def local_texture(image: Tensor, sigma: float = 2.0, window: float = 3.0, gain: float = 10.0) -> Tensor:
    """Local texture energy: ``gain * sqrt(G_w * (x - G_s * x)^2 + 1e-6)``, per channel.

    The detail finer than a Gaussian of ``sigma`` pixels, its square averaged under a Gaussian
    of ``window`` pixels: how strongly the image varies around each pixel. Two regions of one
    grey level but different grain differ here, and a box average to half size (phase 1's
    input) keeps the difference where it erases the grain itself. Differentiable.

    Args:
        image: ``(B, C, H, W)``.
        sigma, window: the two blurs' standard deviations in pixels (reflected borders).
        gain: a scale; grain of standard deviation 0.01-0.1 in ``[0, 1]`` images gives about 0.1-1.

    Returns:
        ``(B, C, H, W)``, same device, non-negative; computed outside autocast, in float32
        for float16/bfloat16 inputs (and returned so).
    """
    detail = image - _gaussian_blur(image, sigma)
    return gain * torch.sqrt(_gaussian_blur(detail * detail, window) + 1e-6)


TEXTURE_ENERGY = ("template", "both")


@dataclass
class DPCNOutput:
    """Everything one pass computes (for losses, metrics and interpretability figures)."""

    pose: Pose
    rotation_scale: RotationScale
    translation: Translation
    unwarped_source: Tensor
    features: dict[str, Tensor]


class TemplateFeatures(NamedTuple):
    """A template's U-Net features for both phases (:meth:`DPCN.template_features`), to
    match one template against many sources without running its U-Nets again.

    ``rotation_scale``: ``(views * B, C, h, w)`` phase-1 features of the template's
    ``views`` dihedral views, view-major; ``translation``: ``(B, C, H, W)`` phase-2 features.
    """

    rotation_scale: Tensor
    translation: Tensor
    views: int

    def expand(self, n: int) -> TemplateFeatures:
        """The features of one template (``B = 1``) for ``n`` pairs, in the layout a batch of
        ``n`` identical templates would have (phase 2's without a copy)."""
        if self.translation.shape[0] != 1:
            raise ValueError(f"only the features of one template can be expanded, got {self.translation.shape[0]}")
        rs = self.rotation_scale
        rs = rs[:, None].expand(-1, n, -1, -1, -1).reshape(self.views * n, *rs.shape[1:])
        return TemplateFeatures(rs, self.translation.expand(n, -1, -1, -1), self.views)


class DPCN(nn.Module):
    """Deep Phase Correlation Network. ``forward(template, source) -> DPCNOutput``.

    A ``(1, C, H, W)`` template is matched against each of ``B`` sources with its U-Nets run
    once (e.g. a robot's local map against aerial crops at many particle poses).

    Args:
        in_channels: image channels (1 or 3).
        feature_channels: channels of each U-Net's output (pooled by the correlation).
        base_channels, depth: U-Net width and number of down-sampling levels (see
            :class:`~dpcn.models.unet.UNet`); presets: ``tiny`` (4, 3; phase 1: 8, 4 at half size), ``paper`` (32, 4).
        norm, input_skip, upsample: U-Net normalisation, input skip and decoder upsampling
            (see :class:`~dpcn.models.unet.UNet`).
        rotation_scale_downsample: phase 1 runs its U-Nets at ``1 / d`` of the image size for
            this integer factor ``d``. Rotation and scale survive the shrinking, and at half
            size a U-Net sees twice the context for a quarter of the cost; phase 2
            (translation, which needs every pixel) always runs at full size.
        rotation_scale_pooling: how phase 1 shrinks its input: ``average`` (a d x d box
            average) or ``space_to_depth`` (each d x d block becomes ``d * d`` channels, as
            ``torch.nn.functional.pixel_unshuffle``: the same resolution and nearly the same
            cost, but fine texture that averaging would erase still reaches the U-Net).
        rotation_scale_base_channels, rotation_scale_depth: width and depth of the phase-1
            U-Nets (``None``: ``base_channels`` / ``depth``).
        rotation_scale_template_channels: width of the template's phase-1 U-Net alone
            (``None``: ``rotation_scale_base_channels``). The two sides need not match: only
            their output feature maps meet, and the template side is the harder one when its
            sensor shows the shared structure faintly (the simulated style A).
        image_size: ``(H, W)`` the model is built for; other sizes raise a clear error
            (``None`` accepts any size).
        n_angles, n_radii, min_radius, max_radius, highpass, log_spectrum, radius_window:
            phase-1 log-polar settings (see :func:`~dpcn.estimator.estimate_rotation_scale`;
            ``radius_window``: a Hann window along the maps' log-radius axis, which the
            classical estimator gains from and `tiny` trained worse with: README).
        sigma, rotation_sigma, temperature, rotation_temperature, window: sub-pixel peak
            location at inference (see :class:`~dpcn.estimator.PhaseCorrelationEstimator`).
        train_temperature: softmax temperature of the training losses (the paper's
            temperature), per phase ``(rotation_scale, translation)``; correlation values
            are in ``[-1, 1]``.
        learnable_temperature: learn the two training temperatures.
        scale_range: the scales phase 1 searches, ``[low, high]`` with ``low <= 1 <= high``
            (``None``: every scale of the log-polar maps), in training and at inference;
            settable on a loaded model, e.g. to the range a robot's and an aerial map's
            resolutions allow (a scale prior, like ``rotation_range``).
        rotation_hypotheses: phase-1 peaks (rotation/scale hypotheses) that phase 2 checks at
            inference; each costs two more phase-2 source U-Net passes (one with
            ``half_turn_pass="winner"``). Training is unaffected (phase 1 learns from its own
            surface).
        hypothesis_ratio: in ``[0, 1]``; with ``rotation_hypotheses > 1``, phase 2 checks a
            pair's further peaks only when its second phase-1 peak is at least this fraction
            of its first, and keeps the first peak of the other pairs (their pose is the one
            hypothesis's). ``0``: every pair. A clear first peak is rarely wrong, so e.g.
            ``0.7`` keeps nearly all of the hypotheses' gain for the cost of the ambiguous
            pairs alone (README, Benchmarks).
        spectrum_window_grid, spectrum_window_step: at inference, phase 1 also correlates the
            template's spectrum with the source's under an ``n x n`` grid of windows shifted by
            multiples of ``spectrum_window_step`` (a fraction of the image side), the best per
            bin counting (see :func:`~dpcn.estimator.estimate_rotation_scale`); ``n`` odd,
            ``1``: the centred window only.
        rotation_views: at inference, phase 1 averages its log-polar surfaces over this many
            dihedral views of the pair (1-8, see :func:`~dpcn.estimator.dihedral_views`: 2 adds
            the mirrored pair, 4 and 8 quarter turns too, for square images); each view costs
            one more pass of both phase-1 U-Nets and spectra.
        inference_radii: at inference, phase 1's log-polar maps have this many radii instead
            of ``n_radii`` (``None``: ``n_radii``); the same radius range, so each column spans
            ``n_radii / inference_radii`` times the log-scale step. Training always uses
            ``n_radii``: the U-Nets come before the log-polar resampling, so their weights do
            not depend on it. Half the radii halve the cost of phase 1's log-polar maps and
            their DFTs (README, Benchmarks).
        inference_sigma: at inference, the blur (pixels) of phase 2's correlation surfaces
            before their peak is located, instead of ``sigma`` (``None``: ``sigma``); training
            keeps ``sigma``. A broader blur than the training's locates the peak more
            steadily (`tiny`: 3 for a training 2; README, Benchmarks).
        template_relief: with a gain ``g`` (``None``: off), the template's U-Nets (both
            phases) take the image and its :func:`local_relief` (gain ``g``, ``sigma`` 4 px
            at full size) side by side, twice the input channels: for templates whose shared
            structure is small steps next to large ones, such as kerbs beside buildings on an
            elevation map. The source side is unchanged.
        texture_energy: ``None`` (off), ``"template"`` or ``"both"``: those phase-1 U-Nets
            also take the image's :func:`local_texture`, computed at full size before the
            shrink to phase 1's resolution (which averages fine grain away): for regions told
            apart by their grain rather than their grey level. Phase 2 sees full-size images
            and is unchanged.
        rotation_scale_correlation: how phase 1 correlates the log-polar maps: ``joint``
            (the paper's 2-D phase correlation) or ``decoupled`` (DPCN++'s 1-D phase
            correlations of their angle and log-radius profiles, rotation and scale each
            found whatever the other; see :func:`~dpcn.estimator.log_polar_correlation`).
            Training and inference both use it.
        rotation_range: inference only: a known range of the rotation, ``[low, high]``
            degrees (a heading prior; the paper's data: ``[0, 180]``). A range of at most 180
            degrees settles the half-turn that phase 1 leaves open, so phase 2 runs once
            instead of twice per candidate; a wider one only rules out turns outside it.
            ``None``: the full circle, phase 2 decides (settable on a loaded model).
        half_turn_pass: inference only: which half-turns phase 2 runs its source U-Net on.
            ``"every"``: each candidate's (two passes per candidate, as in training).
            ``"winner"``: the turns are compared on the upright pass's features turned by
            half a turn (a U-Net is nearly, not exactly, equivariant to the turn), and only
            a winner that is turned gets its own pass, which places its peak and must still
            beat the strongest upright candidate: one source pass per candidate plus one
            per pair at most. Faster in batches, within half a point of ``"every"`` on the
            test sets measured (README, Benchmarks); settable on a loaded model.
    """

    def __init__(
        self,
        in_channels: int = 1,
        feature_channels: int = 1,
        base_channels: int = 8,
        depth: int = 3,
        norm: str = "group",
        input_skip: bool = False,
        upsample: str = "bilinear",
        rotation_scale_downsample: int = 1,
        rotation_scale_pooling: str = "average",
        rotation_scale_base_channels: int | None = None,
        rotation_scale_depth: int | None = None,
        rotation_scale_template_channels: int | None = None,
        image_size: tuple[int, int] | list[int] | None = (256, 256),
        n_angles: int = 256,
        n_radii: int = 256,
        min_radius: float = 0.03,
        max_radius: float = 0.95,
        highpass: bool = True,
        log_spectrum: bool = False,
        sigma: float = 2.0,
        rotation_sigma: float = 1.0,
        temperature: float = 0.1,
        rotation_temperature: float = 0.07,
        window: int = 3,
        train_temperature: tuple[float, float] | list[float] | float = (0.02, 0.02),
        learnable_temperature: bool = True,
        scale_range: tuple[float, float] | list[float] | None = (0.5, 2.0),
        rotation_hypotheses: int = 1,
        hypothesis_ratio: float = 0.0,
        spectrum_window_grid: int = 1,
        spectrum_window_step: float = 0.125,
        rotation_views: int = 1,
        inference_radii: int | None = None,
        inference_sigma: float | None = None,
        template_relief: float | None = None,
        texture_energy: str | None = None,
        rotation_scale_correlation: str = "joint",
        rotation_range: tuple[float, float] | list[float] | None = None,
        radius_window: bool = False,
        half_turn_pass: str = "every",
    ) -> None:
        super().__init__()
        # Config values by name (they may arrive as strings from the command line).
        check_ints(
            "model.net.",
            ("in_channels", in_channels, 1),
            ("feature_channels", feature_channels, 1),
            ("base_channels", base_channels, 1),
            ("depth", depth, 0),
            ("rotation_scale_downsample", rotation_scale_downsample, 1),
            ("rotation_scale_base_channels", rotation_scale_base_channels, 1),
            ("rotation_scale_depth", rotation_scale_depth, 0),
            ("rotation_scale_template_channels", rotation_scale_template_channels, 1),
            ("n_angles", n_angles, 2),
            ("n_radii", n_radii, 2),
            ("window", window, 0),
        )
        for name, value in (("min_radius", min_radius), ("max_radius", max_radius)):
            check_number(f"model.net.{name}", value, low=0.0, high=1.0, low_open=True)
        if template_relief is not None:
            template_relief = check_number("model.net.template_relief", template_relief, low=0.0, low_open=True)
        if texture_energy is not None and texture_energy not in TEXTURE_ENERGY:
            raise ValueError(
                f"model.net.texture_energy must be null or one of {', '.join(TEXTURE_ENERGY)}, got {texture_energy!r}"
            )
        for name, value in (("sigma", sigma), ("rotation_sigma", rotation_sigma)):
            check_number(f"model.net.{name}", value, low=0.0)
        for name, value in (("temperature", temperature), ("rotation_temperature", rotation_temperature)):
            check_number(f"model.net.{name}", value, low=0.0, low_open=True)
        switches = (("input_skip", input_skip), ("highpass", highpass), ("log_spectrum", log_spectrum))
        for name, value in (*switches, ("radius_window", radius_window)):
            check_bool(f"model.net.{name}", value)
        if image_size is not None:
            check_sequence("image_size", image_size, 2, "an (H, W) pair of integers")
            image_size = [check_int("image_size", v, low=8 * int(rotation_scale_downsample)) for v in image_size]
        log_polar_grid(8, 8, n_angles, n_radii, min_radius, max_radius)  # validates the grid
        self.rotation_scale_correlation = check_rotation_scale_correlation(rotation_scale_correlation)
        if rotation_scale_pooling not in ROTATION_SCALE_POOLING:
            raise ValueError(
                f"model.net.rotation_scale_pooling must be one of {', '.join(ROTATION_SCALE_POOLING)}, "
                f"got {rotation_scale_pooling!r}"
            )

        def unet(channels: int, width: int, levels: int) -> UNet:
            return UNet(channels, feature_channels, width, levels, norm, input_skip, upsample)

        rs_width = base_channels if rotation_scale_base_channels is None else rotation_scale_base_channels
        rs_levels = depth if rotation_scale_depth is None else rotation_scale_depth
        if image_size is not None:  # deeper U-Nets only halve 1x1 maps again, at a width that doubles each time
            side = min(image_size)
            rs_name = "depth" if rotation_scale_depth is None else "rotation_scale_depth"
            rs_side = side // rotation_scale_downsample
            for name, levels, pixels in (("depth", depth, side), (rs_name, rs_levels, rs_side)):
                most = max(int(math.log2(pixels)), 0)
                if levels > most:
                    raise ValueError(
                        f"model.net.{name}={levels} halves {pixels}x{pixels} maps {levels} times, but {most} "
                        f"halvings reach 1x1: at most {most} for image_size={list(image_size)}"
                    )
        rs_channels = in_channels * (rotation_scale_downsample**2 if rotation_scale_pooling == "space_to_depth" else 1)
        rs_template_width = rs_width if rotation_scale_template_channels is None else rotation_scale_template_channels
        relief = 1 if template_relief is None else 2  # the template's input channels, in images
        textured = {"template": texture_energy is not None, "source": texture_energy == "both"}
        rs_template_in = rs_channels * (relief + textured["template"])
        self.rs_template = unet(rs_template_in, rs_template_width, rs_levels)
        self.rs_source = unet(rs_channels * (1 + textured["source"]), rs_width, rs_levels)
        self.t_template = unet(in_channels * relief, base_channels, depth)
        self.t_source = unet(in_channels, base_channels, depth)
        self.rotation_scale_downsample = rotation_scale_downsample
        self.rotation_scale_pooling = rotation_scale_pooling
        self.template_relief = template_relief
        self.texture_energy = texture_energy
        self._textured = textured
        self.in_channels = in_channels
        self.image_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
        self.n_angles, self.n_radii = n_angles, n_radii
        self.min_radius, self.max_radius = min_radius, max_radius
        self.highpass, self.log_spectrum = highpass, log_spectrum
        self.radius_window = radius_window
        self.sigma, self.rotation_sigma = sigma, rotation_sigma
        self.temperature, self.rotation_temperature = temperature, rotation_temperature
        self.window = window
        self.scale_range = scale_range
        self.rotation_hypotheses = rotation_hypotheses
        self.hypothesis_ratio = hypothesis_ratio
        window_grid_shifts(8, 8, spectrum_window_grid, spectrum_window_step)  # validates them
        self.spectrum_window_grid = spectrum_window_grid
        self.spectrum_window_step = float(spectrum_window_step)
        self.rotation_views = rotation_views
        self.inference_radii = inference_radii
        self.inference_sigma = inference_sigma
        self.rotation_range = rotation_range
        self.half_turn_pass = half_turn_pass
        if isinstance(train_temperature, (int, float, str)):
            train_temperature = (train_temperature, train_temperature)
        check_sequence("train_temperature", train_temperature, 2, "one number or two")
        for t in train_temperature:
            check_number("train_temperature", t, low=0.0, low_open=True)
        log_t = torch.tensor([math.log(t) for t in train_temperature], dtype=torch.float32)
        if learnable_temperature:
            self.log_train_temperature = nn.Parameter(log_t)
        else:
            self.register_buffer("log_train_temperature", log_t)

    # ------------------------------------------------------------------ helpers
    @property
    def rotation_hypotheses(self) -> int:
        """Phase-1 peaks checked by phase 2 at inference (settable on a loaded model)."""
        return self._rotation_hypotheses

    @rotation_hypotheses.setter
    def rotation_hypotheses(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"rotation_hypotheses must be an integer >= 1, got {value!r}")
        self._rotation_hypotheses = value

    @property
    def hypothesis_ratio(self) -> float:
        """Second-to-first phase-1 peak ratio from which phase 2 checks a pair's further
        peaks (``0``: every pair; settable on a loaded model)."""
        return self._hypothesis_ratio

    @hypothesis_ratio.setter
    def hypothesis_ratio(self, value: float) -> None:
        self._hypothesis_ratio = check_number("hypothesis_ratio", value, low=0.0, high=1.0)

    @property
    def spectrum_window_grid(self) -> int:
        """Side of the grid of source spectrum windows phase 1 uses at inference (settable)."""
        return self._spectrum_window_grid

    @spectrum_window_grid.setter
    def spectrum_window_grid(self, value: int) -> None:
        window_grid_shifts(8, 8, value)  # validates it
        self._spectrum_window_grid = value

    @property
    def rotation_views(self) -> int:
        """Dihedral views whose phase-1 surfaces are averaged at inference (settable)."""
        return self._rotation_views

    @rotation_views.setter
    def rotation_views(self, value: int) -> None:
        self._rotation_views = check_views(value, self.image_size)

    @property
    def inference_radii(self) -> int | None:
        """Radii of phase 1's log-polar maps at inference (``None``: ``n_radii``; settable)."""
        return self._inference_radii

    @inference_radii.setter
    def inference_radii(self, value: int | None) -> None:
        if value is not None:
            if isinstance(value, bool) or not isinstance(value, int) or value < 2:
                raise ValueError(f"inference_radii must be an integer >= 2 or None, got {value!r}")
        self._inference_radii = value

    @property
    def inference_sigma(self) -> float | None:
        """Blur (pixels) of phase 2's surfaces at inference (``None``: ``sigma``; settable)."""
        return self._inference_sigma

    @inference_sigma.setter
    def inference_sigma(self, value: float | None) -> None:
        self._inference_sigma = None if value is None else check_number("inference_sigma", value, low=0.0)

    @property
    def scale_range(self) -> tuple[float, float] | None:
        """The scales ``[low, high]`` phase 1 searches, or ``None`` for all (settable on a
        loaded model)."""
        return self._scale_range

    @scale_range.setter
    def scale_range(self, value: tuple[float, float] | list[float] | None) -> None:
        self._scale_range = check_scale_range(value)

    @property
    def rotation_range(self) -> tuple[float, float] | None:
        """The known range of rotations ``[low, high]`` (degrees) used at inference, or ``None``."""
        return self._rotation_range

    @rotation_range.setter
    def rotation_range(self, value: tuple[float, float] | list[float] | None) -> None:
        self._rotation_range = check_rotation_range(value)

    @property
    def half_turn_pass(self) -> str:
        """Whose half-turn gets its own phase-2 source U-Net pass at inference (settable on
        a loaded model): ``"winner"`` or ``"every"`` candidate (:data:`HALF_TURN_PASSES`)."""
        return self._half_turn_pass

    @half_turn_pass.setter
    def half_turn_pass(self, value: str) -> None:
        if value not in HALF_TURN_PASSES:
            raise ValueError(f"half_turn_pass must be one of {', '.join(HALF_TURN_PASSES)}, got {value!r}")
        self._half_turn_pass = value

    @property
    def unet_dtype(self) -> str:
        """Dtype of the four U-Nets' weights: ``float32`` or, for inference, ``bfloat16``
        (settable). Features are cast back to the input's dtype, so the phase correlation
        always runs in float32. A bfloat16 ``paper`` U-Net pass is 1.4x faster on an H200,
        and bfloat16 moved s2d's accuracy by at most a point (README, Benchmarks). Train in
        float32; casting back keeps the bfloat16-rounded weights (reload the checkpoint)."""
        return str(self.t_source.head.weight.dtype).removeprefix("torch.")

    @unet_dtype.setter
    def unet_dtype(self, value: str) -> None:
        if value not in UNET_DTYPES:
            raise ValueError(f"unet_dtype must be one of {', '.join(UNET_DTYPES)}, got {value!r}")
        for name in (n for names in PHASE_UNETS.values() for n in names):
            getattr(self, name).to(getattr(torch, value))

    def spectrum_window_shifts(self, height: int, width: int, grid: int) -> list[tuple[int, int]]:
        """Circular shifts ``(rows, cols)`` of a ``height x width`` feature map for a
        ``grid x grid`` set of windows (``(0, 0)`` first; see :func:`~dpcn.estimator.window_grid_shifts`)."""
        return window_grid_shifts(height, width, grid, self.spectrum_window_step)

    @property
    def radius_step(self) -> float:
        """ln-scale per log-polar column."""
        return log_radius_step(self.n_radii, self.min_radius, self.max_radius)

    @property
    def train_temperature(self) -> Tensor:
        """``(2,)`` softmax temperatures of the losses: rotation/scale, translation."""
        return self.log_train_temperature.exp()

    def check_inputs(self, template: Tensor, source: Tensor) -> None:
        """Raise ``ValueError`` naming the problem for inputs this model cannot match:
        ``(B, C, H, W)`` templates and sources of the built size and channels, or one
        ``(1, C, H, W)`` template against ``B`` sources."""
        check_pair(template, source, min_size=8 * self.rotation_scale_downsample, one_to_many=True)
        if template.shape[1] != self.in_channels:
            raise ValueError(f"this model takes {self.in_channels}-channel images, got {template.shape[1]} channels")
        if self.image_size is not None and tuple(template.shape[-2:]) != self.image_size:
            h, w = self.image_size
            raise ValueError(
                f"this model was built for {h}x{w} images, got {template.shape[-2]}x{template.shape[-1]}; "
                f"resize or crop the inputs to {h}x{w} (scale the translation back by the same factor)"
            )

    # ------------------------------------------------------------------ phases
    def rotation_scale_input(self, image: Tensor) -> Tensor:
        """An image (or any map) shrunk to phase 1's resolution by a box average:
        ``(B, C, ceil(H / d), ceil(W / d))``."""
        d = self.rotation_scale_downsample
        return F.avg_pool2d(image, d, ceil_mode=True) if d > 1 else image

    def template_unet_input(self, template: Tensor) -> Tensor:
        """What the template's U-Nets take at full size: ``(B, C, H, W)``, or with
        ``template_relief`` the image and its :func:`local_relief`, ``(B, 2 C, H, W)``."""
        if self.template_relief is None:
            return template
        return torch.cat([template, local_relief(template, self.template_relief)], dim=1)

    def with_texture(self, image: Tensor, unet_input: Tensor, side: str) -> Tensor:
        """``unet_input`` with the :func:`local_texture` of ``image`` beside it where
        ``texture_energy`` covers ``side`` (``"template"`` or ``"source"``), else as it is."""
        if not self._textured[side]:
            return unet_input
        return torch.cat([unet_input, local_texture(image)], dim=1)

    def rotation_scale_unet_input(self, image: Tensor) -> Tensor:
        """What the phase-1 U-Nets take: ``(B, C, H, W)`` shrunk by ``rotation_scale_pooling``
        to ``(B, C', ceil(H / d), ceil(W / d))``, ``C' = C`` (average) or ``C * d * d``
        (space to depth; edge rows/columns repeated up to a multiple of ``d``)."""
        d = self.rotation_scale_downsample
        if d == 1 or self.rotation_scale_pooling == "average":
            return self.rotation_scale_input(image)
        pad_h, pad_w = -image.shape[-2] % d, -image.shape[-1] % d
        if pad_h or pad_w:
            image = F.pad(image, (0, pad_w, 0, pad_h), mode="replicate")
        return F.pixel_unshuffle(image, d)

    def nearest_window_shifts(self, tx: Tensor, ty: Tensor, size: tuple[int, int]) -> Tensor:
        """Per pair, the circular shift ``(rows, cols)`` of ``size`` phase-1 maps that puts the
        source's spectrum window on the point of :attr:`spectrum_window_grid`'s grid nearest
        to where the template's centre lies in the source (``tx``, ``ty``: ``(B,)`` true
        translation in image pixels): the window the inference grid would ideally pick.
        ``(B, 2)`` integers; all zero for a grid of 1."""
        grid = torch.tensor(self.spectrum_window_shifts(*size, self.spectrum_window_grid), device=tx.device)
        # The template's centre is at (cx + tx, cy + ty) in the source: rolling phase 1's maps
        # by -t / d would bring it to their centre; take the grid's shift nearest to that.
        wanted = -torch.stack([ty, tx], dim=1).detach() / self.rotation_scale_downsample
        return grid[torch.cdist(wanted.to(torch.float64), grid.to(torch.float64)).argmin(dim=1)]

    def rotation_scale_template_features(self, template: Tensor, views: int = 1) -> Tensor:
        """The template's phase-1 features: ``(B, C, H, W) -> (views * B, C', H / d, W / d)``
        for its ``views`` dihedral views, view-major."""
        template_views = dihedral_views(template, views)
        template_in = self.with_texture(template_views, self.template_unet_input(template_views), "template")
        return self.rs_template(self.rotation_scale_unet_input(template_in))

    def template_features(self, template: Tensor) -> TemplateFeatures:
        """The template's features for both phases with this model's ``rotation_views``:
        what :meth:`forward` computes of a template, for reuse against many sources."""
        views = self.rotation_views
        translation = self.t_template(self.template_unet_input(template))
        return TemplateFeatures(self.rotation_scale_template_features(template, views), translation, views)

    def rotation_scale(
        self,
        template: Tensor,
        source: Tensor,
        hypotheses: int = 1,
        window_grid: int = 1,
        views: int = 1,
        source_shifts: Tensor | None = None,
        radii: int | None = None,
        template_features: Tensor | None = None,
    ) -> tuple[RotationScale, dict[str, Tensor]]:
        """Phase 1: features, then rotation (mod 180 degrees) and scale (and the next
        strongest peaks, ``hypotheses`` in all, as ``candidate_*``), with the source spectrum
        under a ``window_grid x window_grid`` grid of windows and the surfaces of ``views``
        dihedral views of the pair averaged.

        ``source_shifts`` (training, with one window and one view): ``(B, 2)`` integer circular
        shifts ``(rows, cols)`` of each pair's source features before the spectrum, which moves
        its window (see :meth:`nearest_window_shifts`). ``radii``: columns of the log-polar
        maps (``None``: ``n_radii``, what training uses). ``template_features``: the
        template's (:meth:`rotation_scale_template_features` with ``views``) if already
        computed.

        The features are ``(B, C, H / d, W / d)`` with ``d = rotation_scale_downsample`` (of
        the first view, the pair as given), unshifted.
        """
        rs_template = template_features
        if rs_template is None:
            rs_template = self.rotation_scale_template_features(template, views)
        source_views = dihedral_views(source, views)
        source_in = self.with_texture(source_views, source_views, "source")
        rs_source = self.rs_source(self.rotation_scale_unet_input(source_in))
        windowed = rs_source
        if source_shifts is not None:
            if views != 1 or window_grid != 1 or source_shifts.shape != (rs_source.shape[0], 2):
                raise ValueError("source_shifts takes one (rows, cols) shift per pair, with one view and one window")
            shifts = source_shifts.tolist()
            windowed = torch.stack(
                [torch.roll(f, tuple(s), dims=(-2, -1)) for f, s in zip(rs_source, shifts, strict=True)]
            )
        rs = self.rotation_scale_from_features(rs_template, windowed, hypotheses, window_grid, views, radii)
        batch = template.shape[0]
        return rs, {"rs_template": rs_template[:batch], "rs_source": rs_source[:batch]}

    def rotation_scale_from_features(
        self,
        template_features: Tensor,
        source_features: Tensor,
        hypotheses: int = 1,
        window_grid: int = 1,
        views: int = 1,
        radii: int | None = None,
    ) -> RotationScale:
        """Phase 1's estimate from ``(B, C, h, w)`` feature maps (``(views * B, C, h, w)``:
        those of dihedral views), with this model's log-polar and peak settings (also for
        maps from elsewhere, e.g. to compare extractors); ``radii`` replaces ``n_radii``."""
        return estimate_rotation_scale(
            template_features,
            source_features,
            n_angles=self.n_angles,
            n_radii=self.n_radii if radii is None else radii,
            min_radius=self.min_radius,
            max_radius=self.max_radius,
            highpass=self.highpass,
            log_spectrum=self.log_spectrum,
            sigma=self.rotation_sigma,
            temperature=self.rotation_temperature,
            window=self.window,
            scale_range=self.scale_range,
            hypotheses=hypotheses,
            source_shifts=self.spectrum_window_shifts(*source_features.shape[-2:], window_grid),
            views=views,
            correlation=self.rotation_scale_correlation,
            radius_window=self.radius_window,
        )

    def translation_turns(
        self,
        template: Tensor,
        unwarped_source: Tensor,
        angle: Tensor,
        scale: Tensor,
        half_turn_too: bool = True,
        template_features: Tensor | None = None,
        sigma: float | None = None,
        turn_features: bool = False,
    ) -> tuple[list[Translation], Tensor, tuple[Tensor, ...]]:
        """Phase 2 per half-turn hypothesis, without choosing: the source as un-warped and,
        with ``half_turn_too``, turned by half a turn (its own source U-Net pass: a CNN is not
        equivariant to the turn, so this is what the half-turn check compares; with
        ``turn_features``, the upright pass's features turned instead, which picks the turn
        about as well for half the passes but places a turned peak up to a pixel off).

        Args:
            template: ``(B, C, H, W)``.
            unwarped_source, angle, scale: ``(B * K, C, H, W)``, ``(B * K,)``, ``(B * K,)``,
                ``K`` candidates per pair, pair-major.
            template_features: the template's phase-2 features if already computed.
            sigma: the surfaces' blur in pixels (``None``: the model's ``sigma``).
            turn_features: the turned hypothesis from the upright features turned (no
                second source U-Net pass).

        Returns:
            one :class:`Translation` ``(B * K,)`` per hypothesis (upright first; the second's
            angle is ``angle + 180``), the template's phase-2 features ``(B, C', H, W)`` and
            the source's per hypothesis.
        """
        k = unwarped_source.shape[0] // template.shape[0]
        ft = self.t_template(self.template_unet_input(template)) if template_features is None else template_features
        if half_turn_too and turn_features:
            upright = self.t_source(unwarped_source)
            fs_all: tuple[Tensor, ...] = (upright, half_turn(upright))
        else:
            turns = (unwarped_source, half_turn(unwarped_source)) if half_turn_too else (unwarped_source,)
            fs_all = self.t_source(torch.cat(turns)).chunk(len(turns))
        ft_k = ft.repeat_interleave(k, dim=0) if k > 1 else ft
        results = [
            self.translation_peak(ft_k, fs, angle + 180.0 * turn, scale, sigma) for turn, fs in enumerate(fs_all)
        ]
        return results, ft, fs_all

    def translation_peak(
        self, template_features: Tensor, source_features: Tensor, angle: Tensor, scale: Tensor, sigma: float | None
    ) -> Translation:
        """Phase 2's correlation of given features, ``(N, C', H, W)`` each, for the pose
        ``angle``/``scale`` ``(N,)`` they were un-warped by (``sigma``: the surfaces' blur in
        pixels, ``None``: the model's ``sigma``)."""
        blur = self.sigma if sigma is None else sigma
        return estimate_translation(
            template_features,
            source_features,
            angle,
            scale,
            resolve_180=False,
            sigma=blur,
            temperature=self.temperature,
            window=self.window,
        )

    def translation(
        self,
        template: Tensor,
        unwarped_source: Tensor,
        angle: Tensor,
        scale: Tensor,
        resolve_180: bool = True,
        valid: Tensor | None = None,
        rotation_range: tuple[float, float] | None = None,
        template_features: Tensor | None = None,
        sigma: float | None = None,
    ) -> tuple[Translation, dict[str, Tensor], Tensor]:
        """Phase 2 on sources already un-warped by ``angle``/``scale``; the strongest
        translation peak over the candidates wins.

        Args:
            template: ``(B, C, H, W)``.
            unwarped_source, angle, scale: ``K`` candidates per pair, pair-major:
                ``(B * K, C, H, W)``, ``(B * K,)``, ``(B * K,)`` (``K = 1``: one un-warp each).
            resolve_180: also try each candidate turned by half a turn (one more source U-Net
                pass, batched with the first); the angle of the winner says which.
            valid: ``(B, K)`` candidates allowed to win (``None``: all).
            rotation_range: with ``resolve_180``, a turn whose angle lies further outside this
                range than the other turn's cannot win.
            template_features: the template's phase-2 features if already computed.
            sigma: the surfaces' blur in pixels (``None``: the model's ``sigma``).

        Returns:
            the winning :class:`Translation` ``(B,)``, the phase-2 features of the winner, and
            ``(B,)`` the index of the winning candidate.
        """
        ft, winner, _ = self._translation_picks(
            template,
            unwarped_source,
            angle,
            scale,
            resolve_180,
            valid,
            rotation_range,
            template_features,
            sigma,
            turn_features=False,
        )
        return winner.tr, {"t_template": ft, "t_source": winner.t_source}, winner.choice

    def _translation_picks(
        self,
        template: Tensor,
        unwarped_source: Tensor,
        angle: Tensor,
        scale: Tensor,
        resolve_180: bool,
        valid: Tensor | None,
        rotation_range: tuple[float, float] | None,
        template_features: Tensor | None,
        sigma: float | None,
        turn_features: bool,
    ) -> tuple[Tensor, _Pick, _Pick | None]:
        """:meth:`translation`'s work: the template's phase-2 features, the strongest allowed
        candidate over both turns and, with ``turn_features`` (the turns compared on the
        upright features turned, :meth:`translation_turns`), the strongest upright one, which
        :meth:`forward` falls back on should the winner's own turned pass peak lower."""
        batch = template.shape[0]
        k = unwarped_source.shape[0] // batch
        if k < 1 or unwarped_source.shape[0] != batch * k:
            raise ValueError(f"{unwarped_source.shape[0]} un-warped sources for {batch} templates (need B * K)")
        results, ft, fs_all = self.translation_turns(
            template, unwarped_source, angle, scale, resolve_180, template_features, sigma, turn_features
        )
        turns = len(results)

        def candidates(values: list[Tensor]) -> Tensor:  # (B * K, ...) per turn -> (B, K * turns, ...)
            return torch.stack([v.view(batch, k, *v.shape[1:]) for v in values], dim=2).flatten(1, 2)

        score = candidates([r.confidence for r in results])
        allowed = None if valid is None else valid.repeat_interleave(turns, dim=1)
        if rotation_range is not None and turns == 2:
            upright, turned = (outside_rotation_range(r.angle, rotation_range) for r in results)
            nearest = torch.minimum(upright, turned)
            turn_ok = candidates([upright == nearest, turned == nearest])
            allowed = turn_ok if allowed is None else allowed & turn_ok
        if allowed is not None:
            score = score.masked_fill(~allowed, -torch.inf)
        rows = torch.arange(batch, device=score.device)
        per_candidate = [candidates([getattr(r, field) for r in results]) for field in _TRANSLATION_FIELDS]
        sources, unwarped = candidates(list(fs_all)), unwarped_source.view(batch, k, *unwarped_source.shape[1:])

        def pick(scores: Tensor) -> _Pick:
            choice = scores.argmax(dim=1)
            candidate = torch.div(choice, turns, rounding_mode="floor")
            tr = Translation(*(values[rows, choice] for values in per_candidate))
            return _Pick(
                tr,
                sources[rows, choice],
                candidate,
                choice % turns == 1,
                unwarped[rows, candidate],
                scores[rows, choice],
            )

        upright_only = None
        if turn_features and turns == 2:
            upright_only = pick(
                score.masked_fill(torch.arange(score.shape[1], device=score.device) % 2 == 1, -torch.inf)
            )
        return ft, pick(score), upright_only

    def forward(
        self, template: Tensor, source: Tensor, template_features: TemplateFeatures | None = None
    ) -> DPCNOutput:
        """End to end, no ground truth: ``(B, C, H, W) x 2 -> DPCNOutput``; a ``(1, C, H, W)``
        template is matched against each of the ``B`` sources, its U-Nets run once.

        ``template_features``: the template's :meth:`template_features`, if already computed
        (e.g. once for a stream of source batches).
        """
        self.check_inputs(template, source)
        k = self.rotation_hypotheses
        with inputs_checked():
            if template_features is None:
                template_features = self.template_features(template)
            self._check_template_features(template, template_features)
            if template.shape[0] != source.shape[0]:  # one template, many sources
                template = template.expand(source.shape[0], -1, -1, -1)
                template_features = template_features.expand(source.shape[0])
            rs, features = self.rotation_scale(
                template,
                source,
                k,
                self.spectrum_window_grid,
                self.rotation_views,
                radii=self.inference_radii,
                template_features=template_features.rotation_scale,
            )
            angle = rs.candidate_angle  # (B, K)
            known = self.rotation_range
            settled = known is not None and known[1] - known[0] <= 180.0
            if settled:  # the range picks the half-turn: phase 2 runs on that one alone
                angle = angle + 180.0 * choose_half_turn(angle, known).to(angle.dtype)
            valid = torch.isfinite(rs.candidate_score)
            # "winner": the turns compared on the upright pass's features turned, then a turned
            # winner's own pass (below), where "every" gives each candidate's turn its own pass.
            lazy = not settled and not self.training and self.half_turn_pass == "winner"

            def phase2(rows: Tensor | slice, first: int, stop: int, ft: Tensor) -> tuple[_Pick, _Pick | None]:
                """Phase 2 on candidates ``first:stop`` of the pairs ``rows``: the winner and,
                when lazy, the strongest upright candidate (candidate indices from ``first``)."""
                n = stop - first
                candidates = source[rows].repeat_interleave(n, dim=0) if n > 1 else source[rows]
                a, s = angle[rows, first:stop].flatten(), rs.candidate_scale[rows, first:stop].flatten()
                unwarped = unwarp_rotation_scale(candidates, a, s)
                allowed, blur = valid[rows, first:stop], self.inference_sigma
                _, *picks = self._translation_picks(
                    template[rows], unwarped, a, s, not settled, allowed, known, ft, blur, lazy
                )
                return tuple(None if p is None else p._replace(choice=p.choice + first) for p in picks)

            ft = template_features.translation
            if k == 1 or self.hypothesis_ratio == 0:  # every pair, all its candidates at once
                winner, upright = phase2(slice(None), 0, k, ft)
            else:  # every pair's first peak, then the further peaks of the ambiguous pairs
                winner, upright = phase2(slice(None), 0, 1, ft)
                rows = self.ambiguous_pairs(rs.candidate_score).nonzero().squeeze(1)
                if len(rows):
                    further, further_upright = phase2(rows, 1, k, ft[rows])
                    winner = _merge_picks(winner, rows, further, further.tr.confidence > winner.tr.confidence[rows])
                    if upright is not None:
                        upright = _merge_picks(
                            upright, rows, further_upright, further_upright.score > upright.score[rows]
                        )
            rows = winner.turned.nonzero().squeeze(1) if lazy else None
            if rows is not None and len(rows):  # a turned winner's own pass places its peak
                fs = self.t_source(half_turn(winner.unwarped[rows]))
                chosen = winner.choice[rows]
                placed = self.translation_peak(
                    ft[rows], fs, winner.tr.angle[rows], rs.candidate_scale[rows, chosen], self.inference_sigma
                )
                exact = _Pick(placed, fs, chosen, winner.turned[rows], winner.unwarped[rows], placed.confidence)
                holds = placed.confidence >= upright.score[rows]  # else the turned features erred
                winner = _merge_picks(winner, rows, exact, holds)
                winner = _merge_picks(winner, rows, _pick_rows(upright, rows), ~holds)
        tr, choice = winner.tr, winner.choice
        scale = rs.candidate_scale[torch.arange(template.shape[0], device=choice.device), choice]
        t_features = {"t_template": ft, "t_source": winner.t_source}
        unwarped = winner.unwarped
        pose = Pose(tr.tx, tr.ty, wrap_angle(tr.angle), scale, tr.confidence)
        return DPCNOutput(pose, rs, tr, unwarped, {**features, **t_features})

    def _check_template_features(self, template: Tensor, features: TemplateFeatures) -> None:
        """``features`` must be this model's :meth:`template_features` of ``template``: its
        views, batch, size and feature channels (of both phases)."""
        batch, size = template.shape[0], tuple(template.shape[-2:])
        channels = (self.rs_template.head.out_channels, self.t_template.head.out_channels)
        d = self.rotation_scale_downsample
        rs_shape = (self.rotation_views * batch, channels[0], -(-size[0] // d), -(-size[1] // d))
        fits = (
            features.views == self.rotation_views
            and tuple(features.translation.shape) == (batch, channels[1], *size)
            and tuple(features.rotation_scale.shape) == rs_shape
        )
        if not fits:
            got = features.translation.shape
            raise ValueError(
                f"template_features are of {got[0]} template(s) of {got[-2]}x{got[-1]} with {features.views} "
                f"view(s) and {got[1]} channels; these inputs need {batch} of {size[0]}x{size[1]} with "
                f"rotation_views={self.rotation_views} and {channels[1]} channels: compute them with this "
                "model's template_features(template) after any change"
            )

    def ambiguous_pairs(self, candidate_score: Tensor) -> Tensor:
        """``(B,)`` the pairs whose second phase-1 peak reaches ``hypothesis_ratio`` times
        their first (``candidate_score``: ``(B, K)``, strongest first)."""
        if candidate_score.shape[1] < 2:
            return torch.zeros(candidate_score.shape[0], dtype=torch.bool, device=candidate_score.device)
        second = candidate_score[:, 1]
        return torch.isfinite(second) & (second >= self.hypothesis_ratio * candidate_score[:, 0])

    @torch.no_grad()
    def match(self, template: Tensor, source: Tensor, chunk_size: int | None = None) -> Pose:
        """Inference: the pose mapping ``template`` onto ``source`` (``(B,)`` fields).

        ``(B, C, H, W)`` tensors, moved to the model's device; or anything
        :func:`dpcn.io.prepare_pair` reads (``(H, W)`` / ``(H, W, C)`` arrays, image paths),
        converted to the model's channels as the data sets convert images (colour to grey for a
        grey model, grey repeated for a colour one).

        Large batches run ``chunk_size`` pairs at a time (default: 4 on CPUs, ``4 //
        rotation_views`` with several views, all at once elsewhere): on a CPU the
        full-resolution feature maps of bigger batches fall out of the cache, and the time per
        pair grows instead of shrinking (`tiny` on 2 cores, 32 test pairs, ``python
        benchmarks/bench_inference.py --chunks``: 30.0 ms per pair in chunks of 4, 36.9 in
        chunks of 8, 52.6 in chunks of 16; with 4 views 89.7 one at a time, 94.4 in twos).

        One template against many sources (a ``(1, C, H, W)`` template, or a batch expanded
        from one, as :func:`dpcn.io.prepare_pair` makes it): the template's U-Nets run once
        for all the chunks. A pair whose template or source is constant gets confidence 0,
        with a warning (:func:`dpcn.io.flag_featureless`).
        """
        device = self.rs_template.head.weight.device
        if not is_tensor_pair(template, source):
            template, source = prepare_pair(template, source, device, channels=self.in_channels)
        template, source = template.to(device), source.to(device)
        if chunk_size is None:
            chunk_size = max(1, 4 // self.rotation_views) if device.type == "cpu" else source.shape[0]
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        # Eval mode for the call, each module's own mode back after it: a frozen U-Net of a
        # training model stays in eval, and a model already in eval costs no walk of setattr calls.
        training = [module for module in self.modules() if module.training]
        for module in training:
            module.training = False
        try:
            self.check_inputs(template, source)  # the whole batch once; chunks check shapes only
            if copies_of_one(template):  # copies of one template
                template = template[:1]
            sources = source.split(chunk_size)
            shared = template.shape[0] == 1
            templates = [template] * len(sources) if shared else template.split(chunk_size)
            with inputs_checked():
                features = self.template_features(template) if shared else None
                pose = Pose.cat([self(t, s, features).pose for t, s in zip(templates, sources, strict=True)])
        finally:
            for module in training:
                module.training = True
        return flag_featureless(pose, template, source, stacklevel=4)  # past torch.no_grad's wrapper
