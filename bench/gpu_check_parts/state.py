"""Part 0 of ``bench/gpu_check.py``: the process-wide state a GPU run depends on, set or
checked before the parts run: cuBLAS's deterministic workspace (:func:`set_cublas_workspace`),
torch's deterministic-algorithm and cuDNN flags, put back after each part
(:func:`flags_restored`), and the loader workers ``/dev/shm`` holds (:func:`plan_workers`)."""

from __future__ import annotations

import contextlib
import math
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

#: The value Lightning sets under ``trainer.deterministic=true``: cuBLAS's deterministic workspace.
CUBLAS_WORKSPACE = ":4096:8"
#: torch DataLoader's default ``prefetch_factor`` (batches each worker keeps ready)
PREFETCH = 2
#: /dev/shm must hold this many times the loader's batches in flight (the workers' tensors stay
#: there until the main process has copied them, and a persistent validation pool holds its own)
SHM_HEADROOM = 1.5


def set_cublas_workspace() -> str:
    """Set ``CUBLAS_WORKSPACE_CONFIG`` before anything uses cuBLAS; what was done, in words."""
    if os.environ.get("CUBLAS_WORKSPACE_CONFIG"):
        return f"`CUBLAS_WORKSPACE_CONFIG={os.environ['CUBLAS_WORKSPACE_CONFIG']}` (given)"
    os.environ["CUBLAS_WORKSPACE_CONFIG"] = CUBLAS_WORKSPACE
    return f"`CUBLAS_WORKSPACE_CONFIG={CUBLAS_WORKSPACE}` (set before any cuBLAS call)"


def torch_flags() -> dict[str, bool]:
    """torch's process-wide settings that Lightning's Trainer changes and never puts back."""
    return {
        "deterministic algorithms": torch.are_deterministic_algorithms_enabled(),
        "warn only": torch.is_deterministic_algorithms_warn_only_enabled(),
        "cuDNN benchmark": bool(torch.backends.cudnn.benchmark),
        "cuDNN deterministic": bool(torch.backends.cudnn.deterministic),
    }


@contextlib.contextmanager
def flags_restored() -> Iterator[dict[str, bool]]:
    """Run a part with torch's settings as they are now, and put them back after it."""
    saved = torch_flags()
    try:
        yield saved
    finally:
        torch.use_deterministic_algorithms(
            saved["deterministic algorithms"], warn_only=saved["warn only"]
        )
        torch.backends.cudnn.benchmark = saved["cuDNN benchmark"]
        torch.backends.cudnn.deterministic = saved["cuDNN deterministic"]


@dataclass
class ShmPlan:
    """The loader workers /dev/shm can hold, and what the report says about it."""

    workers: int
    note: str


def sample_bytes(dataset_cfg: Any) -> int:
    """Bytes of the tensors of one training sample (what a worker puts in shared memory)."""
    from hydra.utils import instantiate

    sample = instantiate(dataset_cfg).dataset("train")[0]
    return sum(v.nbytes for v in sample.values() if isinstance(v, torch.Tensor))


def plan_workers(workers: int, batch: int, eval_batch: int, per_sample: int, shm: Path) -> ShmPlan:
    """How many loader workers fit in ``shm``: each keeps :data:`PREFETCH` batches of the train
    and of the evaluation loader in flight there; :data:`SHM_HEADROOM` times that must be free.
    """
    if workers <= 0:
        return ShmPlan(0, "no loader workers: nothing goes through /dev/shm")
    per_worker = PREFETCH * (batch + eval_batch) * per_sample
    need = workers * per_worker
    try:
        free = shutil.disk_usage(shm).free
    except OSError:
        free = 0
    mb = 2**20
    if free >= SHM_HEADROOM * need:
        return ShmPlan(
            workers,
            f"{shm}: {free / mb:.0f} MB free, {workers} workers keep ~{need / mb:.0f} MB in "
            "flight: enough",
        )
    fit = int(free // (SHM_HEADROOM * per_worker))
    keep = max(0, min(workers, fit))
    return ShmPlan(
        keep,
        f"**{shm}: {free / mb:.0f} MB free, too small for {workers} workers** (~{need / mb:.0f} MB "
        f"in flight: {workers} × {PREFETCH} prefetched × ({batch} + {eval_batch}) samples × "
        f"{per_sample / 1024:.0f} KB, ×{SHM_HEADROOM} headroom): ran with "
        f"`dataset.num_workers={keep}`. To keep {workers}, give the container more shared "
        f"memory (`docker run --shm-size={math.ceil(SHM_HEADROOM * need / mb / 64) * 64}m`, or "
        "Kubernetes: an `emptyDir` with `medium: Memory` mounted on /dev/shm); a training run "
        f"on this machine needs `dataset.num_workers={keep}` too",
    )
