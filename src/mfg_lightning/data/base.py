"""The shared base of every dataset and DataModule: splits, loaders, collation, worker seeding.
What every dataset read from files does the same way is in :mod:`mfg_lightning.data.file_datasets`.

A new dataset is its layout plus its sample loader: a
:class:`~mfg_lightning.data.file_datasets.FileMotionDataset` subclass that checks its root
(:func:`~mfg_lightning.data.file_datasets.check_data_root`), fills ``samples`` with
``(sequence, source, target)`` triples (:func:`portion_frames` for the training head /
validation tail of a sequence), reports index problems with
:meth:`~mfg_lightning.data.file_datasets.FileMotionDataset.report_problems` and loads one sample
in ``_load``; and an :class:`MFGDataModule` subclass whose :meth:`~MFGDataModule.build_dataset`
picks the sequences of a split (:func:`split_sequences`). Errors and the skip counter are in
:mod:`mfg_lightning.core.data_errors`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, DistributedSampler, default_collate

from mfg_lightning.core import geometry
from mfg_lightning.core.data_errors import report_skipped
from mfg_lightning.data import transforms
from mfg_lightning.data.device_resident import DeviceResidentLoader, fits_on_device
from mfg_lightning.data.resumable_loader import ResumableDataLoader
from mfg_lightning.data.workers import SHM, plan_workers, sample_bytes

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
#: The frames of a sequence a split's samples come from: every frame (``all``), the training
#: head (``train``) or the validation tail (``val``) of :func:`portion_frames`.
PORTIONS = ("all", "train", "val")
#: The portion of its sequences each split reads (validation is the tail of training sequences).
SPLIT_PORTION = {"train": "train", "val": "val", "test": "all"}


class EmptySplitError(ValueError):
    """A split has no samples (a wrong ``data_root`` or sequence list, usually)."""


class MotionDataset(Dataset):
    """A map-style dataset of samples in the schema of :mod:`mfg_lightning.data.sample`.

    Subclasses set ``height``, ``width`` and ``name``, fill ``samples`` with one
    ``(sequence, source frame, target frame)`` triple per sample, sorted by sequence then source
    frame, and implement ``__getitem__`` and :meth:`relative_poses`.
    """

    name: str = "dataset"
    height: int
    width: int
    samples: list[tuple[str, int, int]]

    def __len__(self) -> int:
        return len(self.samples)

    def relative_poses(self) -> torch.Tensor:
        """``(N, 4, 4)`` ground-truth relative pose ``T_src,tgt`` of every sample, in order.

        Must not decode flow: it is used for statistics over a whole split (the mean-motion
        baseline, dataset checks) and should be fast.
        """
        raise NotImplementedError

    def sequences(self) -> dict[str, list[int]]:
        """Sample indices grouped by sequence, each list in frame order (for trajectories)."""
        out: dict[str, list[int]] = {}
        for i, (seq, _, _) in enumerate(self.samples):
            out.setdefault(seq, []).append(i)
        return out


def portion_frames(n_frames: int, portion: str, val_fraction: float, span: int) -> range:
    """Frames ``0 … n_frames − 1`` of a sequence, its training head or its validation tail.

    Args:
        n_frames: frames in the sequence.
        portion: ``all``, ``train`` or ``val`` (:data:`PORTIONS`).
        val_fraction: the validation tail's fraction
            (:func:`~mfg_lightning.data.transforms.holdout_ranges`).
        span: the largest ``|offset|`` of a sample, so that no sample straddles the cut.
    """
    if portion == "all":
        return range(n_frames)
    train, val = transforms.holdout_ranges(n_frames, val_fraction, span)
    return train if portion == "train" else val


def normalize_sequence(seq: Any) -> str:
    """``9``, ``"9"`` or ``"09"`` → ``"09"`` (YAML reads unquoted ``09`` as a number)."""
    text = str(seq).strip()
    return f"{int(text):02d}" if text.isdigit() else text


def check_offsets(offsets: Sequence[int]) -> list[int]:
    """``dataset.offsets`` (target frame = source frame + offset) as distinct non-zero ints."""
    out = [int(o) for o in offsets]
    if not out or 0 in out or len(set(out)) != len(out):
        raise ValueError(f"dataset.offsets must be distinct non-zero integers, got {out}")
    return out


def check_split(train: Sequence[str], test: Sequence[str], val_fraction: float, unit: str) -> float:
    """Refuse a split whose training and test ``unit`` (sequences, worlds) overlap or whose
    ``val_fraction`` is not in (0, 1); return the fraction."""
    overlap = sorted(set(train) & set(test))
    if overlap:
        raise ValueError(f"{unit} {overlap} are in both the training and the test split")
    if not 0.0 < float(val_fraction) < 1.0:
        raise ValueError(
            f"dataset.val_fraction must be in (0, 1) (a tail of each training "
            f"{unit.rstrip('s')}), got {val_fraction}"
        )
    return float(val_fraction)


def split_sequences(split: str, train: Sequence[str], test: Sequence[str]) -> tuple[list, str]:
    """The sequences of ``split`` (``train``, ``val``: the training ones; ``test``) and the
    portion of each it reads (:data:`SPLIT_PORTION`)."""
    if split not in SPLIT_PORTION:
        raise ValueError(f"unknown split {split!r}")
    return list(test if split == "test" else train), SPLIT_PORTION[split]


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

    A rank whose shard is empty (a split smaller than the number of ranks) gets one index
    :data:`EMPTY_SHARD`, which :class:`EvaluationShard` turns into a batch of None: Lightning
    skips the whole evaluation loop, epoch-end hooks included, on a rank without batches, and
    those hooks hold the metrics' collectives that every rank must join.
    """

    def __init__(self, dataset: Dataset, num_replicas: int, rank: int) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False)
        self.num_samples = len(range(rank, len(dataset), num_replicas))  # type: ignore[arg-type]
        self.total_size = len(dataset)  # type: ignore[arg-type]

    def __iter__(self):
        if not self.num_samples:
            return iter([EMPTY_SHARD])
        return iter(range(self.rank, self.total_size, self.num_replicas))

    def __len__(self) -> int:
        return max(self.num_samples, 1)


#: The index :class:`UnpaddedDistributedSampler` gives a rank with no sample.
EMPTY_SHARD = -1


class EvaluationShard(Dataset):
    """An evaluation dataset seen through :class:`UnpaddedDistributedSampler`: sample ``i`` is
    the dataset's, :data:`EMPTY_SHARD` is None (dropped by :func:`collate_samples`, so the
    rank's one batch is None, which the module and the batch checks skip)."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Any:
        return None if index == EMPTY_SHARD else self.dataset[index]


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
        device_resident: hold the training split whole on the training device once it has been
            read, and gather its batches there by index (no workers, no copies:
            :mod:`mfg_lightning.data.device_resident`).
        device_resident_mb: the largest split held so (MB); a larger one keeps the ordinary
            loader, with a warning.
    """

    def __init__(
        self,
        height: int = 48,
        width: int = 128,
        batch_size: int = 16,
        eval_batch_size: int = 64,
        num_workers: int = 0,
        seed: int = 0,
        pin_memory: bool = False,
        persistent_workers: bool = False,
        device_resident: bool = False,
        device_resident_mb: float = 8192,
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
        self.device_resident = bool(device_resident)
        self.device_resident_mb = float(device_resident_mb)
        self.datasets: dict[str, MotionDataset] = {}
        # the workers /dev/shm holds (None: not checked yet; mfg_lightning.data.workers)
        self._shm_workers: int | None = None
        self._sample_bytes: dict[str, int] = {}  # split -> bytes of a sample's tensors

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

    def _loader(
        self,
        split: str,
        shuffle: bool,
        batch_size: int,
        num_workers: int | None = None,
        persistent_workers: bool | None = None,
        drop_last: bool = False,
    ) -> DataLoader:
        """The loader of ``split``; ``num_workers``, ``persistent_workers``: the DataModule's
        unless given (a split's own, e.g. one persistent worker that keeps its sample cache)."""
        workers = self.num_workers if num_workers is None else num_workers
        workers = self._workers_that_fit(workers, split)
        if persistent_workers is None:
            persistent_workers = self.persistent_workers
        generator = torch.Generator().manual_seed(self.seed) if shuffle else None
        dataset = self.dataset(split)
        sampler = None
        if not shuffle and dist.is_available() and dist.is_initialized():
            # Every evaluation sample on exactly one process: DDP metrics equal one process's.
            sampler = UnpaddedDistributedSampler(dataset, dist.get_world_size(), dist.get_rank())
            dataset = EvaluationShard(dataset)
        return DataLoader(
            dataset,
            batch_size=batch_size,
            shuffle=shuffle,
            sampler=sampler,
            num_workers=workers,
            collate_fn=collate_samples,
            worker_init_fn=seed_worker,
            generator=generator,
            pin_memory=self.pin_memory,
            persistent_workers=persistent_workers and workers > 0,
            drop_last=drop_last,
        )

    def _bytes_per_sample(self, split: str) -> int:
        """Bytes of the tensors of a sample of ``split`` (its first, read once)."""
        if split not in self._sample_bytes:
            self._sample_bytes[split] = sample_bytes(self.dataset(split)[0])
        return self._sample_bytes[split]

    def _workers_that_fit(self, workers: int, split: str) -> int:
        """``workers``, or fewer where shared memory (``/dev/shm``) cannot hold their batches
        (:func:`mfg_lightning.data.workers.plan_workers`, sized by a sample of ``split``):
        checked once, with a warning that says what to change, since a worker that runs out of
        it dies with a bus error."""
        if workers <= 0 or not SHM.is_dir():  # not Linux: no /dev/shm to run out of
            return workers
        if self._shm_workers is None:
            try:
                per_sample = self._bytes_per_sample(split)
            except Exception as err:  # the loader will name a bad sample; not this check
                log.debug("/dev/shm not checked: the first %s sample failed (%s)", split, err)
                return workers
            # the node's processes share /dev/shm (DDP: one per device)
            trainer = self.trainer
            local = max(1, int(trainer.num_devices)) if trainer is not None else 1
            plan = plan_workers(workers, self.batch_size, self.eval_batch_size, per_sample,
                                processes=local)  # fmt: skip
            if not plan.enough:
                log.warning("%s", plan.note)
            self._shm_workers = plan.workers
        return min(workers, self._shm_workers)

    def _device_resident_loader(self) -> DataLoader | None:
        """The training loader of ``device_resident=true``, or None (with a warning) where the
        split does not fit (:func:`~mfg_lightning.data.device_resident.fits_on_device`; under
        DDP every process takes the answer of all: one that does not fit decides for all)."""
        trainer = self.trainer  # None outside a fit (a direct call)
        device = trainer.strategy.root_device if trainer is not None else torch.device("cpu")
        dataset = self.dataset("train")
        try:
            nbytes = len(dataset) * self._bytes_per_sample("train")  # type: ignore[arg-type]
            fits, why = fits_on_device(nbytes, device, self.device_resident_mb)
        except Exception as err:  # an unreadable first sample: the ordinary loader names it
            fits, why = False, f"its first sample did not load: {err}"
        if trainer is not None and trainer.world_size > 1:
            fits = bool(trainer.strategy.reduce_boolean_decision(fits, all=True))
            why = why if fits else f"{why}, or another process's split does not"
        if not fits:
            log.warning("dataset.device_resident: the training split does not fit (%s): "
                        "the ordinary loader trains it", why)  # fmt: skip
            return None
        # the whole split, in its own order, on every process (the order picks any index)
        workers = self._workers_that_fit(self.num_workers, "train")
        source = DataLoader(dataset, batch_size=self.eval_batch_size, shuffle=False,
                            num_workers=workers, collate_fn=collate_samples,
                            worker_init_fn=seed_worker)  # fmt: skip
        return DeviceResidentLoader(dataset, source=source, device=device, seed=self.seed,
                                    batch_size=self.batch_size, shuffle=True,
                                    collate_fn=collate_samples)  # fmt: skip

    def train_dataloader(self) -> DataLoader:
        """The device-resident loader where ``device_resident`` is set and the split fits,
        else :meth:`ordinary_train_loader`."""
        if self.device_resident and (loader := self._device_resident_loader()) is not None:
            return loader
        return self.ordinary_train_loader()

    def ordinary_train_loader(self) -> ResumableDataLoader:
        """The training loader that reads the dataset (a subclass adds its prefetch here)."""
        # Epoch e's order depends on (seed, e) only, and the position is checkpointed mid-epoch.
        return ResumableDataLoader.like(
            self._loader("train", shuffle=True, batch_size=self.batch_size), seed=self.seed
        )

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False, batch_size=self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False, batch_size=self.eval_batch_size)

    def teardown(self, stage: str | None = None) -> None:
        # How many bad samples each split skipped (skip_bad_samples), once the stage is over.
        report_skipped(self.datasets)

    def mean_motion(self, split: str = "train") -> tuple[torch.Tensor, torch.Tensor]:
        """Mean egomotion ``(t, ω)`` over a split: the 'always predict the mean' baseline.

        Returns:
            ``(t, ω)``, ``(3,)`` each (metres and radians per frame).
        """
        t, w = geometry.pose_to_motion(self.dataset(split).relative_poses().double())
        return t.mean(0).float(), w.mean(0).float()
