"""Reading and writing trajectory files in the formats other tools read (KITTI, TUM).

Formats, as distributed:

* **KITTI** (``poses/XX.txt`` of the odometry benchmark; ``docs/formats.md``): one line
  per frame, 12 numbers, the row-major 3×4 ``[R | t]`` of ``T_world_cam`` (camera-to-world, the
  camera of frame 0 is the world), metres. Results may put the frame index first (13 numbers a
  line, as kitti-odom-eval reads them): then the file may start late, end early and skip frames;
  the indices must be whole numbers ≥ 0 in increasing order (``PoseFile.frames``).
* **TUM** (Sturm et al. 2012, the TUM RGB-D benchmark's ``groundtruth.txt``): one line per pose,
  ``timestamp tx ty tz qx qy qz qw``: time in seconds, the camera's position and its orientation
  as a unit quaternion with the scalar last, again camera-to-world.
* KITTI ``sequences/XX/times.txt``: one timestamp in seconds per frame.

Numbers are separated by whitespace. Blank lines and lines starting with ``#`` are skipped in
every format (TUM files carry ``#`` headers; skipping them in KITTI files too costs nothing).
Poses are returned as float64 numpy arrays ``(N, 4, 4)``; quaternions are converted with
:class:`scipy.spatial.transform.Rotation` (whose ``(x, y, z, w)`` order is TUM's).

Bad input raises :class:`PoseFileError`, the project's data error
(:class:`~mfg_lightning.core.data_errors.DataLineError`, a :class:`ValueError`) whose message is
one line ``<file>:<line>: <reason>`` with a 1-based line number. Every pose must be a rigid
transform and frame indices whole, unique and increasing: the checks every camera-file reader
shares (:func:`~mfg_lightning.core.data_errors.rigid_problem`,
:func:`~mfg_lightning.core.data_errors.frame_problem`). Problems with the file as a whole (missing,
unreadable, no poses) point at line 1, where reading stopped. Writes are atomic: the text goes to a
temporary file in the target's directory, which then replaces the target, so a failed write leaves
the previous file (or none) and never a half-written one.

This module imports numpy and scipy only (no torch), so command-line tools stay quick to start.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.core.data_errors import (
    RIGID_TOLERANCE,
    DataLineError,
    file_error,
    frame_problem,
    rigid_problem,
)

__all__ = [
    "PoseFile",
    "PoseFileError",
    "PoseFormat",
    "check_increasing",
    "detect_pose_format",
    "frame_times",
    "read_kitti_poses",
    "read_kitti_times",
    "read_poses",
    "read_tum_poses",
    "write_kitti_poses",
    "write_trajectory",
    "write_tum_poses",
]

PoseFormat = Literal["kitti", "tum"]

_COLUMNS: dict[str, int] = {"kitti": 12, "tum": 8}
# A unit quaternion, like a rotation block, is checked to the rounding of a text file.
_UNIT_TOLERANCE = RIGID_TOLERANCE
_QUOTE_LIMIT = 60


class PoseFileError(DataLineError):
    """A pose or times file that cannot be read as its format says.

    Attributes:
        path: the file.
        line: 1-based line number of the problem (1 for problems with the file as a whole).
        reason: what is wrong, one line.
    """


@dataclass(frozen=True)
class PoseFile:
    """The contents of a pose file.

    Attributes:
        path: the file read.
        format: ``"kitti"`` or ``"tum"``.
        poses: ``(N, 4, 4)`` float64 camera-to-world poses ``T_world_cam``, in file order.
        timestamps: ``(N,)`` float64 seconds (TUM), or ``None`` (KITTI files have none).
        lines: ``(N,)`` int, the 1-based line number of each pose, for error messages.
        frames: ``(N,)`` int64 frame indices of a KITTI file with an index column (13 numbers a
            line), increasing; ``None`` for 12 numbers a line (frames ``0 … N − 1``) and TUM.
    """

    path: Path
    format: PoseFormat
    poses: np.ndarray
    timestamps: np.ndarray | None
    lines: np.ndarray
    frames: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def frame_indices(self) -> np.ndarray:
        """``(N,)`` int64 frame index of every pose: the index column, else ``0 … N − 1``."""
        return self.frames if self.frames is not None else np.arange(len(self), dtype=np.int64)


# ------------------------------------------------------------------------------------------------
# Reading
# ------------------------------------------------------------------------------------------------


def _quote(text: str) -> str:
    text = text.strip()
    if len(text) > _QUOTE_LIMIT:
        text = text[: _QUOTE_LIMIT - 1] + "…"
    return repr(text)


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """``(line number, whitespace-split fields)`` of every non-blank, non-comment line."""
    try:
        raw = path.read_bytes()
    except IsADirectoryError as exc:
        raise PoseFileError(path, 1, file_error(path, exc).removeprefix(f"{path}: ")) from None
    except OSError as exc:
        raise PoseFileError(path, 1, f"cannot read file: {exc.strerror or exc}") from None
    rows: list[tuple[int, list[str]]] = []
    for number, chunk in enumerate(raw.split(b"\n"), start=1):
        try:
            text = chunk.decode("utf-8")
        except UnicodeDecodeError:
            raise PoseFileError(path, number, "not UTF-8 text") from None
        fields = text.split()
        if fields and not fields[0].startswith("#"):
            rows.append((number, fields))
    if not rows:
        raise PoseFileError(path, 1, "empty file: no poses")
    return rows


def _numbers(path: Path, number: int, fields: list[str], columns: int, what: str) -> list[float]:
    """Parse one line of ``columns`` finite floats."""
    if len(fields) != columns:
        raise PoseFileError(
            path,
            number,
            f"expected {columns} number{'s' if columns > 1 else ''} ({what}), "
            f"found {len(fields)}: {_quote(' '.join(fields))}",
        )
    try:
        values = [float(f) for f in fields]
    except ValueError:
        bad = next(f for f in fields if not _is_float(f))
        raise PoseFileError(path, number, f"not a number: {_quote(bad)}") from None
    if not all(math.isfinite(v) for v in values):
        bad = next(f for f, v in zip(fields, values, strict=True) if not math.isfinite(v))
        raise PoseFileError(path, number, f"non-finite number: {_quote(bad)}")
    return values


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def detect_pose_format(path: str | os.PathLike[str]) -> PoseFormat:
    """The format of a pose file from the column count of its first pose line (12 or 13 KITTI,
    8 TUM).

    Raises:
        PoseFileError: unreadable or empty file, or a column count of neither format.
    """
    path = Path(path)
    number, fields = _data_lines(path)[0]
    return _format_of(path, number, fields)


def _format_of(path: Path, number: int, fields: list[str]) -> PoseFormat:
    if len(fields) in (_COLUMNS["kitti"], _COLUMNS["kitti"] + 1):
        return "kitti"
    if len(fields) == _COLUMNS["tum"]:
        return "tum"
    raise PoseFileError(
        path,
        number,
        f"cannot tell the format from {len(fields)} columns (KITTI has 12, or 13 with a frame "
        "index first; TUM has 8)",
    )


def _check_rigid(path: Path, lines: Sequence[int], poses: np.ndarray) -> None:
    """Every pose must be a rigid transform up to the rounding of a text file."""
    problem = rigid_problem(poses)
    if problem is not None:
        raise PoseFileError(path, int(lines[problem[0]]), problem[1])


def _parse_kitti(path: Path, rows: list[tuple[int, list[str]]]) -> PoseFile:
    # The first line decides between 12 numbers and 13 (a frame index first); every line then
    # has as many.
    indexed = len(rows[0][1]) == 13
    what = "a frame index and a row-major 3×4 pose" if indexed else "a row-major 3×4 pose"
    values = np.asarray(
        [_numbers(path, n, f, 13 if indexed else 12, what) for n, f in rows], dtype=np.float64
    )
    lines = np.array([n for n, _ in rows], dtype=np.int64)
    frames = _frame_indices(path, lines, values[:, 0]) if indexed else None
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :] = values[:, int(indexed) :].reshape(-1, 3, 4)
    _check_rigid(path, lines, poses[:, :3, :])
    return PoseFile(path, "kitti", poses, None, lines, frames)


def _frame_indices(path: Path, lines: np.ndarray, column: np.ndarray) -> np.ndarray:
    """The index column of a 13-number KITTI file as int64: whole numbers ≥ 0, increasing."""
    problem = frame_problem(column, lines, "frame index", "frame indices")
    if problem is not None:
        raise PoseFileError(path, int(lines[problem[0]]), problem[1])
    return column.astype(np.int64)


def check_increasing(
    path: str | os.PathLike[str],
    lines: Sequence[int],
    values: np.ndarray,
    what: str,
    why: str,
) -> None:
    """Refuse values that do not strictly increase, naming the first line that does not.

    Args:
        path: the file the values come from.
        lines: ``(N,)`` the 1-based line of each value.
        values: ``(N,)`` frame indices or timestamps.
        what: their name in the message (``"timestamp"``).
        why: why they must increase, ending the message.

    Raises:
        PoseFileError: ``<path>:<line>: <what> v does not follow u (line l): <why>``.
    """
    back = np.flatnonzero(np.diff(values) <= 0)
    if back.size:
        i = int(back[0]) + 1
        previous, value = values[i - 1].item(), values[i].item()
        raise PoseFileError(
            path,
            int(lines[i]),
            f"{what} {value!r} does not follow {previous!r} (line {int(lines[i - 1])}): {why}",
        )


def _parse_tum(path: Path, rows: list[tuple[int, list[str]]]) -> PoseFile:
    from scipy.spatial.transform import Rotation

    values = np.asarray(
        [_numbers(path, n, f, 8, "timestamp tx ty tz qx qy qz qw") for n, f in rows],
        dtype=np.float64,
    )
    lines = np.array([n for n, _ in rows], dtype=np.int64)
    quat = values[:, 4:8]
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > _UNIT_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise PoseFileError(
            path, int(lines[i]), f"quaternion (qx qy qz qw) has norm {norm[i]:.6g}, not 1"
        )
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
    poses[:, :3, 3] = values[:, 1:4]
    return PoseFile(path, "tum", poses, values[:, 0].copy(), lines)


def read_poses(
    path: str | os.PathLike[str], fmt: PoseFormat | Literal["auto"] = "auto"
) -> PoseFile:
    """Read a KITTI or TUM pose file.

    Args:
        path: the file.
        fmt: ``"kitti"`` (12 numbers a line, or 13 with a frame index first), ``"tum"`` or
            ``"auto"`` (by the column count of the first pose line).

    Returns:
        :class:`PoseFile` with ``(N, 4, 4)`` float64 camera-to-world poses.

    Raises:
        PoseFileError: missing or unreadable file, no poses, a line with the wrong number of
            columns, a field that is not a number, a non-finite number, a 3×3 block that is not a
            rotation or a quaternion that is not a unit one, a frame index that is not a whole
            number or does not increase.
    """
    path = Path(path)
    rows = _data_lines(path)
    if fmt == "auto":
        fmt = _format_of(path, *rows[0])
    if fmt == "kitti":
        return _parse_kitti(path, rows)
    if fmt == "tum":
        return _parse_tum(path, rows)
    raise ValueError(f"unknown pose format {fmt!r}: use 'kitti', 'tum' or 'auto'")


def read_kitti_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """``(N, 4, 4)`` float64 camera-to-world poses of a KITTI ``poses/XX.txt`` file (in file
    order; an index column is read and dropped: :func:`read_poses` keeps it)."""
    return read_poses(path, "kitti").poses


def read_tum_poses(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps (N,) in s, poses (N, 4, 4))`` of a TUM trajectory file, float64."""
    pose_file = read_poses(path, "tum")
    return np.asarray(pose_file.timestamps), pose_file.poses


def read_kitti_times(path: str | os.PathLike[str]) -> np.ndarray:
    """``(N,)`` float64 timestamps in seconds of a KITTI ``sequences/XX/times.txt``."""
    path = Path(path)
    rows = _data_lines(path)
    return np.array([_numbers(path, n, f, 1, "a time in seconds")[0] for n, f in rows])


# ------------------------------------------------------------------------------------------------
# Writing
# ------------------------------------------------------------------------------------------------


def _as_poses(poses: object) -> np.ndarray:
    """``(N, 4, 4)`` or ``(N, 3, 4)`` finite float64 array with N >= 1 (anything array-like)."""
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim != 3 or array.shape[1:] not in ((4, 4), (3, 4)) or array.shape[0] == 0:
        raise ValueError(f"poses must be (N, 4, 4) or (N, 3, 4) with N >= 1, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(
            "poses contain non-finite values; refusing to write a file no reader takes"
        )
    return array


def _format_number(value: float) -> str:
    # repr is the shortest text that reads back to the same float64: round trips are exact.
    return repr(float(value))


def write_kitti_poses(
    path: str | os.PathLike[str], poses: object, frames: object | None = None
) -> None:
    """Write camera-to-world poses as a KITTI pose file (12 numbers per line, row-major 3×4).

    Args:
        path: the file (replaced atomically).
        poses: ``(N, 4, 4)`` or ``(N, 3, 4)`` array-like (numpy, CPU tensor), finite, N >= 1.
            Numbers are written with the shortest text that reads back exactly.
        frames: ``(N,)`` increasing whole frame indices ≥ 0 to write first on each line (13
            numbers, the layout kitti-odom-eval also reads), or None.
    """
    array = _as_poses(poses)[:, :3, :].reshape(-1, 12)
    text = [" ".join(map(_format_number, row)) for row in array]
    if frames is not None:
        index = np.asarray(frames).reshape(-1)
        steps = np.diff(index)
        if index.shape[0] != array.shape[0] or (index < 0).any() or (steps <= 0).any():
            raise ValueError(f"frames must be {array.shape[0]} increasing indices >= 0")
        text = [f"{int(f)} {line}" for f, line in zip(index, text, strict=True)]
    atomic_write_text(Path(path), "".join(line + "\n" for line in text))


def write_kitti_times(path: str | os.PathLike[str], timestamps: object) -> None:
    """Write a KITTI ``times.txt``: one timestamp in seconds per line (the inverse of
    :func:`read_kitti_times`; the shortest text that reads back exactly).

    Args:
        path: the file (replaced atomically).
        timestamps: ``(N,)`` seconds, finite, N >= 1.
    """
    times = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if times.size == 0 or not np.isfinite(times).all():
        raise ValueError(f"{path}: timestamps must be N >= 1 finite seconds, got {times[:5]}")
    atomic_write_text(Path(path), "".join(f"{_format_number(t)}\n" for t in times))


def write_tum_poses(path: str | os.PathLike[str], timestamps: object, poses: object) -> None:
    """Write a TUM trajectory file (``timestamp tx ty tz qx qy qz qw`` per line).

    Args:
        path: the file (replaced atomically).
        timestamps: ``(N,)`` seconds, finite.
        poses: ``(N, 4, 4)`` or ``(N, 3, 4)`` camera-to-world poses, finite, N >= 1. The rotation
            blocks are converted to unit quaternions ``(qx, qy, qz, qw)`` by scipy.
    """
    from scipy.spatial.transform import Rotation

    array = _as_poses(poses)
    times = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if times.shape[0] != array.shape[0]:
        raise ValueError(f"{times.shape[0]} timestamps for {array.shape[0]} poses")
    if not np.isfinite(times).all():
        raise ValueError("timestamps contain non-finite values")
    quat = Rotation.from_matrix(array[:, :3, :3]).as_quat()
    table = np.concatenate([times[:, None], array[:, :3, 3], quat], axis=1)
    text = "".join(" ".join(map(_format_number, row)) + "\n" for row in table)
    atomic_write_text(Path(path), text)


def write_trajectory(
    directory: str | os.PathLike[str], name: str, timestamps: object, poses: object
) -> tuple[Path, Path]:
    """Write one trajectory in both distributed formats, the layout evo and the devkit read:
    ``<directory>/poses/kitti/<name>.txt`` and ``<directory>/poses/tum/<name>.txt``.

    Args:
        directory: the run directory.
        name: the file stem (a sequence, e.g. ``09``; ``09_gt`` for its ground truth).
        timestamps: ``(N,)`` seconds for the TUM file.
        poses: ``(N, 4, 4)`` or ``(N, 3, 4)`` camera-to-world poses (metres).

    Returns:
        The KITTI and the TUM path.
    """
    kitti = Path(directory) / "poses" / "kitti" / f"{name}.txt"
    tum = Path(directory) / "poses" / "tum" / f"{name}.txt"
    write_kitti_poses(kitti, poses)
    write_tum_poses(tum, timestamps, poses)
    return kitti, tum


def frame_times(dataset: object, seq: str, frames: np.ndarray, frame_rate: float) -> np.ndarray:
    """``(N,)`` TUM timestamps (s) of ``frames`` of sequence ``seq``: the dataset's own clock
    where it has one (``dataset.timestamps(seq)``, KITTI's ``times.txt``, so that
    ``mfg-eval-poses`` matches the files to KITTI's ground truth by time), else
    ``frame / frame_rate``.

    Args:
        dataset: the split's dataset, or None; any object with a ``timestamps(seq)`` method
            returning one time (s) per frame of the sequence, or None, has a clock.
        seq: the sequence name.
        frames: ``(N,)`` frame indices.
        frame_rate: frames per second of the fallback clock.
    """
    clock = getattr(dataset, "timestamps", None)
    times = clock(seq) if clock is not None else None
    if times is not None and len(times) > int(frames.max()):
        return np.asarray(times, np.float64)[frames]
    return frames.astype(np.float64) / frame_rate
