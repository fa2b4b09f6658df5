"""A training split held whole on the training device, its batches gathered there by index.

Every dataset of this project hands out the same sample for the same index in every epoch (a
rendered world's exact flow is a pure function of its pair, a flow cache is read back unchanged),
so after one pass there is nothing left for a loader to compute: only batches to gather. With
``dataset.device_resident=true`` the training split is loaded once (through the split's ordinary
loader, with its workers) into one tensor per key on the training device, and each batch is then
an ``index_select`` per key there: no worker processes, no collation, no copy to the device, no
pinned memory (``mfg_lightning.data.workers``' ``/dev/shm`` question does not arise).

The order is the resumable one (:class:`~mfg_lightning.data.resumable_loader.EpochShuffleSampler`,
rank-aware): the same batches as the ordinary loader, in the same order, resumed mid-epoch alike;
``tests/test_device_resident.py`` compares them batch for batch. The split must fit:
``dataset.device_resident_mb`` bounds it (a larger one keeps the ordinary loader, with a
warning), and on a GPU so does half of its free memory.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from mfg_lightning.data.resumable_loader import EpochShuffleSampler, ResumableDataLoader

log = logging.getLogger(__name__)

__all__ = ["DeviceBatches", "DeviceResidentLoader", "fits_on_device"]


class DeviceBatches:
    """A split's samples as tensors ``(N, …)`` on one device, and their other fields (sample ids,
    …) as arrays on the host, gathered by index.

    Args:
        tensors: key → ``(N, …)`` tensor, all on one device.
        others: key → ``(N,)`` object array (fields a batch carries as lists).
    """

    def __init__(self, tensors: dict[str, Tensor], others: dict[str, np.ndarray]) -> None:
        sizes = {len(v) for v in [*tensors.values(), *others.values()]}
        if len(sizes) != 1:
            raise ValueError(f"the fields of a device-resident split differ in length: {sizes}")
        self.tensors, self.others = tensors, others
        self.n = sizes.pop()

    @classmethod
    def load(cls, loader: DataLoader, device: torch.device) -> DeviceBatches:
        """Every batch of ``loader`` (in its order; unshuffled, the dataset's), stacked per key,
        the tensors moved to ``device``. A batch key seen in some batches only, or a batch
        with unreadable samples (None), is an error: the split would not be the dataset."""
        parts: dict[str, list[Any]] = {}
        for b, batch in enumerate(loader):
            if batch is None or (parts and batch.keys() != parts.keys()):
                raise ValueError(
                    f"batch {b} of the training split differs from the first (unreadable "
                    "samples, or other fields): dataset.device_resident needs every sample"
                )
            for key, value in batch.items():
                parts.setdefault(key, []).append(value)
        tensors, others = {}, {}
        for key, values in parts.items():
            if isinstance(values[0], Tensor):
                tensors[key] = torch.cat(values).to(device)
            else:
                flat = [x for v in values for x in v]
                others[key] = np.empty(len(flat), dtype=object)
                others[key][:] = flat
        return cls(tensors, others)

    @property
    def nbytes(self) -> int:
        return sum(t.nbytes for t in self.tensors.values())

    def gather(self, on_device: Tensor, on_host: np.ndarray) -> dict[str, Any]:
        """The batch of these indices (the same ones on the device and on the host)."""
        batch: dict[str, Any] = {k: t.index_select(0, on_device) for k, t in self.tensors.items()}
        for key, values in self.others.items():
            batch[key] = values[on_host].tolist()
        return batch


def fits_on_device(nbytes: int, device: torch.device, most_mb: float) -> tuple[bool, str]:
    """Whether ``nbytes`` may be held on ``device``: at most ``most_mb`` megabytes, and on a GPU
    at most half its free memory. Returns the answer and why, in words."""
    mb = nbytes / 2**20
    if mb > most_mb:
        return False, f"{mb:.0f} MB, above dataset.device_resident_mb={most_mb:g}"
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        if nbytes > free / 2:
            return False, f"{mb:.0f} MB, above half the GPU's {free / 2**20:.0f} MB free"
    return True, f"{mb:.0f} MB"


class DeviceResidentLoader(ResumableDataLoader):
    """The training loader of a split held on the device (see the module's docstring).

    The samples are loaded at the first iteration, by ``source`` (the split's ordinary,
    unshuffled loader); then every pass gathers its batches on the device, in the order of
    :class:`~mfg_lightning.data.resumable_loader.EpochShuffleSampler`.

    Args:
        dataset: the split (its length sets the order; its samples are read through ``source``).
        source: a loader of ``dataset`` in its own order (workers welcome).
        device: where the split is held.
        seed, batch_size, num_replicas, rank: as :class:`ResumableDataLoader`'s.
    """

    def __init__(
        self,
        dataset: Dataset,
        *,
        source: DataLoader,
        device: torch.device,
        seed: int,
        batch_size: int | None = 1,
        num_replicas: int | None = None,
        rank: int | None = None,
        **kwargs: Any,
    ) -> None:
        kwargs.pop("num_workers", None)  # no workers: the batches are gathered here
        super().__init__(dataset, seed=seed, batch_size=batch_size, num_replicas=num_replicas,
                         rank=rank, num_workers=0, **kwargs)  # fmt: skip
        self.source, self.device = source, torch.device(device)
        self.store: DeviceBatches | None = None

    def _batches(self, order: EpochShuffleSampler) -> Iterator[Any]:
        if self.store is None:
            store = DeviceBatches.load(self.source, self.device)
            if store.n != len(self.dataset):  # type: ignore[arg-type]
                raise ValueError(
                    f"dataset.device_resident: {len(self.dataset) - store.n} of the "  # type: ignore[arg-type]
                    f"{len(self.dataset)} training samples did not load (skipped as unreadable): "  # type: ignore[arg-type]
                    "a split held on the device needs every sample; fix them or set "
                    "dataset.device_resident=false"
                )
            self.store = store
            log.info(
                "training split on %s: %d samples, %.0f MB, gathered by index from now on",
                self.device, self.store.n, self.store.nbytes / 2**20,
            )  # fmt: skip
        host = np.fromiter(order, dtype=np.int64)  # this pass's indices (a resumed one's rest)
        on_device = torch.from_numpy(host).to(self.device)  # one copy per pass
        size = int(self.batch_size or 1)
        for start in range(0, len(host), size):
            yield self.store.gather(on_device[start : start + size], host[start : start + size])
