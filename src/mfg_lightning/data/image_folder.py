"""A plain folder of images (one's own video) as a DataModule for prediction without ground truth.

Layout read (``data_root`` is never written to)::

    <data_root>/<any name matching dataset.pattern>    one frame per file, 8-bit PNG or JPEG,
                                                       all of the same size

The frames are the files matching ``pattern`` (default ``*.png``) in natural name order
(``img2`` before ``img10``); frame ``k`` is the k-th of them. The camera is given in the config:
``fx fy cx cy`` in pixels of the native (file) image size, scaled to the model's input size like
KITTI's ``P2``. Timestamps are ``k / frame_rate``, or the lines of ``times`` (one number of
seconds per frame, as KITTI's ``times.txt``).

The only split is ``predict`` (every pair ``k → k + 1``, no ground truth): training and
evaluation need poses and refuse this dataset with a clear error. Flow is computed exactly as
for KITTI (:class:`~mfg_lightning.data.sequences.ImageSequenceDataset`, the engine both build on:
OpenCV's DIS on the grey images, cached under ``<cache_dir>/kitti_flow/``, the RGB frame cached
beside it), of which this dataset is the layout only.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from torch.utils.data import DataLoader

from mfg_lightning.core.data_errors import DataFileError
from mfg_lightning.data.base import MFGDataModule, normalize_sequence
from mfg_lightning.data.file_datasets import check_data_root
from mfg_lightning.data.sequences import ImageSequence, ImageSequenceDataset, image_flow_source
from mfg_lightning.flow import io as flow_io
from mfg_lightning.trajectory import pose_io

__all__ = ["ImageFolderDataModule", "ImageFolderDataset", "NoGroundTruthError"]


class NoGroundTruthError(ValueError):
    """Training or evaluation asked for a dataset that has no ground-truth poses."""


def _natural_key(path: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def check_intrinsics(fx: Any, fy: Any, cx: Any, cy: Any) -> np.ndarray:
    """``(4,)`` float64 ``(fx, fy, cx, cy)`` from the config, or a :class:`ValueError` naming
    the keys that are unset, not numbers, not finite or (focal lengths) not positive."""
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    unset = [k for k, v in values.items() if v is None]
    if unset:
        raise ValueError(
            f"dataset.{', dataset.'.join(unset)} not set: the camera's intrinsics in pixels at "
            "the native image size, e.g. dataset.fx=718.9 dataset.fy=718.9 dataset.cx=607.2 "
            "dataset.cy=185.2"
        )
    out = []
    for key, value in values.items():
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"dataset.{key} must be a number of pixels, got {value!r}") from None
        if not np.isfinite(number) or (key in ("fx", "fy") and number <= 0):
            raise ValueError(f"dataset.{key} must be finite (focal lengths > 0), got {value!r}")
        out.append(number)
    return np.array(out)


class ImageFolderDataset(ImageSequenceDataset):
    """The frames of one folder as one sequence without ground truth (see the module docstring).

    Args:
        data_root: the folder.
        intrinsics: ``(fx, fy, cx, cy)`` in pixels of the native image size.
        pattern: glob pattern of the frames inside ``data_root`` (not recursive unless it says
            ``**``).
        sequence: the sequence name in outputs (default: the folder's name).
        frame_rate: frames per second, for timestamps when ``times`` is not given.
        times: a text file of one timestamp (seconds) per frame, or None.
        kwargs: the flow and input-size arguments of
            :class:`~mfg_lightning.data.sequences.ImageSequenceDataset` (``height``, ``width``,
            ``flow``, ``cache_dir``, ``load_rgb``).
    """

    name = "image_folder"
    title = "image folder"

    def __init__(
        self,
        data_root: str | os.PathLike | None,
        intrinsics: Sequence[float],
        pattern: str = "*.png",
        sequence: str | None = None,
        frame_rate: float = 10.0,
        times: str | os.PathLike | None = None,
        **kwargs: Any,
    ) -> None:
        if not pattern or Path(pattern).is_absolute():
            raise ValueError(
                f"dataset.pattern must be a glob relative to data_root, got {pattern!r}"
            )
        if not float(frame_rate) > 0:
            raise ValueError(f"dataset.frame_rate must be positive (Hz), got {frame_rate}")
        self.pattern = pattern
        self.native_intrinsics = np.asarray(intrinsics, np.float64)
        self.frame_rate = float(frame_rate)
        self.times_file = Path(times).expanduser() if times else None
        self._files: list[Path] = []
        root = self._check_root(data_root)
        name = normalize_sequence(sequence) if sequence else root.name
        super().__init__(root, [name], offsets=(1,), split="predict", require_poses=False, **kwargs)

    def _check_root(self, data_root: str | os.PathLike | None) -> Path:
        root = check_data_root(
            data_root, "a folder of images, e.g. dataset.data_root=/data/my_drive/frames"
        )
        return root.resolve()

    def _layout_key(self) -> dict[str, Any]:
        # Frame k is the k-th match of the pattern: another pattern, other frames.
        return {"pattern": self.pattern}

    def _load_sequence(self, seq: str) -> tuple[ImageSequence, list[int], list[str]]:
        self._files = sorted(
            (p for p in self.root.glob(self.pattern) if p.is_file()), key=_natural_key
        )
        if len(self._files) < 2:
            raise DataFileError(
                f"{self.root}: {len(self._files)} file(s) match dataset.pattern={self.pattern!r}; "
                "prediction needs at least two frames"
            )
        native_hw = flow_io.image_size(self._files[0])
        n = len(self._files)
        info = ImageSequence(seq, self.root, self.native_intrinsics, native_hw, None, n)
        return info, list(range(n)), []

    def image_path(self, seq: str, frame: int) -> Path:
        return self._files[frame]

    def timestamps(self, seq: str) -> np.ndarray:
        """``(n_frames,)`` seconds: the ``times`` file's lines, or ``k / frame_rate``."""
        n = len(self._files)
        if self.times_file is None:
            return np.arange(n, dtype=np.float64) / self.frame_rate
        try:
            times = pose_io.read_kitti_times(self.times_file)
        except pose_io.PoseFileError as err:
            raise DataFileError(str(err)) from None
        if len(times) != n:
            raise DataFileError(
                f"{self.times_file}: {len(times)} timestamps for {n} frames matching "
                f"{self.root / self.pattern}"
            )
        return times


class ImageFolderDataModule(MFGDataModule):
    """A folder of images with intrinsics from the config; only the ``predict`` split.

    Args:
        data_root: the folder of frames.
        fx, fy, cx, cy: the camera in pixels of the native image size (required).
        pattern, sequence, frame_rate, times: see :class:`ImageFolderDataset`.
        flow, cache_dir, load_rgb: the flow source (the ``flow`` config group: ``flow=dis`` by
            default, or ``flow=files``) and its cache, as for KITTI
            (:class:`~mfg_lightning.data.sequences.ImageSequenceDataset`).
        kwargs: ``height``, ``width``, ``eval_batch_size``, ``num_workers``, … of
            :class:`~mfg_lightning.data.base.MFGDataModule` (batches of ``eval_batch_size``).
    """

    def __init__(
        self,
        data_root: str | None = None,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        pattern: str = "*.png",
        sequence: str | None = None,
        frame_rate: float = 10.0,
        times: str | None = None,
        flow: dict[str, Any] | None = None,
        cache_dir: str | None = None,
        load_rgb: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.data_root = data_root
        self.dataset_kwargs: dict[str, Any] = {
            "intrinsics": check_intrinsics(fx, fy, cx, cy),
            "pattern": pattern,
            "sequence": sequence,
            "frame_rate": frame_rate,
            "times": times,
            "height": self.height,
            "width": self.width,
            "flow": image_flow_source(flow),
            "cache_dir": cache_dir,
            "load_rgb": load_rgb,
        }

    def build_dataset(self, split: str) -> ImageFolderDataset:
        if split != "predict":
            raise NoGroundTruthError(
                f"dataset=image_folder has no ground-truth poses, so no {split} split for "
                "training or evaluation; run python -m mfg_lightning.predict on it"
            )
        return ImageFolderDataset(self.data_root, **self.dataset_kwargs)

    def predict_dataloader(self) -> DataLoader:
        return self._loader("predict", shuffle=False, batch_size=self.eval_batch_size)
