"""A Lightning data module over any of the pair data sets, with deterministic epochs."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

__all__ = ["EpochBlockSampler", "PairDataModule"]


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

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self) -> Iterator[int]:
        start = (self.epoch * self.epoch_size) % self.length
        for i in range(self.rank, self.epoch_size, self.world_size):
            yield (start + i) % self.length

    def __len__(self) -> int:
        return len(range(self.rank, self.epoch_size, self.world_size))


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
    ) -> None:
        super().__init__()
        if batch_size < 1 or epoch_size < 1 or val_length < 1 or test_length < 1:
            raise ValueError(
                f"batch_size, epoch_size, val_length, test_length must be >= 1, got "
                f"{batch_size}, {epoch_size}, {val_length}, {test_length}"
            )
        self.factory = dataset
        self.lengths = {"train": train_length, "val": val_length, "test": test_length}
        self.seeds = {"train": 0, "val": 1, "test": 2, **(seeds or {})}
        self.split_kwargs = split_kwargs or {}
        self.epoch_size = epoch_size
        self.batch_size, self.num_workers = batch_size, num_workers
        self.translation_threshold = translation_threshold
        self.name = name
        self.datasets: dict[str, Dataset] = {}

    def build(self, split: str) -> Dataset:
        if split not in self.datasets:
            kwargs = dict(self.split_kwargs.get(split, {}))
            self.datasets[split] = self.factory(length=self.lengths[split], seed=self.seeds[split], **kwargs)
        return self.datasets[split]

    def setup(self, stage: str | None = None) -> None:
        splits = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), None: ("train", "val", "test")}
        for split in splits.get(stage, ("val",)):
            self.build(split)

    def _loader(self, split: str, epoch_size: int | None) -> DataLoader:
        dataset = self.build(split)
        rank, world = (self.trainer.global_rank, self.trainer.world_size) if self.trainer is not None else (0, 1)
        sampler = EpochBlockSampler(len(dataset), epoch_size, rank, world)
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            sampler=sampler,
            num_workers=self.num_workers,
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
