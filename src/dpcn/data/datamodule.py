"""A Lightning data module over any of the pair data sets, with deterministic epochs."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate

from .._validate import check_ints, check_number
from .aeroground import DataError

__all__ = ["EpochBlockSampler", "PairDataModule", "ResumableDataLoader", "collate_pairs"]


class EpochBlockSampler(Sampler[int]):
    """Yields a fresh block of ``epoch_size`` indices each epoch from a (virtually) huge,
    procedurally generated data set: epoch ``e`` reads indices ``[e * epoch_size, (e + 1) *
    epoch_size)`` (wrapping around), split between DDP ranks by stride.

    Every item being a pure function of its index, an epoch is reproducible from its number
    alone, so a run resumed from a checkpoint sees exactly the data it would have seen.
    Lightning calls :meth:`set_epoch` at the start of each epoch.
    """

    def __init__(self, dataset_length: int, epoch_size: int | None = None, rank: int = 0, world_size: int = 1) -> None:
        self.length = dataset_length
        self.epoch_size = min(epoch_size or dataset_length, dataset_length)
        self.rank, self.world_size = rank, world_size
        self.epoch = 0
        self.skip: tuple[int, int] | None = None  # (epoch, items of it already consumed)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self) -> Iterator[int]:
        start = (self.epoch * self.epoch_size) % self.length
        first = 0
        if self.skip is not None:
            if self.skip[0] == self.epoch:
                first = self.skip[1]
            self.skip = None
        for i in list(range(self.rank, self.epoch_size, self.world_size))[first:]:
            yield (start + i) % self.length

    def __len__(self) -> int:
        return len(range(self.rank, self.epoch_size, self.world_size))


def collate_pairs(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """``default_collate`` of pair items, with a :class:`DataError` that says what to do when
    a batch mixes image sizes (torch's own says only that ``stack`` expects equal sizes)."""
    sizes = sorted({tuple(item["template"].shape[-2:]) for item in items if "template" in item})
    if len(sizes) > 1:
        listed = ", ".join(f"{h}x{w}" for h, w in sizes)
        raise DataError(
            f"a batch mixes pairs of different sizes ({listed}, H x W): a data set's pairs must share one size "
            "(data=csv: data.dataset.size=N resizes them all to N x N; or data.batch_size=1)"
        )
    return default_collate(items)


class ResumableDataLoader(DataLoader):
    """A DataLoader over an :class:`EpochBlockSampler` that Lightning checkpoints mid-epoch.

    Its state is the epoch and the number of its batches whose optimiser step is done;
    loading that state makes the next iteration of the same epoch skip them (indices only:
    nothing is generated), so a run resumed from a mid-epoch checkpoint sees exactly the rest
    of that epoch, the interrupted batch included.

    Args:
        steps_done: returns the number of batches of the current epoch already applied (the
            training loop's count); without it, the batches handed out are counted, which is
            one too many when a run is interrupted inside a step.
    """

    def __init__(self, *args: Any, steps_done: Callable[[], int] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._steps_done = steps_done
        self._served = 0

    def __iter__(self) -> Iterator[Any]:
        skip = self.sampler.skip
        self._served = skip[1] // self.batch_size if skip is not None and skip[0] == self.sampler.epoch else 0
        for batch in super().__iter__():
            self._served += 1
            yield batch

    def state_dict(self) -> dict[str, int]:
        done = self._served if self._steps_done is None else min(self._served, self._steps_done())
        return {"epoch": self.sampler.epoch, "batches": done}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.sampler.skip = (int(state["epoch"]), int(state["batches"]) * self.batch_size)


SPLITS = ("train", "val", "test")


def _check_splits(name: str, per_split: Mapping[str, Any] | None) -> None:
    """A per-split setting names only train, val and test: a misspelt split would be ignored."""
    if per_split is not None and not isinstance(per_split, Mapping):
        raise ValueError(f"data.{name} must map splits ({', '.join(SPLITS)}) to values, got {per_split!r}")
    unknown = sorted(set(per_split or {}) - set(SPLITS))
    if unknown:
        names = ", ".join(map(repr, unknown))
        raise ValueError(f"data.{name} has unknown split(s) {names}; the splits are {', '.join(SPLITS)}")


class PairDataModule(L.LightningDataModule):
    """Builds train/val/test sets from one data set factory with different seeds and sizes.

    Args:
        dataset: a callable ``(length=, seed=, **split_kwargs) -> Dataset`` (a Hydra partial).
        train_length: size of the (virtual) training set; epochs draw blocks from it.
        epoch_size: training pairs per epoch.
        val_length, test_length: fixed evaluation set sizes.
        seeds: ``{"train", "val", "test"}`` seeds (distinct seeds: disjoint pairs).
        split_kwargs: extra keyword arguments per split (e.g. ``{"train": {"split": "train"}}``
            for map data sets with regions).
        batch_size, num_workers: data loading.
        translation_threshold: the paper's translation threshold (px) for this data.
        **references: values that a data config only interpolates into ``dataset`` or
            ``split_kwargs`` (``root``, scene lists, CSV paths); kept for the record.
    """

    def __init__(
        self,
        dataset: Callable[..., Dataset],
        train_length: int = 1_000_000,
        epoch_size: int = 2000,
        val_length: int = 200,
        test_length: int = 500,
        seeds: dict[str, int] | None = None,
        split_kwargs: dict[str, dict[str, Any]] | None = None,
        batch_size: int = 16,
        num_workers: int = 0,
        translation_threshold: float = 5.0,
        name: str = "pairs",
        **references: Any,
    ) -> None:
        super().__init__()
        check_ints(
            "data.",
            ("batch_size", batch_size, 1),
            ("epoch_size", epoch_size, 1),
            ("train_length", train_length, 1),
            ("val_length", val_length, 1),
            ("test_length", test_length, 1),
            ("num_workers", num_workers, 0),
        )
        check_number("data.translation_threshold", translation_threshold, low=0.0, low_open=True)
        _check_splits("seeds", seeds)
        _check_splits("split_kwargs", split_kwargs)
        for split, kwargs in (split_kwargs or {}).items():
            if not isinstance(kwargs, Mapping):
                raise ValueError(f"data.split_kwargs.{split} must be a mapping of data set arguments, got {kwargs!r}")
        self.factory = dataset
        self.lengths = {"train": train_length, "val": val_length, "test": test_length}
        self.seeds = {"train": 0, "val": 1, "test": 2, **(seeds or {})}
        check_ints("data.seeds.", *((split, seed, 0) for split, seed in self.seeds.items()))
        self.split_kwargs = split_kwargs or {}
        self.epoch_size = epoch_size
        self.batch_size, self.num_workers = batch_size, num_workers
        self.translation_threshold = translation_threshold
        self.name = name
        self.references = references
        self.datasets: dict[str, Dataset] = {}

    def build(self, split: str) -> Dataset:
        if split not in self.datasets:
            kwargs = dict(self.split_kwargs.get(split, {}))
            try:
                self.datasets[split] = self.factory(length=self.lengths[split], seed=self.seeds[split], **kwargs)
            except (ValueError, TypeError) as error:
                if type(error) not in (ValueError, TypeError):
                    raise  # data errors (DataError, DpcnInputError) already name their file or row
                # A bad value: the constructor's message names the argument only, so say where it was
                # set (data.split_kwargs.<split> when the argument is one of the split's own).
                named = [key for key in kwargs if re.search(rf"\b{re.escape(str(key))}\b", str(error))]
                where = f"data.split_kwargs.{split}" if named else "data.dataset"
                raise type(error)(f"{where}: {error}") from error
        return self.datasets[split]

    def setup(self, stage: str | None = None) -> None:
        splits = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), None: ("train", "val", "test")}
        for split in splits.get(stage, ("val",)):
            self.build(split)

    def _loader(self, split: str, epoch_size: int | None) -> DataLoader:
        dataset = self.build(split)
        rank, world = (self.trainer.global_rank, self.trainer.world_size) if self.trainer is not None else (0, 1)
        sampler = EpochBlockSampler(len(dataset), epoch_size, rank, world)
        if split == "train" and len(sampler) < self.batch_size:  # Lightning would train 0 steps and say so in a warning
            per = f" per epoch on each of {world} processes" if world > 1 else " per epoch"
            raise DataError(
                f"the training set gives {len(sampler)} pair(s){per}, fewer than one batch of "
                f"data.batch_size={self.batch_size} (training drops a partial batch): lower data.batch_size "
                "or give it more pairs"
            )
        extra: dict[str, Any] = {}
        if split == "train" and self.trainer is not None:
            progress = self.trainer.fit_loop.epoch_loop.batch_progress
            extra["steps_done"] = lambda: progress.current.processed
        return (ResumableDataLoader if split == "train" else DataLoader)(
            dataset,
            **extra,
            batch_size=self.batch_size,
            sampler=sampler,
            num_workers=self.num_workers,
            collate_fn=collate_pairs,
            pin_memory=torch.cuda.is_available(),
            persistent_workers=False,
            drop_last=split == "train",
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", self.epoch_size)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", None)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", None)
