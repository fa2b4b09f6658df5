"""What goes wrong with a dataset's files, and counting the samples skipped because of it.

Every dataset and codec raises these (never a bare ``OSError`` or a ``None`` that fails later):
:class:`DataFileError` names the file (and the line, for text files), :class:`DataRootError` shows
the layout the dataset expected. With ``skip_bad_samples`` a dataset warns instead and counts the
sample in a :class:`SkipCounter`, which :func:`report_skipped` logs when a stage ends.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

__all__ = ["DataFileError", "DataRootError", "SkipCounter", "read_bytes", "report_skipped"]

log = logging.getLogger(__name__)


class DataFileError(ValueError):
    """A data file is missing, truncated or not in the expected format; the message names it."""


class DataRootError(DataFileError):
    """``data_root`` is missing or does not have the layout of the dataset; shows the layout."""


def read_bytes(path: str | os.PathLike) -> bytes:
    """The bytes of ``path``, or a :class:`DataFileError` naming it (missing, unreadable)."""
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise DataFileError(f"{path}: file not found") from None
    except OSError as err:
        raise DataFileError(f"{path}: cannot read ({err.strerror or err})") from None


class SkipCounter:
    """How many samples a dataset skipped (``skip_bad_samples``), shared with its workers.

    DataLoader workers are separate processes, so a plain integer would only count in each
    worker; the count lives in a ``multiprocessing.Value`` that workers inherit. Pickling it
    outside of process spawning (e.g. to save a dataset) keeps only the current number.
    """

    def __init__(self, start: int = 0) -> None:
        import multiprocessing as mp

        self._value = mp.get_context().Value("q", start)

    def add(self, n: int = 1) -> None:
        with self._value.get_lock():
            self._value.value += n

    @property
    def value(self) -> int:
        return int(self._value.value)

    def __getstate__(self) -> dict:
        from multiprocessing.context import get_spawning_popen

        if get_spawning_popen() is not None:
            return {"shared": self._value}
        return {"count": self.value}

    def __setstate__(self, state: dict) -> None:
        if "shared" in state:
            self._value = state["shared"]
        else:
            self.__init__(state["count"])


def report_skipped(datasets: dict[str, Any]) -> dict[str, int]:
    """Log how many samples each split's dataset skipped (``skip_bad_samples``).

    Args:
        datasets: split name → dataset with a ``skipped`` :class:`SkipCounter`.

    Returns:
        split → number of samples skipped so far.
    """
    counts = {split: ds.skipped.value for split, ds in datasets.items() if hasattr(ds, "skipped")}
    for split, n in counts.items():
        if n:
            log.warning("%s split: %d bad sample(s) skipped (see the warnings above)", split, n)
    return counts
