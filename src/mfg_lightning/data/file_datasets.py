"""What every dataset read from files does the same way: the base class of such a dataset
(:class:`FileMotionDataset`: sample ids, a file error raised naming the sample or skipped with a
warning, index problems reported at once) and the helpers of its index (the root checked,
text files read, numbered files listed, long lists shortened for messages).

A new dataset subclasses :class:`FileMotionDataset` (see :mod:`mfg_lightning.data.base` for its
DataModule). Errors and the skip counter are in :mod:`mfg_lightning.core.data_errors`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mfg_lightning.core.data_errors import DataFileError, DataRootError, SkipCounter, read_bytes
from mfg_lightning.data.base import PORTIONS, MotionDataset, portion_frames

# What a config says for "not set" (null, Hydra's ??? or an empty string).
_UNSET = ("", "???", "None", "null")


class FileMotionDataset(MotionDataset):
    """A dataset read from files: samples are ``(sequence, source, target)`` triples.

    Subclasses call this ``__init__`` first, fill ``samples`` and ``name`` and implement
    :meth:`_load`. A file error is re-raised naming the sample, or, with ``skip_bad_samples``,
    warned about, counted in ``skipped`` (a :class:`~mfg_lightning.core.data_errors.SkipCounter`),
    and the sample dropped (``None``; :func:`~mfg_lightning.data.base.collate_samples` leaves
    it out).

    Args:
        height, width: the model's input size; samples are delivered at it.
        split: name used in ``sample_id`` and messages.
        portion: one of :data:`~mfg_lightning.data.base.PORTIONS`, the frames of each sequence
            to use.
        skip_bad_samples: warn and skip unreadable samples (``__getitem__`` returns None, the
            collate drops it) instead of raising.
    """

    #: How messages name the dataset ("KITTI train split: …").
    title: str = "dataset"

    def __init__(
        self,
        height: int = 48,
        width: int = 128,
        split: str = "train",
        portion: str = "all",
        skip_bad_samples: bool = False,
    ) -> None:
        super().__init__()
        if portion not in PORTIONS:
            raise ValueError(f"portion must be 'all', 'train' or 'val', got {portion!r}")
        self.height, self.width = int(height), int(width)
        self.split = split
        self.portion = portion
        self.skip_bad_samples = bool(skip_bad_samples)
        self.skipped = SkipCounter()
        self.samples = []

    def sample_id(self, index: int) -> str:
        seq, src, tgt = self.samples[index]
        return f"{self.name}/{self.split}/{seq}/{src}->{tgt}"

    def sample_identity(self, index: int) -> dict[str, Any]:
        """The fields naming sample ``index``: ``sequence``, ``frame``, ``target`` and
        ``sample_id``."""
        seq, src, tgt = self.samples[index]
        return {"sequence": seq, "frame": src, "target": tgt, "sample_id": self.sample_id(index)}

    def _load(self, index: int) -> dict[str, Any]:
        raise NotImplementedError

    def __getitem__(self, index: int) -> dict[str, Any] | None:
        try:
            return self._load(index)
        except DataFileError as err:
            self.bad_sample(index, err, "skipping")
            self.skipped.add()
            return None

    def bad_sample(self, index: int, err: DataFileError, doing: str) -> None:
        """Sample ``index`` could not be read: raise naming it, or (``skip_bad_samples``) warn
        ``<doing> <sample id>: <err>`` and return so that the caller skips it."""
        if not self.skip_bad_samples:
            raise DataFileError(f"{self.sample_id(index)}: {err}") from err
        warnings.warn(f"{doing} {self.sample_id(index)}: {err}", stacklevel=3)

    def report_problems(self, problems: list[str]) -> None:
        """Problems found while indexing (missing frames, short pose files): one
        :class:`~mfg_lightning.core.data_errors.DataFileError` listing them all, or with
        ``skip_bad_samples`` one warning (the affected samples are already left out)."""
        if not problems:
            return
        text = "\n".join(problems)
        if not self.skip_bad_samples:
            raise DataFileError(
                f"{self.title} {self.split} split: {text}\n(set dataset.skip_bad_samples=true to "
                "skip the affected samples with a warning)"
            )
        warnings.warn(
            f"{self.title} {self.split} split, skipping affected samples: {text}", stacklevel=3
        )

    def portion_frames(self, n_frames: int, val_fraction: float, span: int) -> range:
        """The frames of a sequence of ``n_frames`` that this dataset's ``portion`` uses."""
        return portion_frames(n_frames, self.portion, val_fraction, span)


def check_data_root(data_root: str | os.PathLike | None, point_at: str, layout: str = "") -> Path:
    """``data_root`` expanded (``~``), or a :class:`~mfg_lightning.core.data_errors.DataRootError`
    when it is not set or not a directory.

    Args:
        data_root: the config's ``dataset.data_root``.
        point_at: what it should point at, for the message ("a folder of images, e.g. …").
        layout: the expected tree, shown after the message ("" : none).
    """
    tail = f". Expected layout:\n{layout}" if layout else ""
    if data_root is None or str(data_root).strip() in _UNSET:
        raise DataRootError(f"dataset.data_root is not set: point it at {point_at}{tail}")
    root = Path(data_root).expanduser()
    if not root.is_dir():
        # The dataset configs default data_root below paths.data_dir, so the path may come from
        # no setting the user typed: say both ways of pointing it at the data.
        where = "" if root.is_absolute() else f" (relative to {Path.cwd()})"
        raise DataRootError(
            f"dataset.data_root={root}{where} is not a directory: point it at {point_at}, or set "
            f"MFG_DATA_DIR to the folder holding the datasets (kitti/, vkitti/){tail}"
        )
    return root


def read_text_lines(path: str | os.PathLike) -> list[str]:
    """The lines of a UTF-8 text file, or a :class:`~mfg_lightning.core.data_errors.DataFileError`
    naming it (missing, unreadable, not text). Callers name the line of what they parse."""
    try:
        return read_bytes(path).decode("utf-8").splitlines()
    except UnicodeDecodeError:
        raise DataFileError(f"{path}: not a text file (not UTF-8)") from None


def some_of(items: Sequence[Any], limit: int, inline: bool = False) -> str:
    """The first ``limit`` of ``items`` for a message: one indented line each, then
    ``… and N more``; ``inline``: comma-separated, then `` …``."""
    if inline:
        return ", ".join(map(str, items[:limit])) + (" …" if len(items) > limit else "")
    shown = "\n".join(f"  {item}" for item in items[:limit])
    return shown + (f"\n  … and {len(items) - limit} more" if len(items) > limit else "")


def list_numbered(directory: Path, prefix: str = "", suffix: str = ".png") -> list[int]:
    """Frame numbers ``k`` of the files ``<prefix><digits k><suffix>`` in ``directory`` (suffix
    case-insensitive), sorted; ``[]`` when the directory does not exist."""
    frames = []
    if not directory.is_dir():
        return frames
    with os.scandir(directory) as it:
        for entry in it:
            name = entry.name
            if name.startswith(prefix) and name.lower().endswith(suffix):
                core = name[len(prefix) : len(name) - len(suffix)]
                if core.isdigit():
                    frames.append(int(core))
    return sorted(frames)
