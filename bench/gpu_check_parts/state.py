"""Part 0 of ``bench/gpu_check.py``: the process-wide state a GPU run depends on, set or
checked before the parts run: cuBLAS's deterministic workspace (:func:`set_cublas_workspace`),
torch's deterministic-algorithm and cuDNN flags, put back after each part
(:func:`flags_restored`); the loader workers ``/dev/shm`` holds are the library's
(:mod:`mfg_lightning.data.workers`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import torch

#: The value Lightning sets under ``trainer.deterministic=true``: cuBLAS's deterministic workspace.
CUBLAS_WORKSPACE = ":4096:8"


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
