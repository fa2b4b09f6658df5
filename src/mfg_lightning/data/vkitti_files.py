"""Virtual KITTI 1.3.1 and 2.0.3 on disk: the tree of each version (:class:`VkittiLayout`,
checked by :func:`check_vkitti_root`) and its camera text files (world-to-camera extrinsics,
2.0.3's intrinsics), read by :class:`~mfg_lightning.data.vkitti.VirtualKittiDataset` and written
by :mod:`mfg_lightning.data.export` (``docs/formats.md``)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mfg_lightning.core.data_errors import (
    DataLineError,
    DataRootError,
    frame_problem,
    intrinsics_problem,
    rigid_problem,
)
from mfg_lightning.data.file_datasets import check_data_root, read_text_lines, some_of

__all__ = [
    "VKITTI1_LAYOUT",
    "VKITTI2_LAYOUT",
    "VkittiLayout",
    "check_vkitti_root",
    "normalize_version",
    "read_vkitti_extrinsics",
    "read_vkitti_intrinsics",
    "write_vkitti_extrinsics",
    "write_vkitti_intrinsics",
]

VKITTI1_LAYOUT = """\
<data_root>/                          (the unpacked Virtual KITTI 1.3.1 tarballs)
├── vkitti_1.3.1_rgb/0001/clone/00000.png 00001.png …
├── vkitti_1.3.1_depthgt/0001/clone/00000.png …        16-bit depth, cm
├── vkitti_1.3.1_flowgt/0001/clone/00000.png …         16-bit forward flow
└── vkitti_1.3.1_extrinsicsgt/0001_clone.txt …         world-to-camera 4×4 per frame
    (worlds 0001 0002 0006 0018 0020; variations clone, 15-deg-left, …, fog, rain)"""

VKITTI2_LAYOUT = """\
<data_root>/                          (the unpacked Virtual KITTI 2.0.3 tarballs)
├── vkitti_2.0.3_rgb/Scene01/clone/frames/rgb/Camera_0/rgb_00000.jpg …
├── vkitti_2.0.3_depth/Scene01/clone/frames/depth/Camera_0/depth_00000.png …
├── vkitti_2.0.3_forwardFlow/Scene01/clone/frames/forwardFlow/Camera_0/flow_00000.png …
└── vkitti_2.0.3_textgt/Scene01/clone/extrinsic.txt, intrinsic.txt
    (scenes Scene01 Scene02 Scene06 Scene18 Scene20; variations clone, 15-deg-left, …)"""


def normalize_version(version: Any) -> int:
    """``1``, ``"1.3.1"`` → 1; ``2``, ``"2.0.3"`` → 2."""
    text = str(version).strip()
    if text in ("1", "1.3", "1.3.1"):
        return 1
    if text in ("2", "2.0", "2.0.3"):
        return 2
    raise ValueError(
        f"dataset.version must be 1 (Virtual KITTI 1.3.1) or 2 (2.0.3), got {version!r}"
    )


# --------------------------------------------------------------------------------------------
# Text files
# --------------------------------------------------------------------------------------------


def _numeric_rows(path: Path, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows after the header line of a whitespace-separated table.

    Returns:
        ``(table, lines)``: float64 ``(N, width)`` and the 1-based line number of each row.

    Raises:
        DataLineError: a row with another number of fields, a field that is not a number or a
            non-finite one, naming the file and the line.
    """
    rows, lines = [], []
    for number, line in enumerate(read_text_lines(path)[1:], start=2):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != width:
            raise DataLineError(path, number, f"{len(fields)} fields, expected {width}")
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise DataLineError(path, number, "a field is not a number") from None
        if not np.isfinite(values).all():
            raise DataLineError(path, number, "non-finite entries (nan, inf or out of range)")
        rows.append(values)
        lines.append(number)
    if not rows:
        raise DataLineError(path, 1, "no rows after the header line")
    return np.array(rows, np.float64).reshape(-1, width), np.array(lines, np.int64)


def _camera_rows(path: Path, table: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """The rows of camera 0 of a 2.0.3 table (``frame cameraID …``); every camera ID must be a
    whole number ≥ 0 and every camera's frames unique and increasing."""
    cameras = table[:, 1]
    bad = np.flatnonzero((cameras != np.round(cameras)) | (cameras < 0))
    if bad.size:
        i = int(bad[0])
        raise DataLineError(
            path, int(lines[i]), f"camera ID {float(cameras[i])!r} is not a whole number >= 0"
        )
    for camera in np.unique(cameras):
        mine = cameras == camera
        _check_frames(path, table[mine, 0], lines[mine])
    if not (cameras == 0).any():
        raise DataLineError(path, 1, "no rows of camera 0 (Camera_0, the camera read)")
    return cameras == 0


def _check_frames(path: Path, frames: np.ndarray, lines: np.ndarray) -> None:
    problem = frame_problem(frames, lines)
    if problem is not None:
        raise DataLineError(path, int(lines[problem[0]]), problem[1])


def read_vkitti_extrinsics(path: str | os.PathLike, version: int = 1) -> dict[int, np.ndarray]:
    """World-to-camera extrinsics per frame (camera 0 for 2.0.3).

    1.3.1: ``frame`` then 16 numbers per line; 2.0.3: ``frame cameraID`` then 16 numbers. Frame
    numbers must be whole, unique and increasing (per camera), and every matrix a rigid
    transform (:func:`~mfg_lightning.core.data_errors.rigid_problem`).

    Returns:
        frame → ``(4, 4)`` float64 world-to-camera matrix (``T_cam_world``, metres).

    Raises:
        DataLineError: naming the file and the line of the first bad row.
    """
    path = Path(path)
    if version == 1:
        table, lines = _numeric_rows(path, 17)
        _check_frames(path, table[:, 0], lines)
        mine = np.ones(len(table), bool)
    else:
        table, lines = _numeric_rows(path, 18)
        mine = _camera_rows(path, table, lines)
    mats = table[:, -16:].reshape(-1, 4, 4)
    problem = rigid_problem(mats)
    if problem is not None:
        raise DataLineError(path, int(lines[problem[0]]), problem[1])
    return {int(f): m for f, m in zip(table[mine, 0], mats[mine], strict=True)}


def read_vkitti_intrinsics(
    path: str | os.PathLike, image_hw: tuple[int, int] | None = None
) -> dict[int, np.ndarray]:
    """2.0.3 ``intrinsic.txt``: ``frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]`` per line. Frame
    numbers must be whole, unique and increasing (per camera), focal lengths positive and, with
    ``image_hw``, the principal point inside the image
    (:func:`~mfg_lightning.core.data_errors.intrinsics_problem`).

    Args:
        path: the file.
        image_hw: ``(height, width)`` of the world's images, or None.

    Returns:
        frame → ``(4,)`` ``(fx, fy, cx, cy)`` of camera 0 in native pixels.

    Raises:
        DataLineError: naming the file and the line of the first bad row.
    """
    path = Path(path)
    table, lines = _numeric_rows(path, 6)
    mine = _camera_rows(path, table, lines)
    problem = intrinsics_problem(table[:, 2:], image_hw)
    if problem is not None:
        raise DataLineError(path, int(lines[problem[0]]), problem[1])
    return {int(row[0]): row[2:].copy() for row in table[mine]}


_MATRIX_HEADER = "r1,1 r1,2 r1,3 t1 r2,1 r2,2 r2,3 t2 r3,1 r3,2 r3,3 t3 0 0 0 1"


def _write_table(path: str | os.PathLike, header: str, rows: np.ndarray, ints: int) -> None:
    """A header line, then one row per line: the first ``ints`` columns as integers, the rest as
    the shortest text that reads back exactly (``repr``)."""
    from mfg_lightning.core.atomic import atomic_write_text

    lines = [header]
    for row in rows:
        lines.append(
            " ".join([str(int(v)) for v in row[:ints]] + [repr(float(v)) for v in row[ints:]])
        )
    atomic_write_text(path, "\n".join(lines) + "\n")


def write_vkitti_extrinsics(path: str | os.PathLike, extrinsics: Any, version: int = 1) -> None:
    """Write world-to-camera extrinsics, one line per frame (the inverse of
    :func:`read_vkitti_extrinsics`): 1.3.1 ``frame`` then 16 numbers; 2.0.3 ``frame cameraID``
    (camera 0) then 16 numbers, each after its header line.

    Args:
        path: the file (replaced atomically).
        extrinsics: ``(N, 4, 4)`` world-to-camera matrices ``T_cam_world`` of frames 0 … N−1
            (metres), finite rigid transforms.
        version: 1 (1.3.1) or 2 (2.0.3).
    """
    mats = np.asarray(extrinsics, np.float64)
    if mats.ndim != 3 or mats.shape[1:] != (4, 4) or not np.isfinite(mats).all():
        raise ValueError(f"{path}: extrinsics must be finite (N, 4, 4), got {mats.shape}")
    problem = rigid_problem(mats)
    if problem is not None:  # a file no reader takes
        raise ValueError(f"{path}: extrinsics[{problem[0]}]: {problem[1]}")
    frames = np.arange(len(mats), dtype=np.float64)[:, None]
    if normalize_version(version) == 1:
        _write_table(path, f"frame {_MATRIX_HEADER}", np.hstack([frames, mats.reshape(-1, 16)]), 1)
    else:
        table = np.hstack([frames, np.zeros_like(frames), mats.reshape(-1, 16)])
        _write_table(path, f"frame cameraID {_MATRIX_HEADER}", table, 2)


def write_vkitti_intrinsics(path: str | os.PathLike, intrinsics: Any) -> None:
    """Write a 2.0.3 ``intrinsic.txt`` (the inverse of :func:`read_vkitti_intrinsics`): the
    header, then ``frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]`` per frame (camera 0).

    Args:
        path: the file (replaced atomically).
        intrinsics: ``(N, 4)`` ``(fx, fy, cx, cy)`` of frames 0 … N−1 in pixels, finite,
            ``fx, fy > 0``.
    """
    K = np.asarray(intrinsics, np.float64)
    if K.ndim != 2 or K.shape[1] != 4 or not np.isfinite(K).all():
        raise ValueError(f"{path}: intrinsics must be finite (N, 4), got {K.shape}")
    problem = intrinsics_problem(K)
    if problem is not None:  # a file no reader takes
        raise ValueError(f"{path}: intrinsics[{problem[0]}]: {problem[1]}")
    frames = np.arange(len(K), dtype=np.float64)[:, None]
    table = np.hstack([frames, np.zeros_like(frames), K])
    _write_table(path, "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]", table, 2)


# --------------------------------------------------------------------------------------------
# Layout
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VkittiLayout:
    """Paths of one Virtual KITTI version under ``root`` (the reader's, and the writer's in
    :mod:`mfg_lightning.data.export`)."""

    root: Path
    version: int

    @property
    def tag(self) -> str:
        return "vkitti_1.3.1" if self.version == 1 else "vkitti_2.0.3"

    @property
    def tree(self) -> str:
        return VKITTI1_LAYOUT if self.version == 1 else VKITTI2_LAYOUT

    def _scene(self, world: str) -> str:
        return world if self.version == 1 else f"Scene{int(world):02d}"

    def top_dirs(self) -> list[Path]:
        names = (
            ("rgb", "depthgt", "flowgt", "extrinsicsgt")
            if self.version == 1
            else ("rgb", "depth", "forwardFlow", "textgt")
        )
        return [self.root / f"{self.tag}_{n}" for n in names]

    def rgb_dir(self, world: str, var: str) -> Path:
        if self.version == 1:
            return self.root / f"{self.tag}_rgb" / world / var
        return self.root / f"{self.tag}_rgb" / self._scene(world) / var / "frames/rgb/Camera_0"

    def depth_dir(self, world: str, var: str) -> Path:
        if self.version == 1:
            return self.root / f"{self.tag}_depthgt" / world / var
        return self.root / f"{self.tag}_depth" / self._scene(world) / var / "frames/depth/Camera_0"

    def flow_dir(self, world: str, var: str) -> Path:
        if self.version == 1:
            return self.root / f"{self.tag}_flowgt" / world / var
        return (
            self.root / f"{self.tag}_forwardFlow" / self._scene(world) / var
            / "frames/forwardFlow/Camera_0"
        )  # fmt: skip

    def extrinsics_file(self, world: str, var: str) -> Path:
        if self.version == 1:
            return self.root / f"{self.tag}_extrinsicsgt" / f"{world}_{var}.txt"
        return self.root / f"{self.tag}_textgt" / self._scene(world) / var / "extrinsic.txt"

    def intrinsics_file(self, world: str, var: str) -> Path | None:
        if self.version == 1:
            return None
        return self.root / f"{self.tag}_textgt" / self._scene(world) / var / "intrinsic.txt"

    # file names: (prefix, suffix) of rgb, depth, flow
    def names(self) -> dict[str, tuple[str, str]]:
        if self.version == 1:
            return {"rgb": ("", ".png"), "depth": ("", ".png"), "flow": ("", ".png")}
        return {"rgb": ("rgb_", ".jpg"), "depth": ("depth_", ".png"), "flow": ("flow_", ".png")}

    def directory(self, kind: str, world: str, var: str) -> Path:
        """The directory of the ``rgb``, ``depth`` or ``flow`` files of one world."""
        return {"rgb": self.rgb_dir, "depth": self.depth_dir, "flow": self.flow_dir}[kind](
            world, var
        )

    def file(self, kind: str, world: str, var: str, frame: int) -> Path:
        prefix, suffix = self.names()[kind]
        return self.directory(kind, world, var) / f"{prefix}{frame:05d}{suffix}"


def check_vkitti_root(
    data_root: str | os.PathLike | None, version: int, worlds: Sequence[str], variation: str
) -> VkittiLayout:
    """Return the layout, or raise ONE :class:`DataRootError` listing what is missing and showing
    the expected tree."""
    tree = VKITTI1_LAYOUT if version == 1 else VKITTI2_LAYOUT
    name = "Virtual KITTI 1.3.1" if version == 1 else "Virtual KITTI 2.0.3"
    root = check_data_root(data_root, f"the directory holding the unpacked {name} tarballs", tree)
    layout = VkittiLayout(root.resolve(), version)
    missing = [d for d in layout.top_dirs() if not d.is_dir()]
    if not missing:
        for world in worlds:
            needed = [
                layout.rgb_dir(world, variation),
                layout.depth_dir(world, variation),
                layout.flow_dir(world, variation),
                layout.extrinsics_file(world, variation),
            ]
            intr = layout.intrinsics_file(world, variation)
            missing += [p for p in [*needed, intr] if p is not None and not p.exists()]
    if missing:
        other = VkittiLayout(layout.root, 3 - version)
        hint = ""
        if all(d.is_dir() for d in other.top_dirs()):
            hint = f"\n(this looks like the other version: set dataset.version={3 - version})"
        raise DataRootError(
            f"dataset.data_root={root} does not look like {name} (variation {variation}); "
            f"missing:\n{some_of(missing, 20)}{hint}\nExpected layout:\n{tree}"
        )
    return layout
