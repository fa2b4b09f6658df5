"""Single-threaded worker processes (:mod:`mfg_lightning.core.processes`): the thread caps are
in a worker's environment before it imports anything, and the parent's is left as it was."""

from __future__ import annotations

import os

import pytest

from mfg_lightning.core.machine import usable_cores
from mfg_lightning.core.processes import (
    THREAD_VARIABLES,
    single_thread_environment,
    single_thread_pool,
)


def _threads_seen() -> tuple[dict[str, str | None], int, int]:
    """In a worker: the caps in its environment, then torch's and OpenCV's thread counts as
    these libraries size their pools on import (this is the worker's first import of both)."""
    import sys

    first_import = "torch" not in sys.modules and "cv2" not in sys.modules
    caps = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    import cv2
    import torch

    assert first_import
    return caps, torch.get_num_threads(), cv2.getNumThreads()


def test_the_environment_is_capped_inside_and_restored_after(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    before = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    with single_thread_environment():
        assert all(os.environ[name] == "1" for name in THREAD_VARIABLES)
    assert {name: os.environ.get(name) for name in THREAD_VARIABLES} == before
    with pytest.raises(RuntimeError), single_thread_environment():
        raise RuntimeError("an error inside")
    assert {name: os.environ.get(name) for name in THREAD_VARIABLES} == before
    assert 1 <= usable_cores() <= (os.cpu_count() or 1)


@pytest.mark.slow
def test_workers_start_on_one_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """A spawned worker imports torch and OpenCV on one thread each (seconds: it imports both)."""
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    with single_thread_pool(1) as pool:
        caps, torch_threads, cv2_threads = pool.submit(_threads_seen).result(timeout=120)
    assert caps == dict.fromkeys(THREAD_VARIABLES, "1")
    assert (torch_threads, cv2_threads) == (1, 1)
    assert os.environ["OMP_NUM_THREADS"] == "2"  # the parent's own, back
