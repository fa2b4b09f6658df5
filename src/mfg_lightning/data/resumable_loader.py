"""The training loader whose sample order resumes exactly mid-epoch.

Epoch ``e`` visits the samples in an order drawn from ``(seed, e)`` alone, and the loader's place
in the epoch is stored in every checkpoint (Lightning saves the ``state_dict`` of any loader that
has one), so a run resumed mid-epoch skips exactly the batches it had already trained on, without
loading them, and then sees the same batches an uninterrupted run would have seen.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable, Iterator
from typing import Any

import torch
from torch.utils.data import DataLoader, Dataset, Sampler

log = logging.getLogger(__name__)


def epoch_seed(seed: int, epoch: int, stream: str = "order") -> int:
    """A 63-bit seed derived from ``(seed, epoch, stream)`` alone (no global RNG, no call order).

    Distinct ``stream`` names give independent seeds for the sample order and the workers.
    """
    digest = hashlib.blake2b(f"{seed}/{epoch}/{stream}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & (2**63 - 1)


class EpochShuffleSampler(Sampler[int]):
    """Indices ``0 … n − 1`` in a random order that depends only on ``(seed, epoch)``.

    Lightning calls :meth:`set_epoch` at the start of every training epoch (as it does for a
    ``DistributedSampler``), so epoch ``e`` has the same order in any process, resumed or not.

    Args:
        n: dataset length.
        seed: the run's seed (``dataset.seed``).

    Attributes:
        on_order: None, or called with the indices of each pass (a resumed pass: those left)
            before the first is handed out: a prefetcher follows the order with it
            (:class:`~mfg_lightning.data.sample_cache.Prefetcher`).
    """

    def __init__(self, n: int, seed: int) -> None:
        self.n = int(n)
        self.seed = int(seed)
        self.epoch = 0
        self._skip = 0
        self.on_order: Callable[[list[int]], None] | None = None

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def skip_next(self, count: int) -> None:
        """Start the next pass ``count`` indices into the epoch's permutation (once)."""
        self._skip = max(0, int(count))

    def permutation(self, epoch: int) -> torch.Tensor:
        """``(n,)`` int64: the order of epoch ``epoch``."""
        generator = torch.Generator().manual_seed(epoch_seed(self.seed, epoch))
        return torch.randperm(self.n, generator=generator)

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[int]:
        skip, self._skip = self._skip, 0
        order = self.permutation(self.epoch)[skip:].tolist()
        if self.on_order is not None:
            self.on_order(order)
        return iter(order)


class ResumableDataLoader(DataLoader):
    """A shuffling training ``DataLoader`` whose position in the epoch is checkpointed.

    ``state_dict()`` is ``{"epoch", "batches", "samples"}``: the epoch being iterated, how many
    of its batches have been handed out, and the dataset length. Lightning stores it in the
    fit loop's checkpoint state and calls :meth:`load_state_dict` before iterating again on
    resume; the next pass of that epoch then skips the batches already trained on at the index
    level (no sample is loaded for them). A pass of any other epoch starts from its beginning.

    Iteration is lazy: the permutation, the worker seed and (with ``num_workers > 0``) the
    workers are set up when the first batch is requested, which is after Lightning has called
    ``set_epoch`` for the epoch about to run.

    Lightning rebuilds a loader with a sampler of its own for ``overfit_batches`` (sequential)
    and for distributed training (a ``DistributedSampler``); given a ``sampler`` or
    ``batch_sampler``, this class is a plain ``DataLoader`` of that sampler, and its state is
    empty (that order is not resumed mid-epoch).

    Args:
        dataset: a map-style dataset.
        seed: seed of the sample order (epoch ``e`` uses :func:`epoch_seed` ``(seed, e)``) and of
            the worker processes.
        batch_size: samples per batch.
        shuffle, sampler, batch_sampler, generator: leave them out (this class shuffles); they
            are accepted for Lightning's rebuilding only.
        **kwargs: any other ``DataLoader`` argument.
    """

    def __init__(
        self,
        dataset: Dataset,
        *,
        seed: int,
        batch_size: int | None = 1,
        shuffle: bool | None = None,
        sampler: Sampler | None = None,
        batch_sampler: Sampler | None = None,
        generator: torch.Generator | None = None,
        **kwargs: Any,
    ) -> None:
        self.order: EpochShuffleSampler | None = None
        if sampler is None and batch_sampler is None:
            self.order = EpochShuffleSampler(len(dataset), seed)  # type: ignore[arg-type]
            sampler, shuffle, generator = self.order, None, torch.Generator()
        super().__init__(
            dataset,
            batch_size=batch_size,
            shuffle=shuffle,
            sampler=sampler,
            batch_sampler=batch_sampler,
            generator=generator,
            **kwargs,
        )
        self._epoch = 0  # epoch of the current (or last) pass
        self._position = 0  # batches handed out in that pass
        self._pending: tuple[int, int] | None = None  # (epoch, batches) restored from a checkpoint

    @classmethod
    def like(cls, loader: DataLoader, seed: int) -> ResumableDataLoader:
        """A resumable loader with the dataset, batch size and worker settings of ``loader``."""
        if loader.batch_size is None:
            raise ValueError("a loader with a custom batch_sampler cannot be made resumable")
        workers = loader.num_workers
        extra: dict[str, Any] = {}
        if workers > 0:
            extra = {
                "prefetch_factor": loader.prefetch_factor,
                "multiprocessing_context": loader.multiprocessing_context,
                "persistent_workers": loader.persistent_workers,
            }
        if hasattr(loader, "in_order"):
            extra["in_order"] = loader.in_order
        return cls(
            loader.dataset,
            seed=seed,
            # Tells Lightning this loader shuffles: a DistributedSampler it injects for DDP then
            # reshuffles every epoch (that order is not resumed mid-epoch).
            shuffle=True,
            batch_size=loader.batch_size,
            num_workers=workers,
            collate_fn=loader.collate_fn,
            pin_memory=loader.pin_memory,
            drop_last=loader.drop_last,
            timeout=loader.timeout,
            worker_init_fn=loader.worker_init_fn,
            pin_memory_device=loader.pin_memory_device,
            **extra,
        )

    def __iter__(self) -> Iterator[Any]:
        if self.order is None:
            return super().__iter__()
        return self._iterate(self.order)

    def _iterate(self, order: EpochShuffleSampler) -> Iterator[Any]:
        epoch = order.epoch
        skip = 0
        if self._pending is not None:
            saved_epoch, saved_batches = self._pending
            self._pending = None
            if saved_epoch == epoch:
                skip = min(saved_batches, len(self))
        # Skipping whole batches = skipping batch_size indices each (only the last batch of an
        # epoch can be short, and a skip never reaches past it).
        order.skip_next(skip * int(self.batch_size or 1))
        assert self.generator is not None
        self.generator.manual_seed(epoch_seed(order.seed, epoch, "workers"))
        self._epoch, self._position = epoch, skip
        for batch in super().__iter__():
            self._position += 1
            yield batch

    def state_dict(self) -> dict[str, int]:
        if self.order is None:
            return {}
        if self._pending is not None:  # restored but not iterated yet: still at the saved place
            epoch, batches = self._pending
            return {"epoch": epoch, "batches": batches, "samples": self.order.n}
        return {"epoch": self._epoch, "batches": self._position, "samples": self.order.n}

    def load_state_dict(self, state: dict[str, int]) -> None:
        if self.order is None or not state:
            return
        if int(state.get("samples", self.order.n)) != self.order.n:
            log.warning(
                "the training set has %d samples but the checkpoint was written with %d: "
                "resuming at the start of epoch %d",
                self.order.n,
                state["samples"],
                state["epoch"],
            )
            self._pending = None
        else:
            self._pending = (int(state["epoch"]), int(state["batches"]))
        self.order.set_epoch(int(state["epoch"]))
        self._epoch, self._position = int(state["epoch"]), 0
