"""Lightning modules: DPCN training/evaluation, and the classical estimator evaluated alike."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from omegaconf import OmegaConf
from torch import Tensor

from .._validate import check_bool, check_int, check_number
from ..checkpoint import (
    CheckpointError,
    does_not_fit,
    dpcn_network,
    first_sentence,
    inference_settings,
    load_fitting_weights,
    read_checkpoint,
    set_inference_settings,
    weight_differences,
)
from ..estimator import PhaseCorrelationEstimator, estimate_translation, unwarp_rotation_scale
from ..io import flag_featureless, is_tensor_pair, prepare_pair
from ..metrics import (
    accuracy_curve,
    format_table,
    pose_errors,
    summarize,
    thresholds_for,
    write_csv,
    write_curve_csv,
    write_pairs_csv,
)
from ..models.dpcn import PHASE_UNETS
from ..ops._checks import inputs_checked
from ..pose import Pose, wrap_angle
from .losses import DPCNLoss, rotation_scale_target, translation_target

__all__ = ["DPCNModule", "ClassicalModule", "load_matcher", "load_weights", "CheckpointError"]


TRAIN_SPECTRUM_WINDOWS = ("centred", "nearest")
FREEZABLE = PHASE_UNETS  # what ``freeze`` can hold fixed: a phase's two U-Nets


def _warmup_cosine(step: int, total: int, warmup: float = 0.1, floor: float = 0.04) -> float:
    """Learning-rate factor: cosine ramp from ``floor`` to 1 over the first ``warmup`` of the
    run, then cosine decay to 0 at ``total`` steps."""
    ramp = max(1, int(warmup * total))
    if step < ramp:
        return floor + (1.0 - floor) * 0.5 * (1.0 - math.cos(math.pi * step / ramp))
    progress = min(1.0, (step - ramp) / max(1, total - ramp))
    return 0.5 * (1.0 + math.cos(math.pi * progress))


def _plain_values(value: Any) -> Any:
    """``value`` as plain Python: OmegaConf containers and numpy values become the dicts, lists
    and numbers they hold (recursively); anything else is returned as it is."""
    if OmegaConf.is_config(value):
        value = OmegaConf.to_container(value, resolve=True)
    if isinstance(value, dict):
        return {key: _plain_values(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_plain_values(item) for item in value)
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    return value


def _check_freeze(freeze: object) -> tuple[str, ...]:
    """``model.freeze`` as a tuple of known part names (a clear error otherwise)."""
    if freeze is None:
        return ()
    parts = (freeze,) if isinstance(freeze, str) else freeze
    if not isinstance(parts, (list, tuple)) or any(part not in FREEZABLE for part in parts):
        raise ValueError(f"model.freeze takes a list of {', '.join(FREEZABLE)}; got {freeze!r}")
    if set(parts) == set(FREEZABLE):
        raise ValueError("model.freeze names both phases: nothing would be trained")
    return tuple(dict.fromkeys(parts))


def check_batch(batch: object, paired: bool) -> tuple[Tensor, Tensor, Tensor]:
    """The ``template``, ``source`` and ``pose`` of a loader's batch, with a one-line error for
    a batch of another form (a user's dataset): ``pose`` must be ``(B, 4)`` for the ``B``
    sources, and ``paired`` (training) asks one template per source (evaluation may also match
    one template against every source). The images themselves are checked by the matcher."""
    keys = ("template", "source", "pose")
    if not isinstance(batch, dict) or any(key not in batch for key in keys):
        found = sorted(map(str, batch)) if isinstance(batch, dict) else type(batch).__name__
        raise ValueError(f"a batch must be a dict with the keys {', '.join(keys)}; got {found}")
    template, source, pose = (batch[key] for key in keys)
    sources = source.shape[0] if isinstance(source, Tensor) and source.ndim == 4 else None
    templates = template.shape[0] if isinstance(template, Tensor) and template.ndim == 4 else None
    if sources is None or templates is None:
        return template, source, pose  # the matcher's check names what is wrong with them
    if not isinstance(pose, Tensor) or tuple(pose.shape) != (sources, 4):
        shape = tuple(pose.shape) if isinstance(pose, Tensor) else type(pose).__name__
        raise ValueError(
            f"a batch's pose must be ({sources}, 4) for its {sources} sources (x, y, angle, scale); got {shape}"
        )
    if not pose.is_floating_point():
        raise ValueError(f"a batch's pose must be floating point (x, y, angle, scale); got {pose.dtype}")
    if not torch.isfinite(pose).all():
        row = int((~torch.isfinite(pose)).any(dim=1).nonzero()[0])  # the first bad row, not all of them
        raise ValueError(f"a batch's pose must hold finite numbers; row {row} is {pose[row].tolist()}")
    if paired and templates != sources:
        raise ValueError(
            f"a training batch pairs each template with one source; got {templates} templates and {sources} sources"
        )
    return template, source, pose


class _EvaluationMixin:
    """Shared validation/test logic: per-pair errors gathered over the epoch, the paper's metrics."""

    translation_threshold: float

    def _reset(self) -> None:
        self._records: list[Tensor] = []

    def _evaluate_batch(self, batch: dict[str, Tensor]) -> Tensor:
        template, source, truth = check_batch(batch, paired=False)
        pose = self.match(template, source)
        estimate = pose.as_tensor().to(truth.device).double()
        confidence = pose.confidence if pose.confidence is not None else torch.full_like(estimate[:, 0], float("nan"))
        truth = truth.double()
        # (B, 9): the true pose, the estimate and its confidence, kept for the per-pair table.
        self._records.append(torch.cat([truth, estimate, confidence.to(estimate).reshape(-1, 1)], dim=1).detach())
        return pose_errors(estimate, truth)

    def _gathered_records(self) -> Tensor:
        """``(N, 9)`` records of the epoch in data-set order, gathered over DDP ranks.

        The data module's sampler (:class:`~dpcn.data.datamodule.EpochBlockSampler`) splits
        an evaluation set over ranks by stride, without repeats: rank ``r`` gets the pairs
        ``r, r + world, ...``, so ranks may hold one pair fewer. ``all_gather`` needs equal
        shapes, so each rank pads to the longest with NaN rows, dropped after the ranks are
        interleaved back into data-set order."""
        records = torch.cat(self._records) if self._records else torch.zeros(0, 9, dtype=torch.float64)
        world = self.trainer.world_size if self._trainer is not None else 1
        if world > 1:
            longest = int(self.all_gather(torch.tensor(records.shape[0], device=self.device)).max())
            padding = records.new_full((longest - records.shape[0], 9), float("nan"))
            gathered = self.all_gather(torch.cat([records, padding]))  # (world, longest, 9)
            records = gathered.transpose(0, 1).reshape(-1, 9)
            records = records[~torch.isnan(records[:, 0])]
        return records.cpu()

    def _finish(self, stage: str) -> dict[str, float]:
        records = self._gathered_records()
        errors = pose_errors(records[:, 4:8], records[:, :4])
        thresholds = thresholds_for(self.translation_threshold)
        metrics = summarize(errors, thresholds) if len(errors) else {}
        for key, value in metrics.items():
            if key != "n":
                self.log(f"{stage}/{key}", value, sync_dist=False, rank_zero_only=True)
        self.last_metrics = metrics
        self.last_records, self.last_errors = records, errors
        self._reset()
        return metrics

    def report(self, stage: str, name: str, out_dir: str | Path | None, pair_names: Sequence[str] | None = None) -> str:
        """Table of the last metrics; also written as ``metrics_<stage>.csv`` in ``out_dir``,
        beside ``pairs_<stage>.csv``, every pair's truth, estimate, confidence and errors (and
        its name, given ``pair_names`` in data-set order), and ``accuracy_<stage>.csv``, the
        accuracy against threshold of each component (:func:`~dpcn.metrics.accuracy_curve`)."""
        if not getattr(self, "last_metrics", None):
            return ""
        rows = [(name, self.last_metrics)]
        if out_dir is not None:
            write_csv(Path(out_dir) / f"metrics_{stage}.csv", rows)
            records = self.last_records
            confidence = None if torch.isnan(records[:, 8]).all() else records[:, 8]
            pairs = Path(out_dir) / f"pairs_{stage}.csv"
            write_pairs_csv(pairs, records[:, :4], records[:, 4:8], confidence, pair_names)
            write_curve_csv(Path(out_dir) / f"accuracy_{stage}.csv", accuracy_curve(self.last_errors))
        return format_table(rows)


class DPCNModule(_EvaluationMixin, L.LightningModule):
    """Trains :class:`~dpcn.models.DPCN` end to end from pose supervision.

    Args:
        net: keyword arguments of :class:`~dpcn.models.DPCN` (architecture, log-polar grid,
            inference peak settings).
        temperature: softmax temperature of the training losses (the paper's temperature),
            one value or ``[rotation_scale, translation]``; correlations are in ``[-1, 1]``.
        learnable_temperature: learn it (stored as a logarithm).
        loss: keyword arguments of :class:`~dpcn.training.losses.DPCNLoss`.
        lr, weight_decay: AdamW settings; the learning rate follows a cosine schedule.
        teacher_forcing: probability, per batch, of un-warping the source for phase 2 with the
            ground-truth rotation/scale instead of phase 1's estimate.
        warmup_epochs: epochs with teacher forcing always on.
        warp_grad: let phase-2 gradients flow through the un-warp into phase 1.
        translation_fraction: fraction of each training batch (its first pairs, at least one)
            that phase 2 trains on. Phase 2 costs about twice as much as phase 1 per pair on a
            CPU but learns its easier task much sooner; below 1, the time saved goes to more
            phase-1 steps (every training pair is an independent random draw, so the first
            pairs of a batch are a random subset).
        train_spectrum_window: where phase 1 takes each training pair's source spectrum:
            ``"centred"`` (the centred window, as at inference without the window grid) or
            ``"nearest"`` (the window of the inference grid, ``net.spectrum_window_grid``,
            nearest to where the template's centre lies in the source: the one the grid
            would ideally pick, so phase 1 learns from windows that share their content).
        translation_threshold: the paper's translation accuracy threshold (px) for metrics.
        freeze: phases whose two U-Nets are not trained (``"rotation_scale"``,
            ``"translation"``), e.g. to fine-tune one phase of a trained model (``fit
            init_from=…``): no gradients, no weight decay, kept in eval mode. A frozen phase 1
            also runs without autograd; its losses are still computed and logged (constants).
    """

    def __init__(
        self,
        net: dict[str, Any] | None = None,
        temperature: float | list[float] = 0.02,
        learnable_temperature: bool = True,
        loss: dict[str, Any] | None = None,
        lr: float = 1e-2,
        weight_decay: float = 1e-4,
        teacher_forcing: float = 0.5,
        warmup_epochs: int = 1,
        warp_grad: bool = False,
        translation_fraction: float = 1.0,
        train_spectrum_window: str = "centred",
        translation_threshold: float = 5.0,
        max_epochs: int | None = None,
        freeze: list[str] | tuple[str, ...] | None = None,
    ) -> None:
        super().__init__()
        check_number("model.lr", lr, low=0.0, low_open=True)
        check_number("model.weight_decay", weight_decay, low=0.0)
        check_number("model.teacher_forcing", teacher_forcing, low=0.0, high=1.0)
        check_int("model.warmup_epochs", warmup_epochs, low=0)
        check_number("model.translation_fraction", translation_fraction, low=0.0, high=1.0, low_open=True)
        check_number("model.translation_threshold", translation_threshold, low=0.0, low_open=True)
        check_bool("model.learnable_temperature", learnable_temperature)
        check_bool("model.warp_grad", warp_grad)
        if train_spectrum_window not in TRAIN_SPECTRUM_WINDOWS:
            raise ValueError(
                f"model.train_spectrum_window must be one of {', '.join(TRAIN_SPECTRUM_WINDOWS)}, "
                f"got {train_spectrum_window!r}"
            )
        for t in [temperature] if isinstance(temperature, (int, float, str)) else list(temperature):
            check_number("model.temperature", t, low=0.0, low_open=True)
        frozen = _check_freeze(freeze)
        # Lightning saves the arguments' current values: plain ones (not a Python caller's
        # OmegaConf containers or numpy numbers) load back with torch.load(weights_only=True)
        plain = _plain_values
        net, temperature, loss, freeze = plain(net), plain(temperature), plain(loss), plain(freeze)
        lr, weight_decay, teacher_forcing = plain(lr), plain(weight_decay), plain(teacher_forcing)
        translation_fraction, translation_threshold = plain(translation_fraction), plain(translation_threshold)
        warmup_epochs, max_epochs = plain(warmup_epochs), plain(max_epochs)
        self.save_hyperparameters()
        self.model = dpcn_network(net, temperature, learnable_temperature)
        self.loss = DPCNLoss(**(loss or {}))
        self.translation_threshold = translation_threshold
        self.frozen = frozen
        for module in self._frozen_modules():
            module.requires_grad_(False)
        self._reset()

    def _frozen_modules(self) -> list[torch.nn.Module]:
        return [getattr(self.model, name) for part in self.frozen for name in FREEZABLE[part]]

    def train(self, mode: bool = True) -> DPCNModule:
        super().train(mode)
        for module in self._frozen_modules():  # frozen: no normalisation statistics updated either
            module.eval()
        return self

    @classmethod
    def load_from_checkpoint(  # type: ignore[override]
        cls,
        checkpoint_path: str | Path | Any,
        map_location: Any = None,
        hparams_file: str | Path | None = None,
        strict: bool | None = None,
        weights_only: bool | None = None,
        **kwargs: Any,
    ) -> DPCNModule:
        """Lightning's loader (the notebook path), after :func:`load_matcher`'s checks of a
        local file: :class:`CheckpointError` naming the problem for a missing, damaged (CRC) or
        foreign file, or one whose pickle would run code; the file is then read with
        ``weights_only=True`` unless the caller says otherwise. Streams and remote URLs go to
        Lightning unchecked."""
        local = isinstance(checkpoint_path, (str, Path)) and "://" not in str(checkpoint_path)
        if local:
            read_checkpoint(checkpoint_path)
            weights_only = True if weights_only is None else weights_only
        try:
            return super().load_from_checkpoint(
                checkpoint_path, map_location, hparams_file, strict, weights_only, **kwargs
            )
        except (TypeError, RuntimeError) as error:
            if not local:
                raise
            # unknown or missing arguments, or weights of another shape: an older or newer release
            raise does_not_fit(checkpoint_path, first_sentence(error)) from None

    # ---------------------------------------------------------------- inference
    def match(self, template: Tensor, source: Tensor) -> Pose:
        """Pose of ``source`` relative to ``template`` (tensors ``(B, C, H, W)`` or arrays); one
        template (a batch of one, or an array) is matched against every source of a batch."""
        return self.model.match(template, source)

    def forward(self, template: Tensor, source: Tensor) -> Pose:
        return self.match(template, source)

    # ---------------------------------------------------------------- training
    def _use_ground_truth(self, batch_size: int) -> Tensor:
        if self.current_epoch < self.hparams.warmup_epochs:
            return torch.ones(batch_size, dtype=torch.bool, device=self.device)
        # Drawn from (global step, rank) alone, not from the global RNG: a run resumed from any
        # checkpoint makes the same draws as the uninterrupted run.
        rank = self.trainer.global_rank if self._trainer is not None else 0
        generator = torch.Generator().manual_seed(self.global_step * 1009 + rank)
        return (torch.rand(batch_size, generator=generator) < self.hparams.teacher_forcing).to(self.device)

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        template, source, gt = check_batch(batch, paired=True)
        self.model.check_inputs(template, source)
        with inputs_checked():
            return self._training_loss(template, source, gt)

    def _training_loss(self, template: Tensor, source: Tensor, gt: Tensor) -> Tensor:
        tx, ty, angle, scale = gt.unbind(dim=1)
        shifts = None
        if self.hparams.get("train_spectrum_window", "centred") == "nearest":
            d = self.model.rotation_scale_downsample
            size = (math.ceil(template.shape[-2] / d), math.ceil(template.shape[-1] / d))
            shifts = self.model.nearest_window_shifts(tx, ty, size)
        with torch.set_grad_enabled(torch.is_grad_enabled() and "rotation_scale" not in self.frozen):
            rs, rs_features = self.model.rotation_scale(template, source, source_shifts=shifts)
        align = self._alignment(rs_features, gt) if self.loss.weights["kl_align"] else (None, None)

        # Phase 1's angle is known modulo 180 degrees; take the half-turn closest to the truth
        # so phase 2 learns on upright sources (the half-turn is settled at inference).
        predicted = rs.angle + 180.0 * (wrap_angle(angle - rs.angle).abs() > 90.0)
        predicted_scale = rs.scale
        if not self.hparams.warp_grad:
            predicted, predicted_scale = predicted.detach(), predicted_scale.detach()
        forced = self._use_ground_truth(template.shape[0])
        unwarp_angle = torch.where(forced, angle, predicted)
        unwarp_scale = torch.where(forced, scale, predicted_scale)
        n = max(1, math.ceil(self.hparams.translation_fraction * template.shape[0]))  # phase-2 pairs
        unwarp_angle, unwarp_scale, tx, ty = unwarp_angle[:n], unwarp_scale[:n], tx[:n], ty[:n]
        unwarped = unwarp_rotation_scale(source[:n], unwarp_angle, unwarp_scale)
        half_turn_too = bool(self.loss.weights["kl_half_turn"])
        turns, _, _ = self.model.translation_turns(template[:n], unwarped, unwarp_angle, unwarp_scale, half_turn_too)
        tr, turned = turns[0], turns[1].surface if half_turn_too else None

        m = self.model
        rs_centre = rotation_scale_target(angle, scale, m.n_angles, m.n_radii, m.radius_step)
        t_centre = translation_target(tx, ty, unwarp_angle.detach(), unwarp_scale.detach(), template.shape[-2:])
        loss = self.loss(rs.surface, rs_centre, tr.surface, t_centre, m.train_temperature, *align, turned)
        batch_size = template.shape[0]
        self.log("train/loss", loss.total, prog_bar=True, batch_size=batch_size)
        for name, value in loss.terms.items():
            self.log(f"train/{name}", value, batch_size=batch_size)
        self.log("train/temperature_rs", m.train_temperature[0], batch_size=batch_size)
        self.log("train/temperature_t", m.train_temperature[1], batch_size=batch_size)
        return loss.total

    def _alignment(self, features: dict[str, Tensor], gt: Tensor) -> tuple[Tensor, Tensor]:
        """Phase 1's features compared in space (``loss.kl_align``): the source features
        un-warped by the true rotation/scale, phase-correlated with the template features;
        ``(B, h, w)`` surface and ``(B, 2)`` true peak, at phase 1's resolution."""
        tx, ty, angle, scale = gt.unbind(dim=1)
        template, source = features["rs_template"], features["rs_source"]
        d = self.model.rotation_scale_downsample
        unwarped = unwarp_rotation_scale(source, angle, scale)
        surface = estimate_translation(
            template, unwarped, angle, scale, resolve_180=False, sigma=self.model.sigma / d
        ).surface
        return surface, translation_target(tx / d, ty / d, angle, scale, template.shape[-2:])

    def configure_optimizers(self):
        trainable = [p for p in self.parameters() if p.requires_grad]  # frozen U-Nets: not even weight decay
        optimizer = torch.optim.AdamW(trainable, lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        trainer = self._trainer
        if trainer is None or (trainer.max_steps == -1 and trainer.max_epochs in (None, -1)):
            return optimizer  # no known end: constant learning rate
        total: list[int] = []

        def factor(step: int) -> float:
            # The schedule is a pure function of the step and the run's length, and nothing of
            # it goes into the checkpoint: a run resumed with a larger max_epochs stretches it.
            # The length is read at the first step, not here: Lightning builds the training
            # loader to count it, which here would be before a resumed run restores its place.
            if step == 0:
                return _warmup_cosine(0, 1)
            if not total:
                total.append(int(trainer.estimated_stepping_batches))
            return _warmup_cosine(step, total[0])

        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # ---------------------------------------------------------------- evaluation
    def on_validation_epoch_start(self) -> None:
        self._reset()

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate_batch(batch)

    def on_validation_epoch_end(self) -> None:
        metrics = self._finish("val")
        if metrics:
            # one number to select checkpoints by: the mean of the strict accuracies
            strict = [v for k, v in metrics.items() if k in ("acc_x@1", "acc_y@1", "acc_rot@0.5", "acc_scale@0.02")]
            self.log("val/score", sum(strict) / len(strict), prog_bar=True)

    def on_test_epoch_start(self) -> None:
        self._reset()

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate_batch(batch)

    def on_test_epoch_end(self) -> None:
        self._finish("test")


class ClassicalModule(_EvaluationMixin, L.LightningModule):
    """The classical estimator (no learning) behind the same validate/test interface."""

    def __init__(self, translation_threshold: float = 5.0, **options: Any) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.estimator = PhaseCorrelationEstimator(**options)
        self.translation_threshold = translation_threshold
        self._reset()

    def match(self, template: Tensor, source: Tensor) -> Pose:
        if not is_tensor_pair(template, source):
            template, source = prepare_pair(template, source, self.device)
        with torch.no_grad():
            return flag_featureless(self.estimator(template, source), template, source)

    def on_validation_epoch_start(self) -> None:
        self._reset()

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate_batch(batch)

    def on_validation_epoch_end(self) -> None:
        self._finish("val")

    def on_test_epoch_start(self) -> None:
        self._reset()

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate_batch(batch)

    def on_test_epoch_end(self) -> None:
        self._finish("test")

    def configure_optimizers(self):  # nothing to train
        return None


def load_matcher(ckpt_path: str | Path, map_location: str | torch.device = "cpu", **settings: Any) -> DPCNModule:
    """Load a DPCN checkpoint ready for ``.match(template, source) -> Pose`` (eval mode): the
    Lightning module around :func:`dpcn.load_model`'s model.

    ``settings`` are :func:`dpcn.load_model`'s inference settings (``rotation_hypotheses``,
    ``hypothesis_ratio``, ``spectrum_window_grid``, ``rotation_views``, ``unet_dtype``,
    ``inference_radii``, ``inference_sigma``, ``rotation_range``, ``scale_range``,
    ``half_turn_pass``), which
    replace the checkpoint's (see :class:`~dpcn.models.DPCN`); ``None`` keeps one
    (``rotation_range=[-180, 180]`` is the full circle, no prior; ``inference_radii="trained"``:
    the radii the model was trained with, whatever the checkpoint stores).
    Raises :class:`CheckpointError` naming the problem for a missing, corrupt or foreign file.
    """
    settings = inference_settings(**settings)  # checked before the file is read
    path = Path(ckpt_path)
    checkpoint = read_checkpoint(path, map_location)
    try:
        module = DPCNModule(**checkpoint["hyper_parameters"])
    except (TypeError, ValueError) as error:  # settings this release does not know or take
        raise does_not_fit(path, first_sentence(error)) from None
    load_fitting_weights(path, module, checkpoint["state_dict"])
    set_inference_settings(module.model, **settings)
    return module.to(map_location).eval()


def _tuples_as_lists(settings: Any) -> dict[str, Any]:
    """A configuration mapping with tuples as lists (checkpoints store either)."""
    return {k: list(v) if isinstance(v, (list, tuple)) else v for k, v in dict(settings).items()}


def load_weights(module: DPCNModule, ckpt_path: str | Path) -> DPCNModule:
    """Start ``module`` from the network weights of a DPCN checkpoint (``fit init_from=…``).

    Only the weights move (the four U-Nets and the loss temperature): ``module`` keeps its own
    settings, and training starts afresh (optimiser, learning-rate schedule, epoch 0), which is
    how a model trained on one data set is fine-tuned on another. The architectures must
    match; :class:`CheckpointError` lists what differs otherwise. Returns ``module``.
    """
    path = Path(ckpt_path)
    try:
        checkpoint = read_checkpoint(path)
    except CheckpointError as error:
        raise CheckpointError(f"init_from: {error}") from None
    weights = _network_weights(checkpoint)
    mismatch = _network_mismatch(module, checkpoint)
    if mismatch is not None:
        raise CheckpointError(f"init_from={path}: {mismatch}")
    module.model.load_state_dict(weights)
    return module


def check_resumable(module: DPCNModule, ckpt_path: str | Path) -> None:
    """:class:`CheckpointError` unless the run of checkpoint ``ckpt_path`` can resume into
    ``module`` (``fit ckpt_path=…``): the same network, or Lightning fails deep in
    ``load_state_dict`` with every tensor listed."""
    path = Path(ckpt_path)
    mismatch = _network_mismatch(module, read_checkpoint(path))
    if mismatch is not None:
        raise CheckpointError(
            f"ckpt_path={path}: {mismatch}. A run resumes with the settings it started with "
            "(its .hydra/overrides.yaml); init_from= starts a new run from weights that fit"
        )


def _network_weights(checkpoint: dict[str, Any]) -> dict[str, Tensor]:
    return {k[len("model.") :]: v for k, v in checkpoint["state_dict"].items() if k.startswith("model.")}


def _network_mismatch(module: DPCNModule, checkpoint: dict[str, Any]) -> str | None:
    """Why ``checkpoint``'s network does not load into ``module``'s, in one line with the
    settings behind it (from the two runs' configurations), or ``None`` when it does."""
    shown = weight_differences(module.model.state_dict(), _network_weights(checkpoint))
    if shown is None:
        return None
    there = _tuples_as_lists(checkpoint["hyper_parameters"].get("net") or {})
    here = _tuples_as_lists(module.hparams.get("net") or {})
    keys = [k for k in sorted(set(there) | set(here)) if there.get(k) != here.get(k)]
    settings = [f"model.net.{k} {there.get(k)} there, {here.get(k)} here" for k in keys]
    hint = f". Settings that differ: {'; '.join(settings)}" if settings else ""
    return f"its network is not this model's ({shown}){hint}"
