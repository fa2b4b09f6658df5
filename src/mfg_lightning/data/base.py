"""The shared base of every DataModule: splits, loaders, collation, worker seeding.

A concrete DataModule implements :meth:`MFGDataModule.build_dataset` for the splits it has and
the datasets implement :class:`MotionDataset`. The common work lives here once.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, DistributedSampler, default_collate

from mfg_lightning import geometry
from mfg_lightning.data.resumable_loader import ResumableDataLoader

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")


class EmptySplitError(ValueError):
    """A split has no samples (a wrong ``data_root`` or sequence list, usually)."""


class MotionDataset(Dataset):
    """A map-style dataset of samples in the schema of :mod:`mfg_lightning.data.sample`.

    Subclasses set ``height``, ``width`` and ``name`` and implement ``__len__``,
    ``__getitem__`` and :meth:`relative_poses`.
    """

    name: str = "dataset"
    height: int
    width: int

    def relative_poses(self) -> torch.Tensor:
        """``(N, 4, 4)`` ground-truth relative pose ``T_src,tgt`` of every sample, in order.

        Must not decode flow: it is used for statistics over a whole split (the mean-motion
        baseline, dataset checks) and should be fast.
        """
        raise NotImplementedError

    def sequences(self) -> dict[str, list[int]]:
        """Sample indices grouped by sequence, each list in frame order (for trajectories)."""
        raise NotImplementedError


class FileMotionDataset(MotionDataset):
    """A dataset read from files: samples are ``(sequence, source, target)`` triples.

    Subclasses fill ``samples``, ``name``, ``split``, ``skip_bad_samples`` and ``skipped`` (a
    :class:`~mfg_lightning.data.flow_io.SkipCounter`) and implement :meth:`_load`. A file error
    is re-raised naming the sample, or, with ``skip_bad_samples``, warned about, counted, and the
    sample dropped (``None``; :func:`collate_samples` leaves it out).
    """

    samples: list[tuple[str, int, int]]
    split: str
    skip_bad_samples: bool

    def __len__(self) -> int:
        return len(self.samples)

    def sample_id(self, index: int) -> str:
        seq, src, tgt = self.samples[index]
        return f"{self.name}/{self.split}/{seq}/{src}->{tgt}"

    def _load(self, index: int) -> dict[str, Any]:
        raise NotImplementedError

    def __getitem__(self, index: int) -> dict[str, Any] | None:
        from mfg_lightning.data.flow_io import DataFileError

        try:
            return self._load(index)
        except DataFileError as err:
            if not self.skip_bad_samples:
                raise DataFileError(f"{self.sample_id(index)}: {err}") from err
            self.skipped.add()
            warnings.warn(f"skipping {self.sample_id(index)}: {err}", stacklevel=2)
            return None


def collate_samples(batch: Sequence[dict[str, Any] | None]) -> dict[str, Any] | None:
    """Collate samples, dropping ``None`` (samples skipped by ``skip_bad_samples``).

    Returns None when every sample of the batch was skipped.
    """
    kept = [s for s in batch if s is not None]
    if not kept:
        return None
    return default_collate(kept)


def seed_worker(worker_id: int) -> None:
    """DataLoader ``worker_init_fn``: seed numpy and ``random`` from torch's per-worker seed."""
    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)
    import random

    random.seed(seed)


class UnpaddedDistributedSampler(DistributedSampler):
    """Evaluation sharding without padding: rank ``r`` of ``W`` gets indices ``r, r + W, …``.

    torch's ``DistributedSampler`` pads the last round with repeated samples so that every rank
    has as many; a repeated sample is then counted twice by every mean and sum, and DDP metrics
    differ from a single process's. Evaluation needs no equal shards (no gradients are
    synchronised), so this sampler gives every sample to exactly one rank. Being a
    ``DistributedSampler``, Lightning keeps it instead of injecting its own.
    """

    def __init__(self, dataset: Dataset, num_replicas: int, rank: int) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False)
        self.num_samples = len(range(rank, len(dataset), num_replicas))  # type: ignore[arg-type]
        self.total_size = len(dataset)  # type: ignore[arg-type]

    def __iter__(self):
        return iter(range(self.rank, self.total_size, self.num_replicas))

    def __len__(self) -> int:
        return self.num_samples


class MFGDataModule(L.LightningDataModule):
    """Base DataModule.

    Args:
        height, width: the model's input resolution in pixels; every sample is delivered at it.
        batch_size: training batch size (the paper trains with 1).
        eval_batch_size: validation and test batch size.
        num_workers: DataLoader worker processes (0: load in the main process).
        seed: seed of the training shuffle (the sample content has its own seeds).
        pin_memory: pin host memory for faster GPU transfer.
        persistent_workers: keep workers alive between epochs (only with ``num_workers > 0``).
    """

    def __init__(
        self,
        height: int = 48,
        width: int = 128,
        batch_size: int = 16,
        eval_batch_size: int = 32,
        num_workers: int = 0,
        seed: int = 0,
        pin_memory: bool = False,
        persistent_workers: bool = False,
    ) -> None:
        super().__init__()
        if height <= 0 or width <= 0:
            raise ValueError(
                f"dataset.height and dataset.width must be positive, got {height}×{width}"
            )
        if batch_size <= 0 or eval_batch_size <= 0:
            raise ValueError("dataset.batch_size and dataset.eval_batch_size must be positive")
        self.height, self.width = height, width
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size
        self.num_workers = num_workers
        self.seed = seed
        self.pin_memory = pin_memory
        self.persistent_workers = persistent_workers and num_workers > 0
        self.datasets: dict[str, MotionDataset] = {}

    # -- to implement ------------------------------------------------------------------------

    def build_dataset(self, split: str) -> MotionDataset:
        """Build the dataset of ``split`` (one of ``train``, ``val``, ``test``)."""
        raise NotImplementedError

    # -- shared ------------------------------------------------------------------------------

    def setup(self, stage: str | None = None) -> None:
        wanted = {
            "fit": ("train", "val"),
            "validate": ("val",),
            "test": ("test",),
            "predict": ("test",),
            None: SPLITS,
        }[stage]
        for split in wanted:
            if split not in self.datasets:
                self.datasets[split] = self.dataset(split)

    def dataset(self, split: str) -> MotionDataset:
        """The dataset of ``split``, built on first use; an empty split is an error."""
        if split not in self.datasets:
            ds = self.build_dataset(split)
            if len(ds) == 0:
                raise EmptySplitError(
                    f"the {split} split of {type(self).__name__} has no samples; "
                    "check dataset.data_root and the sequence lists"
                )
            self.datasets[split] = ds
        return self.datasets[split]

    def _loader(self, split: str, shuffle: bool, batch_size: int) -> DataLoader:
        generator = torch.Generator().manual_seed(self.seed) if shuffle else None
        dataset = self.dataset(split)
        sampler = None
        if not shuffle and dist.is_available() and dist.is_initialized():
            # Every evaluation sample on exactly one process: DDP metrics equal one process's.
            sampler = UnpaddedDistributedSampler(dataset, dist.get_world_size(), dist.get_rank())
        return DataLoader(
            dataset,
            batch_size=batch_size,
            shuffle=shuffle,
            sampler=sampler,
            num_workers=self.num_workers,
            collate_fn=collate_samples,
            worker_init_fn=seed_worker,
            generator=generator,
            pin_memory=self.pin_memory,
            persistent_workers=self.persistent_workers,
            drop_last=False,
        )

    def train_dataloader(self) -> DataLoader:
        # Epoch e's order depends on (seed, e) only, and the position is checkpointed mid-epoch.
        return ResumableDataLoader.like(
            self._loader("train", shuffle=True, batch_size=self.batch_size), seed=self.seed
        )

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False, batch_size=self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False, batch_size=self.eval_batch_size)

    def mean_motion(self, split: str = "train") -> tuple[torch.Tensor, torch.Tensor]:
        """Mean egomotion ``(t, ω)`` over a split: the 'always predict the mean' baseline.

        Returns:
            ``(t, ω)``, ``(3,)`` each (metres and radians per frame).
        """
        t, w = geometry.pose_to_motion(self.dataset(split).relative_poses().double())
        return t.mean(0).float(), w.mean(0).float()
