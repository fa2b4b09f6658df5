"""Which estimated pose is which ground-truth pose: by frame index (KITTI) or by timestamp (TUM).

The peers do not ask for one pose per ground-truth frame, and neither does ``mfg-eval-poses``:

* **by frame index** (an estimate in KITTI layout, kitti-odom-eval's rule): pose ``k`` of a
  12-number file is frame ``k``; a 13-number file names its frame first
  (:attr:`mfg_lightning.trajectory.pose_io.PoseFile.frames`), so it may start late, end early and
  skip frames. Frame ``f`` is the ground truth's pose of frame ``f`` (its ``f``-th pose, or the
  one its own index column names). A frame the ground truth does not have is an error.
* **by timestamp** (an estimate in TUM layout, ``evo``'s ``sync.associate_trajectories`` with its
  default nearest-time method): the estimate's timestamps are shifted by ``offset`` (evo's
  ``--t_offset``); then, starting from the trajectory with fewer poses (the estimate when both
  have as many), each of its poses is matched to the other's pose nearest in time, if that is at
  most ``max_diff`` seconds away (evo's ``--t_max_diff``, default 0.01 s), ties going to the
  earlier pose. Unmatched poses are left out. The ground truth's timestamps are its own (a TUM
  file) or, for a KITTI ground truth, those of its ``times.txt`` (given, or found in KITTI's
  layout; :func:`ground_truth_times`), else the nominal ``frame / rate`` (10 Hz, KITTI's rate and
  the clock this project's ``evaluate`` and ``predict`` write without a ``times.txt``).

Timestamps must increase along each file (evo then uses the same nearest-neighbour search), so the
matched poses are in the order of both files. The match is returned as rows of both files
(:class:`PoseMatch`); the metrics then score the matched poses (``mfg-eval-poses``).

This module imports numpy only (no torch), so command-line tools stay quick to start.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from mfg_lightning.trajectory.pose_io import (
    PoseFile,
    PoseFileError,
    check_increasing,
    read_kitti_times,
)

__all__ = [
    "DEFAULT_MAX_TIME_DIFF",
    "KITTI_FRAME_RATE",
    "MatchOptions",
    "PoseMatch",
    "SequenceMatcher",
    "associate_timestamps",
    "find_times",
    "ground_truth_times",
    "match_poses",
]

#: evo's default ``--t_max_diff`` in seconds.
DEFAULT_MAX_TIME_DIFF = 0.01
#: KITTI odometry's nominal frame rate (Hz): the clock of a ground truth without ``times.txt``.
KITTI_FRAME_RATE = 10.0


@dataclass(frozen=True)
class PoseMatch:
    """The estimated poses matched to ground-truth poses, in the order of both files.

    Attributes:
        gt_rows: ``(M,)`` int64 rows of the ground-truth file (non-decreasing).
        pred_rows: ``(M,)`` int64 rows of the estimate's file (increasing).
        by: ``"frame"`` (frame index) or ``"timestamp"``.
        num_gt: poses in the ground-truth file.
        num_pred: poses in the estimate's file (the poses given).
        max_time_diff: the largest ``|Δt|`` of a timestamp match (s, after the offset); None by
            frame index.
        times: where the ground truth's timestamps came from (a ``times.txt``, the TUM file
            itself, or ``frame / 10 Hz``); None by frame index.
    """

    gt_rows: np.ndarray
    pred_rows: np.ndarray
    by: Literal["frame", "timestamp"]
    num_gt: int
    num_pred: int
    max_time_diff: float | None = None
    times: str | None = None

    @property
    def num_matched(self) -> int:
        """The poses used."""
        return int(self.pred_rows.shape[0])

    def describe(self, options: MatchOptions) -> str:
        """How the poses were matched, in words (for messages and titles)."""
        if self.by == "frame":
            return "by frame index"
        return (
            f"by timestamp within {options.max_diff:g} s after an offset of {options.offset:g} "
            f"s; ground-truth times: {self.times}"
        )

    def summary(self) -> dict[str, str | int | float | None]:
        """What was matched, for JSON: ``matched_by``, ``poses_given``, ``gt_poses``,
        ``gt_times`` (the ground truth's clock, by timestamp) and ``max_time_diff`` (s)."""
        return {
            "matched_by": self.by,
            "poses_given": self.num_pred,
            "gt_poses": self.num_gt,
            "gt_times": self.times,
            "max_time_diff": self.max_time_diff,
        }


@dataclass(frozen=True)
class MatchOptions:
    """How estimated poses are matched to the ground truth's (module docstring).

    Attributes:
        max_diff: the largest time difference of a match (s; evo's ``--t_max_diff``).
        offset: seconds added to the estimate's timestamps (evo's ``--t_offset``).
        gt_times: a times file or a directory of them (:func:`find_times`); None: KITTI's layout.
        gt_rate: the clock (Hz) of a KITTI ground truth without times.
        minimum: the fewest matched poses an estimate may have (what the metrics need).
    """

    max_diff: float = DEFAULT_MAX_TIME_DIFF
    offset: float = 0.0
    gt_times: Path | None = None
    gt_rate: float = KITTI_FRAME_RATE
    minimum: int = 2


def associate_timestamps(
    gt_stamps: np.ndarray,
    pred_stamps: np.ndarray,
    max_diff: float = DEFAULT_MAX_TIME_DIFF,
    offset: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-time association of two increasing timestamp sequences (evo's rule; module
    docstring).

    Args:
        gt_stamps: ``(N,)`` ground-truth timestamps (s), increasing.
        pred_stamps: ``(K,)`` estimated timestamps (s), increasing, before ``offset``.
        max_diff: the largest time difference of a match (s).
        offset: added to the estimate's timestamps first (s).

    Returns:
        ``(gt_rows, pred_rows)``, ``(M,)`` int64 each, in the order of the shorter sequence.
    """
    gt_stamps = np.asarray(gt_stamps, dtype=np.float64)
    pred_stamps = np.asarray(pred_stamps, dtype=np.float64)
    pred_longer = pred_stamps.shape[0] > gt_stamps.shape[0]
    # evo shifts the longer trajectory: the estimate by +offset, or the ground truth by -offset.
    if pred_longer:
        short, long = gt_stamps, pred_stamps + offset
    else:
        short, long = pred_stamps, gt_stamps + (-offset)
    if short.size == 0 or long.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    inside = (short >= long[0] - max_diff) & (short <= long[-1] + max_diff)
    upper = np.minimum(np.searchsorted(long, short, side="right"), long.shape[0] - 1)
    diff_ub = long[upper] - short
    diff_lb = np.where(upper > 0, short - long[np.maximum(upper - 1, 0)], np.inf)
    take_upper = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lower = ~take_upper & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    ok = inside & (take_upper | take_lower)
    short_rows = np.flatnonzero(ok).astype(np.int64)
    long_rows = np.where(take_upper, upper, upper - 1)[ok].astype(np.int64)
    return (long_rows, short_rows) if not pred_longer else (short_rows, long_rows)


def _check_increasing(stamps: np.ndarray, path: Path, lines: Sequence[int]) -> None:
    check_increasing(path, lines, stamps, "timestamp", "timestamps must increase to be matched")


def find_times(
    seq: str, gt_path: Path, given: Path | None = None, single: bool = False
) -> Path | None:
    """The ``times.txt`` of a KITTI ground-truth sequence.

    Args:
        seq: the sequence name (``09``).
        gt_path: its ground-truth pose file (``<root>/poses/09.txt``).
        given: ``--gt-times``: a times file (when ``single``) or a directory holding
            ``<seq>.txt`` or ``<seq>/times.txt``; None: KITTI's own layout,
            ``<root>/sequences/<seq>/times.txt``.
        single: one sequence is evaluated, so ``given`` may be the file itself.

    Returns:
        The file, or None when it does not exist.
    """
    if given is not None:
        if given.is_file() and single:
            return given
        candidates = [given / f"{seq}.txt", given / seq / "times.txt"]
    else:
        candidates = [gt_path.parent.parent / "sequences" / seq / "times.txt"]
    return next((c for c in candidates if c.is_file()), None)


def ground_truth_times(
    gt: PoseFile, times_file: Path | None, rate: float = KITTI_FRAME_RATE
) -> tuple[np.ndarray, str]:
    """The timestamps of a ground truth's poses and where they came from.

    Args:
        gt: the ground-truth file.
        times_file: its ``times.txt`` (:func:`find_times`), or None.
        rate: the nominal frame rate (Hz) of a KITTI ground truth without times: frame ``f`` is
            at ``f / rate`` seconds.

    Returns:
        ``((N,) seconds, increasing; the source in words)``: a TUM file's own timestamps, the
        times file's, or the nominal clock's.

    Raises:
        PoseFileError: a times file that does not have one time per pose, or timestamps that do
            not increase.
    """
    if gt.timestamps is not None:
        _check_increasing(gt.timestamps, gt.path, gt.lines)
        return gt.timestamps, str(gt.path)
    if times_file is None:
        return gt.frame_indices() / rate, f"frame / {rate:g} Hz"
    stamps = read_kitti_times(times_file)
    if stamps.shape[0] != len(gt):
        raise PoseFileError(
            times_file,
            min(stamps.shape[0], len(gt)) + 1,
            f"{stamps.shape[0]} timestamps for the {len(gt)} poses of {gt.path}",
        )
    # times.txt holds one number a line and no comments: pose i is on line i + 1.
    _check_increasing(stamps, times_file, np.arange(1, stamps.shape[0] + 1))
    return stamps, str(times_file)


def _by_frame(gt: PoseFile, pred: PoseFile) -> PoseMatch:
    gt_frames, frames = gt.frame_indices(), pred.frame_indices()
    rows = np.minimum(np.searchsorted(gt_frames, frames), len(gt) - 1)
    missing = np.flatnonzero(gt_frames[rows] != frames)
    if missing.size:
        i = int(missing[0])
        raise PoseFileError(
            pred.path,
            int(pred.lines[i]),
            f"frame {int(frames[i])} is not in the ground truth {gt.path} ({len(gt)} poses, "
            f"frames {int(gt_frames[0])}–{int(gt_frames[-1])})",
        )
    return PoseMatch(rows.astype(np.int64), np.arange(len(pred)), "frame", len(gt), len(pred))


def match_poses(
    gt: PoseFile,
    pred: PoseFile,
    gt_times: tuple[np.ndarray, str] | None = None,
    max_diff: float = DEFAULT_MAX_TIME_DIFF,
    offset: float = 0.0,
) -> PoseMatch:
    """Match an estimate's poses to the ground truth's (module docstring).

    Args:
        gt: the ground-truth file (KITTI or TUM).
        pred: the estimate's file: KITTI (by frame index) or TUM (by timestamp).
        gt_times: the ground truth's timestamps and their source (:func:`ground_truth_times`);
            needed for a TUM estimate, unused for a KITTI one.
        max_diff, offset: the timestamp association's tolerance and the estimate's time offset
            (s).

    Returns:
        :class:`PoseMatch` (possibly with few or no poses: the caller decides what is enough).

    Raises:
        PoseFileError: a frame the ground truth does not have, or an estimate's timestamps that do
            not increase.
    """
    if pred.format == "kitti":
        return _by_frame(gt, pred)
    if gt_times is None:
        raise ValueError("a TUM estimate needs the ground truth's timestamps (gt_times)")
    stamps, source = gt_times
    assert pred.timestamps is not None  # a TUM file has them
    _check_increasing(pred.timestamps, pred.path, pred.lines)
    gt_rows, pred_rows = associate_timestamps(stamps, pred.timestamps, max_diff, offset)
    diffs = np.abs(pred.timestamps[pred_rows] + offset - stamps[gt_rows])
    largest = float(diffs.max()) if diffs.size else None
    return PoseMatch(gt_rows, pred_rows, "timestamp", len(gt), len(pred), largest, source)


class SequenceMatcher:
    """Matches the estimates of one sequence to its ground truth, every method's in turn; the
    ground truth's timestamps are looked up once, when a TUM estimate first needs them.

    Args:
        seq: the sequence name.
        gt: its ground-truth file.
        options: :class:`MatchOptions`.
        single: one sequence is evaluated (``options.gt_times`` may then be the times file).
    """

    def __init__(self, seq: str, gt: PoseFile, options: MatchOptions, single: bool) -> None:
        self.seq, self.gt, self.options, self.single = seq, gt, options, single
        self._times: tuple[np.ndarray, str] | None = None

    def times(self) -> tuple[np.ndarray, str]:
        """The ground truth's timestamps and their source (:func:`ground_truth_times`).

        Raises:
            ValueError: ``options.gt_times`` holds no times for the sequence.
        """
        if self._times is None:
            given, found = self.options.gt_times, None
            if self.gt.timestamps is None:
                found = find_times(self.seq, self.gt.path, given, self.single)
                if given is not None and found is None:
                    raise ValueError(
                        f"--gt-times {given}: no times for sequence {self.seq} (looked for "
                        f"{given / (self.seq + '.txt')} and {given / self.seq / 'times.txt'})"
                    )
            self._times = ground_truth_times(self.gt, found, self.options.gt_rate)
        return self._times

    def __call__(self, pred: PoseFile) -> PoseMatch:
        """Match one estimate (:func:`match_poses`).

        Raises:
            PoseFileError: as :func:`match_poses`, or fewer matched poses than
                ``options.minimum``, naming the estimate and how many matched.
        """
        o = self.options
        times = self.times() if pred.format == "tum" else None
        match = match_poses(self.gt, pred, times, o.max_diff, o.offset)
        if match.num_matched < o.minimum:
            raise PoseFileError(
                pred.path,
                int(pred.lines[0]),
                f"only {match.num_matched} of its {len(pred)} poses match the {len(self.gt)} of "
                f"the ground truth {self.gt.path} ({match.describe(o)}); the metrics need at "
                f"least {o.minimum}",
            )
        return match
