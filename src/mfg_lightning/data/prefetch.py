"""The first epoch computed ahead of the training step: ``dataset.prefetch``'s modes and the
background thread of the training process that fills a dataset's sample cache
(:class:`~mfg_lightning.data.sample_cache.SampleStore`) in the order the training loader will
ask for its samples."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from typing import Any

log = logging.getLogger(__name__)

#: How ``dataset.prefetch`` may fill the first epoch ahead of the training step.
PREFETCH_MODES = ("thread", "worker", "none")


def check_prefetch(mode: str) -> str:
    """``dataset.prefetch``, refused naming the key unless one of :data:`PREFETCH_MODES`."""
    if mode not in PREFETCH_MODES:
        raise ValueError(
            f"dataset.prefetch must be one of {', '.join(PREFETCH_MODES)}, got {mode!r}"
        )
    return mode


class Prefetcher:
    """Fills a dataset's cache from a background thread of the training process, in the order
    the training loader will ask for its samples.

    :meth:`follow` is given the indices of each pass of the loader before the first is handed
    out (:attr:`~mfg_lightning.data.resumable_loader.EpochShuffleSampler.on_order`); the thread
    walks them, calling ``fill(index)``
    (:meth:`~mfg_lightning.data.sample_cache.SampleStore.prefetch` of that sample), and stops
    at the end, when ``fill`` returns False (nothing more can be kept), when a sample fails (the
    loader then meets the error itself) or at :meth:`stop`.

    The samples are the same whoever computes them (each is a pure function of its index), so
    the thread changes when a sample is computed, never what the loader returns.

    Args:
        fill: computes and keeps sample ``index``; False when nothing more can be kept.
        name: the thread's name (for debuggers and logs).
    """

    def __init__(self, fill: Callable[[int], bool], name: str = "prefetch") -> None:
        self.fill, self.name = fill, name
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def follow(self, order: Sequence[int]) -> None:
        """Stop the current walk and start one over ``order``."""
        self.stop()
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._walk, args=(list(order), self._stop), name=self.name, daemon=True
        )
        self._thread.start()

    def _walk(self, order: list[int], stop: threading.Event) -> None:
        for index in order:
            if stop.is_set():
                return
            try:
                if not self.fill(index):
                    return
            except Exception:
                log.debug("%s: sample %d failed; leaving it to the loader", self.name, index,
                          exc_info=True)  # fmt: skip
                return

    def stop(self) -> None:
        """Stop the walk (after the sample being computed) and wait for the thread."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def __getstate__(self) -> dict[str, Any]:
        # A copy (a pickled DataModule) has no thread of its own.
        return {"fill": self.fill, "name": self.name}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["fill"], state["name"])
