"""The two-stage Fourier-Mellin pose estimator, differentiable end to end.

Stage 1: magnitude spectra -> log-polar maps -> phase correlation -> rotation and scale
(modulo 180 degrees). Stage 2: the source is un-rotated/un-scaled by that estimate (kornia
warp), a second phase correlation gives the translation; both the angle and the angle + 180
degrees are tried there and the stronger peak wins, so the full 360 degrees are recovered.

The stages take arbitrary ``(B, C, H, W)`` inputs, so the same code runs on raw pixels (the
classical estimator, :class:`PhaseCorrelationEstimator`) and on learned feature maps (DPCN).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import kornia
import torch
from torch import Tensor, nn

from ._validate import check_bool, check_ints, check_number, check_sequence
from .ops._checks import check_pair, copies_of_one, full_precision, inputs_checked
from .ops.correlation import correlation_surface, cross_power_spectrum, phase_correlation_1d
from .ops.logpolar import log_polar, log_polar_grid, log_radius_step
from .ops.soft_argmax import local_maxima2d, soft_argmax2d
from .ops.spectrum import apodization_window, magnitude_spectrum
from .pose import Pose, pose_to_matrix, wrap_angle

__all__ = [
    "RotationScale",
    "Translation",
    "estimate_rotation_scale",
    "unwarp_rotation_scale",
    "estimate_translation",
    "window_grid_shifts",
    "dihedral_views",
    "DIHEDRAL_VIEWS",
    "check_rotation_range",
    "outside_rotation_range",
    "choose_half_turn",
    "ROTATION_SCALE_CORRELATIONS",
    "log_polar_correlation",
    "PhaseCorrelationEstimator",
]

# (quarter turns, left-right mirror) of each view, in the order `dihedral_views` stacks them.
DIHEDRAL_VIEWS: tuple[tuple[int, bool], ...] = tuple((turns, mirror) for turns in range(4) for mirror in (False, True))


@dataclass
class RotationScale:
    """Output of :func:`estimate_rotation_scale` (all ``(B,)`` unless noted).

    ``angle`` is in ``[-90, 90)`` degrees: the magnitude spectrum cannot tell ``angle`` from
    ``angle + 180``. ``surface`` is the ``(B, n_angles, n_radii)`` log-polar correlation.
    ``candidate_angle``, ``candidate_scale``, ``candidate_score`` are ``(B, K)``: the ``K``
    highest separate peaks of the surface (``hypotheses``), strongest first; the first is
    ``angle``/``scale`` (a score of ``-inf`` marks a missing peak).
    """

    angle: Tensor
    scale: Tensor
    confidence: Tensor
    surface: Tensor
    log_polar_template: Tensor
    log_polar_source: Tensor
    candidate_angle: Tensor
    candidate_scale: Tensor
    candidate_score: Tensor


@dataclass
class Translation:
    """Output of :func:`estimate_translation` (all ``(B,)`` unless noted).

    ``angle`` is the full-turn angle (the stage-1 angle or that plus 180 degrees, whichever
    correlates better); ``surface`` is the ``(B, H, W)`` correlation of the winner.
    """

    tx: Tensor
    ty: Tensor
    angle: Tensor
    confidence: Tensor
    surface: Tensor


# How stage 1 correlates two log-polar maps: "joint", the paper's 2-D phase correlation; or
# "decoupled", DPCN++'s (Chen et al. 2022) 1-D phase correlations of the maps' angle and
# log-radius profiles.
ROTATION_SCALE_CORRELATIONS = ("joint", "decoupled")


def check_rotation_scale_correlation(value: str) -> str:
    """Validate a stage-1 correlation name (:data:`ROTATION_SCALE_CORRELATIONS`)."""
    if value not in ROTATION_SCALE_CORRELATIONS:
        raise ValueError(
            f"rotation_scale_correlation must be one of {', '.join(ROTATION_SCALE_CORRELATIONS)}, got {value!r}"
        )
    return value


def log_polar_correlation(template: Tensor, sources: Tensor, sigma: float = 0.0, correlation: str = "joint") -> Tensor:
    """Stage 1's correlation surface of log-polar maps.

    Args:
        template: ``(B, C, A, R)`` log-polar maps (angle rows, log-radius columns).
        sources: ``(B, C, A, R)`` or ``(N, B, C, A, R)`` (several sources per template).
        sigma: Gaussian blur of the surface, in bins.
        correlation: ``joint``: the 2-D phase correlation of the maps (the paper). A peak
            needs the maps to agree bin by bin under one shift. ``decoupled``: the mean of
            two 1-D phase correlations, of the maps summed over radius (the angle profiles:
            rotation only) and summed over angle (the log-radius profiles: scale only; less
            their mean and under a Hann window, the axis not being periodic), as in DPCN++.
            Rotation is then found whatever the scale and vice versa; the surface is
            separable, so its softmax is the product of the two 1-D softmaxes and the
            one-peak KL on it is the sum of the two 1-D ones.

    Returns:
        ``(B, A, R)`` or ``(N * B, A, R)`` surface, circularly centred as
        :func:`dpcn.ops.correlation_surface`; a perfect match peaks at 1 either way.
    """
    check_rotation_scale_correlation(correlation)
    n_angles, n_radii = template.shape[-2:]
    if correlation == "joint":
        cross = cross_power_spectrum(template, sources)
        return correlation_surface(cross.flatten(0, -3), (n_angles, n_radii), sigma)
    if template.shape[-2:] != sources.shape[-2:] or template.shape[-4:-2] != sources.shape[-4:-2]:
        raise ValueError(f"log-polar maps differ: template {tuple(template.shape)}, sources {tuple(sources.shape)}")
    # The log-radius axis is not periodic, and a power-law spectrum (natural images: ~1/f)
    # gives every image nearly the same trend along it, which a circular correlation would
    # match at zero shift: the radius profiles lose their mean and get a Hann window.
    hann = torch.hann_window(n_radii, periodic=False, device=template.device, dtype=template.dtype)
    profiles = []
    for summed, window in ((-1, None), (-2, hann)):
        a, b = template.sum(summed), sources.sum(summed)
        a, b = a - a.mean(dim=-1, keepdim=True), b - b.mean(dim=-1, keepdim=True)
        if window is not None:
            a, b = a * window, b * window
        profiles.append(phase_correlation_1d(a, b, sigma).flatten(0, -2))  # (N * B, L)
    return 0.5 * (profiles[0][:, :, None] + profiles[1][:, None, :])


def _scale_mask(n_radii: int, step: float, scale_range: tuple[float, float] | None, device, dtype) -> Tensor | None:
    """Additive ``(1, 1, n_radii)`` mask excluding log-radius shifts outside ``scale_range``."""
    scale_range = check_scale_range(scale_range)
    if scale_range is None:
        return None
    lo, hi = scale_range
    shifts = torch.arange(n_radii, device=device, dtype=dtype) - n_radii // 2
    scales_log = -shifts * step  # column -> ln(scale)
    ok = (scales_log >= math.log(lo) - step) & (scales_log <= math.log(hi) + step)
    # Finite (correlation values are <= 1): -inf would turn into NaN gradients downstream.
    return torch.where(ok, 0.0, -1.0e4).to(dtype)[None, None, :]


def window_grid_shifts(height: int, width: int, grid: int = 1, step: float = 0.125) -> list[tuple[int, int]]:
    """Circular shifts ``(rows, cols)`` of a ``height x width`` map that centre its spectrum
    window on a ``grid x grid`` set of points ``step`` of the side apart (``(0, 0)`` first):
    the ``source_shifts`` of :func:`estimate_rotation_scale`."""
    if isinstance(grid, bool) or not isinstance(grid, int) or grid < 1 or grid % 2 == 0:
        raise ValueError(f"spectrum_window_grid must be an odd integer >= 1, got {grid!r}")
    if isinstance(step, bool) or not isinstance(step, (int, float)) or not 0.0 < step < 0.5:
        raise ValueError(f"spectrum_window_step must be in (0, 0.5) of the image side, got {step!r}")
    dy, dx = round(step * height), round(step * width)
    steps = sorted(range(-(grid // 2), grid // 2 + 1), key=abs)
    return [(i * dy, j * dx) for i in steps for j in steps]


def dihedral_views(image: Tensor, views: int) -> Tensor:
    """The first ``views`` of :data:`DIHEDRAL_VIEWS` of each image, view-major:
    ``(B, C, H, W) -> (views * B, C, H, W)``.

    View ``(k, mirror)`` is ``image`` turned by ``k`` quarter turns (``torch.rot90``), then
    mirrored left-right. The same view of both images of a pair keeps their relative scale; a
    turn keeps their relative rotation and a mirror negates it. Views 1-2 (identity, mirror)
    take any size; quarter turns (``views > 2``) need square images.
    """
    check_views(views, image.shape[-2:])
    stacked = []
    for turns, mirror in DIHEDRAL_VIEWS[:views]:
        view = torch.rot90(image, turns, dims=(-2, -1)) if turns else image
        stacked.append(torch.flip(view, dims=(-1,)) if mirror else view)
    return torch.cat(stacked) if views > 1 else image


def check_views(views: int, size: Sequence[int] | None = None) -> int:
    """Validate a number of dihedral views (1-8; ``> 2`` only for square ``size``)."""
    if isinstance(views, bool) or not isinstance(views, int) or not 1 <= views <= len(DIHEDRAL_VIEWS):
        raise ValueError(f"rotation_views must be an integer from 1 to {len(DIHEDRAL_VIEWS)}, got {views!r}")
    if views > 2 and size is not None and size[0] != size[1]:
        raise ValueError(
            f"rotation_views > 2 turns the images by quarter turns: needs square images, got {size[0]}x{size[1]}"
        )
    return views


def check_scale_range(scale_range: object) -> tuple[float, float] | None:
    """Validate the scales stage 1 searches, ``[low, high]`` (source size over template size):
    two finite numbers with ``0 < low <= 1 <= high``; ``None`` (every scale the log-polar maps
    hold) passes."""
    if scale_range is None:
        return None
    check_sequence("scale_range", scale_range, 2, "a [low, high] pair")
    low, high = (check_number("scale_range", v, low=0.0, low_open=True) for v in scale_range)
    if not low <= 1.0 <= high:
        raise ValueError(f"scale_range must be [low, high] with 0 < low <= 1 <= high, got {scale_range!r}")
    return low, high


def check_rotation_range(rotation_range: object) -> tuple[float, float] | None:
    """Validate a known range of rotations ``[low, high]`` in degrees (the pose convention's
    angle): two finite numbers with ``0 < high - low <= 360``; ``None`` (no prior) passes."""
    if rotation_range is None:
        return None
    ok = isinstance(rotation_range, Sequence) and not isinstance(rotation_range, str) and len(rotation_range) == 2
    values = list(rotation_range) if ok else []
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values)
    if not ok or not 0 < values[1] - values[0] <= 360:
        raise ValueError(
            f"rotation_range must be [low, high] in degrees with 0 < high - low <= 360, got {rotation_range!r}"
        )
    return float(values[0]), float(values[1])


def outside_rotation_range(angle: Tensor, rotation_range: tuple[float, float]) -> Tensor:
    """Degrees by which each ``angle`` lies outside ``rotation_range`` (0 inside; circular)."""
    low, high = rotation_range
    past_low = torch.remainder(angle - low, 360.0)  # [0, 360): how far round from low
    beyond = past_low - (high - low)
    return torch.where(beyond <= 0, torch.zeros_like(angle), torch.minimum(beyond, 360.0 - past_low))


def choose_half_turn(
    angle: Tensor,
    rotation_range: tuple[float, float] | None,
    upright_score: Tensor | None = None,
    turned_score: Tensor | None = None,
) -> Tensor:
    """Whether each pose is ``angle + 180`` rather than ``angle``: ``(B,)`` bool.

    Phase correlation of magnitude spectra finds the rotation modulo a half-turn. Without a
    known range the correlation peaks decide (``turned_score > upright_score``). A range of
    at most 180 degrees decides alone: the turn inside it (or, for a narrower range, the
    nearer to it), so no check is needed. A wider one decides where only one turn is inside
    and leaves the rest to the scores.
    """
    if rotation_range is None:
        if upright_score is None or turned_score is None:
            raise ValueError("choose_half_turn needs a rotation_range or both scores")
        return turned_score > upright_score
    up = outside_rotation_range(angle, rotation_range)
    turned = outside_rotation_range(angle + 180.0, rotation_range)
    if upright_score is None or turned_score is None:
        return turned < up
    return torch.where(up == turned, turned_score > upright_score, turned < up)


def _merge_views(surface: Tensor, views: int) -> Tensor:
    """Average ``(views * B, A, R)`` log-polar surfaces of dihedral views on the first view's
    angle axis: ``(B, A, R)``. A mirror negates the rotation: row ``r`` -> ``(A - r) mod A``."""
    stacked = surface.view(views, -1, *surface.shape[1:])
    aligned = [
        torch.roll(torch.flip(view, dims=(1,)), 1, dims=1) if mirror else view
        for view, (_, mirror) in zip(stacked, DIHEDRAL_VIEWS[:views], strict=True)
    ]
    return torch.stack(aligned).mean(dim=0)


@full_precision
def estimate_rotation_scale(
    template: Tensor,
    source: Tensor,
    n_angles: int = 256,
    n_radii: int = 256,
    min_radius: float = 0.03,
    max_radius: float = 0.95,
    highpass: bool = True,
    log_spectrum: bool = False,
    sigma: float = 2.0,
    temperature: float | Tensor = 0.1,
    window: int | None = 3,
    scale_range: tuple[float, float] | None = (0.5, 2.0),
    relative: bool = True,
    hypotheses: int = 1,
    source_shifts: Sequence[tuple[int, int]] = (),
    views: int = 1,
    correlation: str = "joint",
    radius_window: bool = False,
) -> RotationScale:
    """Rotation (mod 180 degrees) and scale of ``source`` relative to ``template``.

    Args:
        template, source: ``(B, C, H, W)`` images or feature maps. A template batch expanded
            from one image (``template.expand(B, -1, -1, -1)``, stride 0) has its spectrum
            and log-polar map computed once: one template against many sources.
        n_angles, n_radii, min_radius, max_radius: log-polar grid (see
            :func:`dpcn.ops.log_polar`); ``180 / n_angles`` degrees per row.
        highpass: apply the Reddy high-pass filter to the magnitude spectra.
        log_spectrum: log-polar maps of ``log(1 + |F|)`` instead of ``|F|``: compresses the
            spectra's dynamic range, so that the weak high frequencies of edges count beside
            the strong low ones.
        sigma, temperature, window, relative: correlation blur and soft-argmax settings
            (:func:`dpcn.ops.phase_correlation`, :func:`dpcn.ops.soft_argmax2d`).
        scale_range: only scales in this range are searched (``None``: all).
        hypotheses: also locate the next strongest peaks, ``hypotheses`` in all, at least
            ``max(window, 4)`` bins from each other (``candidate_*`` fields), for a later stage to
            choose from.
        source_shifts: integer ``(rows, cols)`` circular shifts of the source: each gives one
            more source spectrum, under a window centred elsewhere in the source, and the
            surface is the element-wise maximum over all windows (the centred one included).
            A translated source shares only part of its centred window's content with the
            template; a window nearer the translated centre shares more (the template's
            spectrum is computed once).
        views: ``template`` and ``source`` hold ``views`` dihedral views of each of ``B``
            pairs, ``(views * B, C, H, W)`` as :func:`dihedral_views` stacks them (e.g. the
            features of the turned and mirrored images: a CNN is not equivariant to either, so
            each view's surface is a partly independent estimate). Their surfaces are averaged
            on the first view's angle axis before the peak search; the result is one estimate
            per pair, with the first view's log-polar maps.
        correlation: ``joint`` (the paper's 2-D log-polar phase correlation) or
            ``decoupled`` (DPCN++'s 1-D correlations of the angle and log-radius profiles);
            see :func:`log_polar_correlation`.
        radius_window: a Hann window along the log-radius axis of both log-polar maps before
            the ``joint`` correlation (the ``decoupled`` one windows its radius profiles
            anyway). The axis is not periodic: its ends hold the lowest and the highest
            frequencies, and the circular correlation of that edge with itself peaks at no
            shift, i.e. at scale 1, whatever the pair; the window removes that peak.

    Returns:
        :class:`RotationScale` with ``angle`` in ``[-90, 90)`` degrees and ``scale``.
    """
    check_pair(template, source)
    check_views(views, template.shape[-2:])
    if template.shape[0] % views:
        raise ValueError(f"{template.shape[0]} maps are not {views} views of whole pairs")
    shifts = [tuple(int(v) for v in shift) for shift in source_shifts if tuple(shift) != (0, 0)]
    sources = [source] + [torch.roll(source, shift, dims=(-2, -1)) for shift in shifts]
    batch = len(template)
    # One template expanded over the batch: its spectrum and map once, expanded again after.
    templates = template[:1] if copies_of_one(template) else template
    # All spectra in one batch: half spectra (point symmetry) sampled on angles [-90, 90).
    spectra = magnitude_spectrum(
        torch.cat([templates, *sources]), window=True, highpass=highpass, log=log_spectrum, half=True
    )
    maps = log_polar(spectra, n_angles, n_radii, min_radius, max_radius, half=True, width=template.shape[-1])
    if radius_window and correlation == "joint":
        maps = maps * torch.hann_window(n_radii, periodic=False, device=maps.device, dtype=maps.dtype)
    lp_t, lp_all = maps[: len(templates)].expand(batch, -1, -1, -1), maps[len(templates) :]
    lp_s = lp_all[:batch]
    surface = log_polar_correlation(lp_t, lp_all.view(len(sources), *lp_t.shape), sigma, correlation)
    if shifts:
        surface = surface.view(len(sources), batch, n_angles, n_radii).amax(dim=0)
    if views > 1:
        surface = _merge_views(surface, views)
        batch //= views
        lp_t, lp_s = lp_t[:batch], lp_s[:batch]
    step = log_radius_step(n_radii, min_radius, max_radius)
    mask = _scale_mask(n_radii, step, scale_range, surface.device, surface.dtype)
    scored = surface if mask is None else surface + mask
    circular = (True, False)
    if hypotheses == 1:
        peak = soft_argmax2d(scored, temperature, window=window, circular=circular, relative=relative)[:, None]
        score = scored.flatten(1).max(dim=1).values[:, None]
    else:
        if not isinstance(hypotheses, int) or hypotheses < 1:
            raise ValueError(f"hypotheses must be an integer >= 1, got {hypotheses!r}")
        if window is None:
            raise ValueError("several rotation/scale hypotheses need a soft-argmax window")
        score, indices = local_maxima2d(scored, hypotheses, radius=max(window, 4), circular=circular)
        repeated = scored.repeat_interleave(hypotheses, dim=0)
        peak = soft_argmax2d(
            repeated, temperature, window=window, circular=circular, relative=relative, peak=indices.flatten(0, 1)
        ).view(-1, hypotheses, 2)
    # A rotation by +a shifts the source's log-polar map by -a rows; a scale s by -ln(s) columns.
    d_angle = peak[..., 0] - n_angles // 2
    d_radius = peak[..., 1] - n_radii // 2
    angle = wrap_angle(-d_angle * (180.0 / n_angles), period=180.0)
    angle = torch.where(angle >= 90.0, angle - 180.0, angle)  # [-90, 90)
    scale = torch.exp(-d_radius * step)
    confidence = score[:, 0].clamp(0.0, 1.0)
    return RotationScale(angle[:, 0], scale[:, 0], confidence, surface, lp_t, lp_s, angle, scale, score)


@full_precision
def unwarp_rotation_scale(source: Tensor, angle: Tensor, scale: Tensor) -> Tensor:
    """Undo a rotation by ``angle`` degrees and a scaling by ``scale`` about the image centre.

    ``(B, C, H, W) -> (B, C, H, W)``; kornia bilinear warp, zeros outside, differentiable in
    the image, the angle and the scale. If ``source`` is the template warped by a pose with
    this angle and scale, the result is the template shifted by ``A^-1 t`` (``A`` the pose's
    2x2 linear part, ``t`` its translation).
    """
    _, _, height, width = source.shape
    zeros = torch.zeros_like(angle)
    inverse = pose_to_matrix(zeros, zeros, -angle, 1.0 / scale, (height, width))
    return kornia.geometry.transform.warp_affine(
        source, inverse.to(source.dtype), (height, width), mode="bilinear", padding_mode="zeros", align_corners=True
    )


@full_precision
def estimate_translation(
    template: Tensor,
    unwarped_source: Tensor,
    angle: Tensor,
    scale: Tensor,
    resolve_180: bool = True,
    apodize: bool = True,
    sigma: float = 2.0,
    temperature: float | Tensor = 0.1,
    window: int | None = 3,
    relative: bool = True,
    rotation_range: tuple[float, float] | None = None,
) -> Translation:
    """Translation of the source, from the template and the un-rotated/un-scaled source.

    Args:
        template: ``(B, C, H, W)`` template images or features (expanded from one, stride 0:
            its DFT is computed once).
        unwarped_source: ``(B, C, H, W)`` source after :func:`unwarp_rotation_scale` with
            ``angle`` and ``scale`` (or features of it).
        angle, scale: ``(B,)`` the stage-1 estimate used for the un-warp.
        resolve_180: also try ``angle + 180``: rotating the un-warped source by half a turn
            about the centre conjugates its spectrum, so this costs one extra inverse DFT,
            no warp and no extra features.
        apodize: Hann-window both inputs first.
        rotation_range: a known range of the rotation, ``[low, high]`` degrees: the half-turn
            inside it wins (:func:`choose_half_turn`; decided by the range alone when it
            spans at most 180 degrees, also without ``resolve_180``). ``None``: no prior.

    Returns:
        :class:`Translation` in the project's pose convention.
    """
    check_pair(template, unwarped_source, ("template", "unwarped_source"))
    _, _, height, width = template.shape
    # One template expanded over the batch: its DFT once (the product broadcasts).
    a = template[:1] if copies_of_one(template) else template
    b = unwarped_source
    a = a - a.mean(dim=(-2, -1), keepdim=True)
    b = b - b.mean(dim=(-2, -1), keepdim=True)
    if apodize:
        win = apodization_window(height, width, template.device, template.dtype)
        a, b = a * win, b * win
    fa, fb = torch.fft.rfft2(a), torch.fft.rfft2(b)
    cross = (fb * fa.conj()).sum(dim=1)
    surface = correlation_surface(cross, (height, width), sigma=sigma)
    angle = angle.to(surface.dtype)
    if resolve_180 or rotation_range is not None:
        # The half-turn hypothesis: b rotated by 180 degrees about (W/2, H/2) is b(-p)
        # circularly, whose DFT is conj(B); no second warp, DFT or feature pass is needed.
        mirrored = correlation_surface((fb * fa).conj().sum(dim=1), (height, width), sigma=sigma)
        scores = (surface.flatten(1).max(dim=1).values, mirrored.flatten(1).max(dim=1).values)
        take_mirror = choose_half_turn(angle, rotation_range, *(scores if resolve_180 else (None, None)))
        surface = torch.where(take_mirror[:, None, None], mirrored, surface)
        angle = torch.where(take_mirror, angle + 180.0, angle)
    peak = soft_argmax2d(surface, temperature, window=window, circular=(True, True), relative=relative)
    dy = torch.remainder(peak[:, 0] - height // 2 + height / 2, height) - height / 2
    dx = torch.remainder(peak[:, 1] - width // 2 + width / 2, width) - width / 2
    # t = A d with A = s [[cos, sin], [-sin, cos]] (the cv2 linear part of the pose); for the
    # half-turn hypothesis A changes sign with the angle, matching the mirrored frame of d.
    theta = torch.deg2rad(angle)
    scale = scale.to(surface.dtype)
    tx = scale * (torch.cos(theta) * dx + torch.sin(theta) * dy)
    ty = scale * (-torch.sin(theta) * dx + torch.cos(theta) * dy)
    confidence = surface.flatten(1).max(dim=1).values.clamp(0.0, 1.0)
    return Translation(tx, ty, wrap_angle(angle), confidence, surface)


class PhaseCorrelationEstimator(nn.Module):
    """Classical Fourier-Mellin registration as a differentiable module.

    ``forward(template, source)`` with ``(B, C, H, W)`` tensors returns a :class:`Pose` such
    that ``source ~= warp(template, pose)`` in the project's convention; a ``(1, C, H, W)``
    template is matched against each of ``B`` sources, its spectra and DFTs computed once.
    Runs on the inputs' device and dtype; gradients flow from the pose to both images.

    Args:
        n_angles, n_radii, min_radius, max_radius: log-polar grid of stage 1.
        highpass: Reddy high-pass on the magnitude spectra.
        log_spectrum: stage 1 on ``log(1 + |F|)`` (see :func:`estimate_rotation_scale`).
        sigma: Gaussian blur (pixels) of the translation correlation surface.
        rotation_sigma, rotation_temperature: the same for the log-polar surface of stage 1
            (default: ``sigma`` and ``temperature``). Less blur there keeps the close
            spectral peaks of periodic textures (bricks, tiles, crop rows) apart.
        temperature: soft-argmax temperature, relative to each surface's peak height.
        window: soft-argmax neighbourhood half-size (``None``: whole surface).
        scale_range: searched scales.
        resolve_180: recover the full 360 degrees (else angles are in ``[-90, 90)``).
        refine: extra stage-1 passes on the un-warped source; each removes the residual
            rotation/scale left by the grid resolution.
        spectrum_window_grid, spectrum_window_step: stage 1 also takes the source's spectrum
            under an ``n x n`` grid of windows ``step`` of the side apart, the best correlation
            per log-polar bin counting (:func:`window_grid_shifts`); ``1``: centred only.
        rotation_scale_correlation: ``joint`` (the paper's 2-D log-polar phase correlation)
            or ``decoupled`` (DPCN++'s 1-D correlations; :func:`log_polar_correlation`).
        rotation_range: a known range of the rotation, ``[low, high]`` degrees (a heading
            prior, or the paper's ``[0, 180]``); it settles the half-turn (see
            :func:`estimate_translation`). ``None``: the full circle.
        radius_window: stage 1's log-polar maps under a Hann window along the log-radius
            axis, which removes the correlation's spurious peak at scale 1 (see
            :func:`estimate_rotation_scale`). On by default; ``False`` is stage 1 as the
            paper describes it.
    """

    def __init__(
        self,
        n_angles: int = 256,
        n_radii: int = 256,
        min_radius: float = 0.03,
        max_radius: float = 0.95,
        highpass: bool = True,
        log_spectrum: bool = False,
        sigma: float = 2.0,
        temperature: float = 0.1,
        window: int | None = 3,
        rotation_sigma: float | None = 1.0,
        rotation_temperature: float | None = 0.07,
        scale_range: tuple[float, float] | None = (0.5, 2.0),
        resolve_180: bool = True,
        refine: int = 0,
        spectrum_window_grid: int = 1,
        spectrum_window_step: float = 0.125,
        rotation_scale_correlation: str = "joint",
        rotation_range: tuple[float, float] | None = None,
        radius_window: bool = True,
    ) -> None:
        super().__init__()
        # Settings arrive from configs and the command line as any type: each is named if wrong.
        check_ints("", ("n_angles", n_angles, 2), ("n_radii", n_radii, 2), ("window", window, 0), ("refine", refine, 0))
        for name, value in (("min_radius", min_radius), ("max_radius", max_radius)):
            check_number(name, value, low=0.0, high=1.0, low_open=True)
        log_polar_grid(8, 8, n_angles, n_radii, min_radius, max_radius)  # validates the grid
        check_rotation_scale_correlation(rotation_scale_correlation)
        switches = (("highpass", highpass), ("log_spectrum", log_spectrum), ("resolve_180", resolve_180))
        for name, value in (*switches, ("radius_window", radius_window)):
            check_bool(name, value)
        rotation_sigma = sigma if rotation_sigma is None else rotation_sigma
        rotation_temperature = temperature if rotation_temperature is None else rotation_temperature
        for name, value in (("sigma", sigma), ("rotation_sigma", rotation_sigma)):
            check_number(name, value, low=0.0)
        for name, value in (("temperature", temperature), ("rotation_temperature", rotation_temperature)):
            check_number(name, value, low=0.0, low_open=True)
        scale_range = check_scale_range(scale_range)
        self.rotation_scale_options = dict(
            n_angles=n_angles,
            n_radii=n_radii,
            min_radius=min_radius,
            max_radius=max_radius,
            highpass=highpass,
            log_spectrum=log_spectrum,
            sigma=rotation_sigma,
            temperature=rotation_temperature,
            window=window,
            scale_range=scale_range,
            relative=True,
            correlation=rotation_scale_correlation,
            radius_window=radius_window,
        )
        self.translation_options = dict(
            resolve_180=resolve_180,
            sigma=sigma,
            temperature=temperature,
            window=window,
            relative=True,
            rotation_range=check_rotation_range(rotation_range),
        )
        self.refine = refine
        window_grid_shifts(8, 8, spectrum_window_grid, spectrum_window_step)  # validates them
        self.spectrum_window = (spectrum_window_grid, spectrum_window_step)

    def check_inputs(self, template: Tensor, source: Tensor) -> None:
        """Raise ``ValueError`` naming the problem for a pair this estimator cannot match."""
        check_pair(template, source, min_size=8, one_to_many=True)

    def forward(self, template: Tensor, source: Tensor) -> Pose:
        """``(B, C, H, W)`` template and source (or one ``(1, C, H, W)`` template against
        ``B`` sources) -> :class:`~dpcn.pose.Pose` with ``(B,)`` fields."""
        self.check_inputs(template, source)
        template = template.expand(source.shape[0], -1, -1, -1)
        shifts = window_grid_shifts(*source.shape[-2:], *self.spectrum_window)
        options = dict(self.rotation_scale_options, source_shifts=shifts)
        with inputs_checked():
            rs = estimate_rotation_scale(template, source, **options)
            angle, scale = rs.angle, rs.scale
            unwarped = unwarp_rotation_scale(source, angle, scale)
            for _ in range(self.refine):
                residual = estimate_rotation_scale(template, unwarped, **options)
                angle, scale = angle + residual.angle, scale * residual.scale
                unwarped = unwarp_rotation_scale(source, angle, scale)
            tr = estimate_translation(template, unwarped, angle, scale, **self.translation_options)
        return Pose(tr.tx, tr.ty, tr.angle, scale, tr.confidence)
