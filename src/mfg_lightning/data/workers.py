"""Loader workers: how many the cores allow, and how many ``/dev/shm`` holds.

A DataLoader worker hands its batches to the training process through shared memory
(``/dev/shm`` on Linux). Docker gives a container 64 MB there by default, and a worker that runs
out of it dies with a bus error, which ends the run with an unhelpful message. :func:`plan_workers`
says how many workers fit; :class:`~mfg_lightning.data.base.MFGDataModule` uses it before its
first loader with workers: too few megabytes give a warning that says what to change, and the run
goes on with the workers that fit (0: loading in the main process).

How many workers the cores allow is :func:`mfg_lightning.core.machine.loader_workers` (the
``${loader_workers:n}`` resolver of ``conf/trainer/gpu.yaml`` and ``ddp_gpu.yaml``).
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

__all__ = ["PREFETCH", "SHM", "SHM_HEADROOM", "ShmPlan", "plan_workers", "sample_bytes"]

#: torch DataLoader's default ``prefetch_factor`` (batches each worker keeps ready)
PREFETCH = 2
#: shared memory must hold this many times the loader's batches in flight (the workers' tensors
#: stay there until the main process has copied them, and a persistent validation pool holds its
#: own)
SHM_HEADROOM = 1.5
#: where the workers' tensors go on Linux
SHM = Path("/dev/shm")


@dataclass
class ShmPlan:
    """The loader workers shared memory can hold, and what to say about it.

    Attributes:
        workers: the workers that fit (at most the asked ones).
        note: one sentence: enough, or too small and what to change.
        enough: all the asked workers fit.
    """

    workers: int
    note: str
    enough: bool


def sample_bytes(sample: dict[str, Any]) -> int:
    """Bytes of the tensors of one sample (what a worker puts in shared memory)."""
    return sum(v.nbytes for v in sample.values() if isinstance(v, torch.Tensor))


def plan_workers(
    workers: int,
    batch: int,
    eval_batch: int,
    per_sample: int,
    shm: Path = SHM,
    processes: int = 1,
) -> ShmPlan:
    """How many loader workers fit in ``shm``: each keeps :data:`PREFETCH` batches of the train
    and of the evaluation loader in flight there; :data:`SHM_HEADROOM` times that must be free.

    Args:
        workers: the workers asked for (``dataset.num_workers``), per training process.
        batch, eval_batch: the training and evaluation batch sizes.
        per_sample: bytes of one sample's tensors (:func:`sample_bytes`).
        shm: the shared-memory file system.
        processes: the training processes of this machine sharing it (DDP: one per device);
            each gets its share.
    """
    if workers <= 0:
        return ShmPlan(0, "no loader workers: nothing goes through /dev/shm", True)
    per_worker = PREFETCH * (batch + eval_batch) * per_sample
    need = workers * per_worker
    try:
        free = shutil.disk_usage(shm).free // max(1, processes)
    except OSError:
        free = 0
    mb = 2**20
    if free >= SHM_HEADROOM * need:
        return ShmPlan(
            workers,
            f"{shm}: {free / mb:.0f} MB free, {workers} workers keep ~{need / mb:.0f} MB in "
            "flight: enough",
            True,
        )
    keep = max(0, min(workers, int(free // (SHM_HEADROOM * per_worker))))
    size = math.ceil(SHM_HEADROOM * need / mb / 64) * 64
    return ShmPlan(
        keep,
        f"{shm}: {free / mb:.0f} MB free, too small for {workers} loader workers (~{need / mb:.0f}"
        f" MB in flight: {workers} × {PREFETCH} prefetched × ({batch} + {eval_batch}) samples × "
        f"{per_sample / 1024:.0f} KB, ×{SHM_HEADROOM} headroom): running with "
        f"dataset.num_workers={keep}. To keep {workers}, give the container more shared memory "
        f"(docker run --shm-size={size}m, or in Kubernetes an emptyDir with medium: Memory "
        "mounted on /dev/shm)",
        False,
    )
