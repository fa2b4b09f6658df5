"""Worker processes that each run on one thread, for CPU work shared out by processes.

A process pool on ``n`` cores whose workers each start the numerical libraries' default
thread pools (one thread per core) runs ``n × n`` threads on ``n`` cores: the threads
oversubscribe the cores and every worker slows down. torch, OpenCV, OpenMP and the BLAS
libraries size their pools from environment variables that they read once, when they are
loaded, so a cap set inside the worker (an initializer calling ``torch.set_num_threads``) comes
after the import that sized them. :func:`single_thread_pool` therefore writes the caps into this
process's environment before the workers start, so that each spawned worker inherits them from
its first instruction, and restores the environment when the pool is closed.

Kept free of torch, like :mod:`.machine`: a caller sets the caps before it imports torch.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

#: The environment variables that size a library's thread pool, each set to 1 in a
#: :func:`single_thread_pool` worker: OpenMP (torch's intra-op pool; OpenCV and numpy's BLAS
#: where built with it), Intel MKL, OpenBLAS, BLIS, Apple's Accelerate, numexpr, and OpenCV's
#: own ``parallel_for_`` pool.
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
)


@contextmanager
def single_thread_environment() -> Iterator[None]:
    """Every :data:`THREAD_VARIABLES` set to ``"1"`` in ``os.environ`` (so also in the
    environment of a process started meanwhile) for the duration of the block, then each put
    back as it was (unset where it was unset). The libraries this process has loaded already
    keep their pools: they read these once."""
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, "1"))
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextmanager
def single_thread_pool(
    processes: int,
    initializer: Callable[..., object] | None = None,
    initargs: tuple[Any, ...] = (),
) -> Iterator[ProcessPoolExecutor]:
    """A pool of ``processes`` spawned workers, each on one thread from its start.

    Spawned rather than forked: a forked worker would inherit the parent's torch and OpenCV
    state (their thread pools included), which is not safe to fork. The thread caps
    (:func:`single_thread_environment`) stay in this process's environment while the pool is
    open, because the executor starts its workers when tasks are submitted, and replaces a
    worker that died, at any point of the pool's life. On an error in the block the tasks not
    yet started are cancelled before the pool is closed, rather than run to the end.

    Args:
        processes: how many workers (at least 1).
        initializer, initargs: run once in every worker as it starts (the arguments are
            pickled once per worker, not once per task: the place for large shared state).
    """
    if processes < 1:
        raise ValueError(f"a pool needs at least one process, got {processes}")
    import multiprocessing

    with single_thread_environment():
        pool = ProcessPoolExecutor(
            processes,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=initializer,
            initargs=initargs,
        )
        try:
            yield pool
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        pool.shutdown(wait=True)
