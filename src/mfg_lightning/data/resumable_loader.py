"""The training loader whose sample order resumes exactly mid-epoch, with one process or many.

Epoch ``e`` visits the samples in an order drawn from ``(seed, e)`` alone; under DDP each process
takes its strided share of that same order. The loader's place in the epoch is stored in every
checkpoint (Lightning saves the ``state_dict`` of any loader that has one), so a run resumed
mid-epoch skips exactly the batches it had already trained on, without loading them, and then
sees the same batches an uninterrupted run would have seen, on every process.

That place is only meaningful for the batches it was counted in: a run resumed inside an epoch
with another batch size, dataset or sampler (seed) than its checkpoint's is refused with one line
naming the key and both values (:class:`ResumeMismatchError`), unless the run says
``resume_restart_epoch=true`` (:func:`restarting_epochs`): then the interrupted epoch starts
again from its beginning with the new settings. Another number of processes restarts the epoch
too, with a warning (the order is the same, only its shares differ).
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import logging
import math
from collections.abc import Callable, Iterator
from typing import Any

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, DistributedSampler, Sampler

from mfg_lightning.core.errors import UserError

log = logging.getLogger(__name__)

# resume_restart_epoch: a resume whose batches differ from the checkpoint's restarts the epoch
# instead of being refused (set around a run by restarting_epochs)
_RESTART_ON_CHANGE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "resume_restart_epoch", default=False
)


class ResumeMismatchError(UserError):
    """A resume inside an epoch whose batch size, dataset or sampler is not the checkpoint's:
    the saved place in the epoch counts other batches. One line naming the key and both
    values."""


@contextlib.contextmanager
def restarting_epochs(enabled: bool) -> Iterator[None]:
    """Within the block, a resume whose batches differ from the checkpoint's
    (:class:`ResumeMismatchError`) restarts the interrupted epoch instead, with a warning
    (``enabled``: the run's ``resume_restart_epoch``). The entry points wrap their run in it."""
    token = _RESTART_ON_CHANGE.set(bool(enabled))
    try:
        yield
    finally:
        _RESTART_ON_CHANGE.reset(token)


def refuse_other_batches(place: dict[str, Any], batch_size: int) -> None:
    """Refuse, before anything of a resumed run is written, a resume inside an epoch whose
    batch size differs from the one the checkpoint's saved ``place`` counts in (the loader's own
    check, :meth:`ResumableDataLoader.load_state_dict`, sees the dataset and sampler too, later).

    Raises:
        ResumeMismatchError: one line naming ``dataset.batch_size`` and both values.
    """
    saved, batches = place.get("batch_size"), int(place.get("batches", 0))
    inside = 0 < batches < int(place.get("length", batches + 1))
    if saved is None or int(saved) == int(batch_size) or not inside:
        return
    raise ResumeMismatchError(
        f"dataset.batch_size: the checkpoint was trained with {saved}, this run asks for "
        f"{batch_size}; the checkpoint stopped {batches} batches into epoch {place.get('epoch')}: "
        "resume with the checkpoint's settings, or with resume_restart_epoch=true to restart "
        "that epoch from its beginning with this run's"
    )


def epoch_seed(seed: int, epoch: int, stream: str = "order") -> int:
    """A 63-bit seed derived from ``(seed, epoch, stream)`` alone (no global RNG, no call order).

    Distinct ``stream`` names give independent seeds for the sample order and the workers.
    """
    digest = hashlib.blake2b(f"{seed}/{epoch}/{stream}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & (2**63 - 1)


class EpochShuffleSampler(DistributedSampler):
    """Indices ``0 … n − 1`` in a random order that depends only on ``(seed, epoch)``; with ``W``
    processes, process ``r`` takes positions ``r, r + W, r + 2W, …`` of it.

    Lightning calls :meth:`set_epoch` at the start of every training epoch, so epoch ``e`` has the
    same order in any process, resumed or not. Under DDP the order is padded to a multiple of
    ``W`` by repeating its first indices, as torch's ``DistributedSampler`` pads: every process
    takes as many steps, which DDP's collectives need. Being a ``DistributedSampler``, it is kept
    by Lightning, which would otherwise put in its own (whose place in an epoch is not saved).

    Args:
        n: dataset length.
        seed: the run's seed (``dataset.seed``).
        num_replicas: the number of processes ``W``; None: the process group's size (1 without
            one).
        rank: this process's rank ``r``; None: the process group's (0 without one).

    Attributes:
        on_order: None, or called with this process's indices of each pass (a resumed pass: those
            left) before the first is handed out: a prefetcher follows the order with it
            (:class:`~mfg_lightning.data.prefetch.Prefetcher`).
    """

    def __init__(
        self, n: int, seed: int, num_replicas: int | None = None, rank: int | None = None
    ) -> None:
        replicas, rank = process_group(num_replicas, rank)
        super().__init__(range(int(n)), num_replicas=replicas, rank=rank, shuffle=True, seed=seed)
        self.n = int(n)
        self.seed = int(seed)
        self._skip = 0
        self.on_order: Callable[[list[int]], None] | None = None

    def skip_next(self, count: int) -> None:
        """Start the next pass ``count`` positions into the epoch's permutation (once), counted
        over every process: ``batches × batch_size × W`` skips that many batches of each."""
        self._skip = max(0, int(count))

    def permutation(self, epoch: int) -> torch.Tensor:
        """``(n,)`` int64: the order of epoch ``epoch`` (the same in every process)."""
        generator = torch.Generator().manual_seed(epoch_seed(self.seed, epoch))
        return torch.randperm(self.n, generator=generator)

    def shard(self, epoch: int, skip: int = 0) -> list[int]:
        """This process's indices of epoch ``epoch`` after the first ``skip`` positions of its
        permutation. What is left is padded to a multiple of ``W`` with the permutation's first
        indices, so that a pass resumed at a multiple of ``W`` continues every process's share
        exactly as the uninterrupted pass would."""
        order = self.permutation(epoch)
        rest = order[skip:]
        pad = (-len(rest)) % self.num_replicas
        if pad:
            rest = torch.cat([rest, order[torch.arange(pad) % self.n]])
        return rest[self.rank :: self.num_replicas].tolist()

    def __len__(self) -> int:
        return math.ceil(self.n / self.num_replicas)

    def __iter__(self) -> Iterator[int]:
        skip, self._skip = self._skip, 0
        order = self.shard(self.epoch, skip)
        if self.on_order is not None:
            self.on_order(order)
        return iter(order)


def process_group(num_replicas: int | None = None, rank: int | None = None) -> tuple[int, int]:
    """``(W, r)``: the given values, else the initialised process group's size and rank, else
    ``(1, 0)``."""
    grouped = dist.is_available() and dist.is_initialized()
    if num_replicas is None:
        num_replicas = dist.get_world_size() if grouped else 1
    if rank is None:
        rank = dist.get_rank() if grouped else 0
    return int(num_replicas), int(rank)


class ResumableDataLoader(DataLoader):
    """A shuffling training ``DataLoader`` whose position in the epoch is checkpointed.

    ``state_dict()`` is ``{"epoch", "batches", "samples", "processes", "length", "batch_size",
    "dataset", "sampler"}``: the epoch being iterated, how many of its batches each process has
    been handed, the dataset length, the number of processes, and what those batches are: the
    epoch's batches per process, their size, the dataset's class and the sampler with its
    seed. Lightning stores it in the fit loop's checkpoint state and calls
    :meth:`load_state_dict` before iterating again on resume; the next pass of that epoch then
    skips the batches already trained on at the index level (no sample is loaded for them), on
    every process (they all took as many; the checkpoint is rank 0's). A pass of any other epoch
    starts from its beginning, and so does the saved epoch when the number of processes changed
    (warned). A saved place inside an epoch whose batch size, dataset or sampler differs is
    refused (:class:`ResumeMismatchError`), or restarts its epoch under
    :func:`restarting_epochs`.

    Iteration is lazy: the permutation, the worker seed and (with ``num_workers > 0``) the
    workers are set up when the first batch is requested, which is after Lightning has called
    ``set_epoch`` for the epoch about to run.

    Under DDP each process iterates its share of the epoch's order (:class:`EpochShuffleSampler`,
    a ``DistributedSampler`` that Lightning keeps). Lightning rebuilds a loader with a sampler of
    its own for ``overfit_batches`` (sequential); given a ``sampler`` or ``batch_sampler``, this
    class is a plain ``DataLoader`` of that sampler, and its state is empty (that order is not
    resumed mid-epoch).

    Args:
        dataset: a map-style dataset.
        seed: seed of the sample order (epoch ``e`` uses :func:`epoch_seed` ``(seed, e)``) and of
            the worker processes.
        batch_size: samples per batch (per process).
        num_replicas, rank: the number of processes and this one's rank; None: the process
            group's (one process without one).
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
        num_replicas: int | None = None,
        rank: int | None = None,
        shuffle: bool | None = None,
        sampler: Sampler | None = None,
        batch_sampler: Sampler | None = None,
        generator: torch.Generator | None = None,
        **kwargs: Any,
    ) -> None:
        self.order: EpochShuffleSampler | None = None
        if sampler is None and batch_sampler is None:
            n = len(dataset)  # type: ignore[arg-type]
            self.order = EpochShuffleSampler(n, seed, num_replicas, rank)
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
        """A resumable loader with the dataset, batch size and worker settings of ``loader``,
        sharded over the process group when there is one."""
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
            # Tells Lightning this loader shuffles, should it rebuild it with a sampler of its own.
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
        # Skipping whole batches = skipping batch_size indices of each process's share, i.e.
        # batch_size × W positions of the epoch's order (only the last batch of an epoch can be
        # short, and a skip never reaches past it).
        order.skip_next(skip * int(self.batch_size or 1) * order.num_replicas)
        assert self.generator is not None
        self.generator.manual_seed(epoch_seed(order.seed, epoch, "workers"))
        self._epoch, self._position = epoch, skip
        for batch in self._batches(order):
            self._position += 1
            yield batch

    def _batches(self, order: EpochShuffleSampler) -> Iterator[Any]:
        """The pass's batches, in ``order`` (a subclass may gather them otherwise:
        :class:`~mfg_lightning.data.device_resident.DeviceResidentLoader`)."""
        return DataLoader.__iter__(self)

    def state_dict(self) -> dict[str, Any]:
        if self.order is None:
            return {}
        # restored but not iterated yet (_pending): still at the saved place
        epoch, batches = (self._epoch, self._position) if self._pending is None else self._pending
        return {
            "epoch": epoch,
            "batches": batches,
            "samples": self.order.n,
            "processes": self.order.num_replicas,
            # what the place is counted in (checked on resume): batches of an epoch, their size,
            # the dataset they come from and the sampler (its seed) that orders them
            "length": len(self),
            "batch_size": int(self.batch_size or 1),
            "dataset": type(self.dataset).__name__,
            "sampler": f"{type(self.order).__name__}(seed={self.order.seed})",
        }

    def _differences(self, state: dict[str, Any]) -> list[str]:
        """``key: the checkpoint was trained with A, this run asks for B`` for each setting of
        the saved place that differs in this loader (those a checkpoint records: a checkpoint
        from before these checks has only the number of samples)."""
        now = self.state_dict()
        keys = {
            "batch_size": "dataset.batch_size",
            "samples": "dataset (training samples)",
            "dataset": "dataset",
            "sampler": "sampler (dataset.seed)",
        }
        return [
            f"{name}: the checkpoint was trained with {state[key]}, this run asks for {now[key]}"
            for key, name in keys.items()
            if key in state and state[key] != now[key]
        ]

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resume at the saved place (see the class's docstring).

        Raises:
            ResumeMismatchError: the place is inside an epoch and the batch size, the dataset
                or the sampler differs from the checkpoint's (not under
                :func:`restarting_epochs`).
        """
        if self.order is None or not state:
            return
        epoch, batches = int(state["epoch"]), int(state["batches"])
        differences = self._differences(state)
        # At an epoch's end (or start) nothing of the epoch is left to skip: the new settings
        # simply apply from the next one.
        inside = 0 < batches < int(state.get("length", batches + 1))
        if differences and inside and not _RESTART_ON_CHANGE.get():
            raise ResumeMismatchError(
                "; ".join(differences)
                + f"; the checkpoint stopped {batches} batches into epoch {epoch}: resume with "
                "the checkpoint's settings, or with resume_restart_epoch=true to restart that "
                "epoch from its beginning with this run's"
            )
        processes = int(state.get("processes", 1))  # a checkpoint from before DDP: 1 process
        if processes != self.order.num_replicas:
            differences.append(
                f"the checkpoint was written on {processes} process(es), this run has "
                f"{self.order.num_replicas}"
            )
        if differences and inside:
            log.warning("resuming at the start of epoch %d: %s", epoch, "; ".join(differences))
            self._pending = None
        else:
            if differences:
                log.info("resumed at an epoch's boundary: %s", "; ".join(differences))
            self._pending = (epoch, batches)
        self.order.set_epoch(epoch)
        self._epoch, self._position = epoch, 0
