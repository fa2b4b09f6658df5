"""What goes wrong with a dataset's files, and counting the samples skipped because of it.

Every dataset and codec raises these (never a bare ``OSError`` or a ``None`` that fails later):
:class:`DataFileError` names the file, :class:`DataLineError` the file and the line
(``<file>:<line>: <reason>``), :class:`DataRootError` shows the layout the dataset expected. With
``skip_bad_samples`` a dataset warns instead and counts the sample in a :class:`SkipCounter`,
which :func:`report_skipped` logs when a stage ends.

The checks of what a camera file *means* live here, once, for every reader (KITTI and TUM poses,
Virtual KITTI extrinsics and intrinsics, KITTI's ``calib.txt``; ``docs/configuration.md`` lists
their messages): :func:`rigid_problem` (a pose is a rigid transform), :func:`frame_problem` (frame
numbers are whole, unique and increasing) and :func:`intrinsics_problem` (positive focal lengths,
the principal point inside the image). Each returns the index of the first bad row and a reason,
and the reader raises its own error at that row's line. They use numpy only: the pose readers
serve command-line tools that do not load torch (:mod:`mfg_lightning.core.geometry` does).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "RIGID_TOLERANCE",
    "DataFileError",
    "DataLineError",
    "DataRootError",
    "SkipCounter",
    "file_error",
    "frame_problem",
    "intrinsics_problem",
    "read_bytes",
    "report_skipped",
    "rigid_problem",
]

#: How far a pose read from a text file may be from a rigid transform: every entry of ``RᵀR − I``
#: and of the bottom row's difference from ``(0, 0, 0, 1)`` within 1e-2, and ``det R > 0`` (with
#: ``RᵀR`` that close to ``I``, within 1.5e-2 of +1). Files are written with as few as 4–6
#: decimals; anything farther is a wrong column, a wrong format, a scaled block or garbage.
RIGID_TOLERANCE = 1e-2

log = logging.getLogger(__name__)


class DataFileError(ValueError):
    """A data file is missing, truncated or not in the expected format; the message names it."""


class DataRootError(DataFileError):
    """``data_root`` is missing or does not have the layout of the dataset; shows the layout."""


class DataLineError(DataFileError):
    """A line of a text data file that is wrong: ``<file>:<line>: <reason>``, one line.

    Attributes:
        path: the file.
        line: 1-based line number of the problem (1 for problems with the file as a whole).
        reason: what is wrong, one line.
    """

    def __init__(self, path: str | os.PathLike[str], line: int, reason: str) -> None:
        self.path = str(path)
        self.line = int(line)
        self.reason = " ".join(reason.split())  # one line, whatever the reason quoted
        super().__init__(f"{self.path}:{self.line}: {self.reason}")


def file_error(path: str | os.PathLike, err: OSError) -> str:
    """``<path>: <why it cannot be read>`` for an ``OSError`` of opening or reading it: a
    missing file, a directory where a file should be, or the system's reason."""
    if isinstance(err, FileNotFoundError):
        return f"{path}: file not found"
    if isinstance(err, IsADirectoryError) or Path(path).is_dir():
        return f"{path}: a directory, not a file"
    return f"{path}: cannot read ({err.strerror or err})"


def read_bytes(path: str | os.PathLike) -> bytes:
    """The bytes of ``path``, or a :class:`DataFileError` naming it (missing, a directory,
    unreadable)."""
    try:
        return Path(path).read_bytes()
    except OSError as err:
        raise DataFileError(file_error(path, err)) from None


# --------------------------------------------------------------------------------------------
# What camera files mean
# --------------------------------------------------------------------------------------------


def rigid_problem(poses: np.ndarray) -> tuple[int, str] | None:
    """The first pose that is not a rigid transform, within :data:`RIGID_TOLERANCE`.

    Args:
        poses: ``(N, 3, 4)`` ``[R | t]`` or ``(N, 4, 4)`` matrices, finite.

    Returns:
        ``(index, reason)`` of the first whose 3×3 block is not a rotation (``RᵀR ≠ I`` or
        ``det R ≤ 0``) or, for 4×4, whose bottom row is not ``(0, 0, 0, 1)``; None if all are.
    """
    poses = np.asarray(poses, np.float64)
    R = poses[:, :3, :3]
    deviation = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((deviation > RIGID_TOLERANCE) | (det <= 0))
    if bad.size:
        i = int(bad[0])
        return i, (
            f"the 3×3 block is not a rotation (max |RᵀR − I| = {deviation[i]:.3g}, "
            f"det = {det[i]:.3g}; a rotation has 0 and 1, within {RIGID_TOLERANCE:g})"
        )
    if poses.shape[1] == 4:
        row = np.abs(poses[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
        bad = np.flatnonzero(row > RIGID_TOLERANCE)
        if bad.size:
            i = int(bad[0])
            shown = " ".join(f"{v:.6g}" for v in poses[i, 3])
            return i, f"the bottom row is {shown}, not 0 0 0 1: not a rigid transform"
    return None


def frame_problem(
    frames: np.ndarray, lines: np.ndarray, what: str = "frame", plural: str = "frame numbers"
) -> tuple[int, str] | None:
    """The first frame number that is not a whole number ≥ 0 or does not follow the one before
    (frame numbers must be unique and increasing).

    Args:
        frames: ``(N,)`` frame numbers as read (float64).
        lines: ``(N,)`` the 1-based line of each, for the message.
        what, plural: their name in the message (``"frame index"``, ``"frame indices"``).

    Returns:
        ``(index, reason)`` of the first bad one, or None.
    """
    frames = np.asarray(frames, np.float64)
    bad = np.flatnonzero((frames != np.round(frames)) | (frames < 0) | (frames > 2**53))
    if bad.size:
        i = int(bad[0])
        return i, f"{what} {float(frames[i])!r} is not a whole number >= 0"
    back = np.flatnonzero(np.diff(frames) <= 0)
    if back.size:
        i = int(back[0]) + 1
        return i, (
            f"{what} {int(frames[i])} does not follow {int(frames[i - 1])} "
            f"(line {int(lines[i - 1])}): {plural} must be unique and increasing"
        )
    return None


def intrinsics_problem(
    intrinsics: np.ndarray, image_hw: tuple[int, int] | None = None
) -> tuple[int, str] | None:
    """The first camera whose focal lengths are not positive, or whose principal point lies
    outside the image.

    Args:
        intrinsics: ``(N, 4)`` ``(fx, fy, cx, cy)`` in pixels, finite.
        image_hw: ``(height, width)`` of the images in pixels, or None (the principal point is
            then not checked).

    Returns:
        ``(index, reason)`` of the first bad row, or None. Inside means ``0 ≤ cx ≤ W`` and
        ``0 ≤ cy ≤ H``.
    """
    K = np.asarray(intrinsics, np.float64).reshape(-1, 4)
    bad = np.flatnonzero((K[:, 0] <= 0) | (K[:, 1] <= 0))
    if bad.size:
        i = int(bad[0])
        return i, f"focal lengths must be positive, got fx = {K[i, 0]:.6g}, fy = {K[i, 1]:.6g}"
    if image_hw is not None:
        height, width = image_hw
        outside = (K[:, 2] < 0) | (K[:, 2] > width) | (K[:, 3] < 0) | (K[:, 3] > height)
        bad = np.flatnonzero(outside)
        if bad.size:
            i = int(bad[0])
            return i, (
                f"principal point (cx, cy) = ({K[i, 2]:.6g}, {K[i, 3]:.6g}) is outside the "
                f"{width}×{height} image"
            )
    return None


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
