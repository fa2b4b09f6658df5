"""KITTI odometry as a Lightning DataModule, with optical flow from OpenCV's DIS (cached on
disk) or the user's own files: the ``flow`` config group (``flow=dis``, the default, or
``flow=files``).

Layout read (``docs/formats.md``; ``data_root`` is the unpacked download, never
written to)::

    <data_root>/sequences/XX/image_2/000000.png …   left colour camera, 8-bit PNG
    <data_root>/sequences/XX/calib.txt              "P2: …" 3×4 projection, row-major
    <data_root>/poses/XX.txt                        12 floats per frame: T_world_cam, row-major 3×4

Split (the paper, after Zhou et al. 2017): train 00–08, test 09 and 10. Validation: a contiguous
tail of each *training* sequence (``val_fraction``, default 5 %, at least one pair per sequence;
:func:`~mfg_lightning.data.transforms.holdout_ranges`); those frames leave the training split, and
the test sequences are never touched.

Samples: for every source frame ``t`` and offset ``o`` in ``offsets`` (default ``[1]``) whose
target ``t + o`` exists, one sample ``t → t + o`` (sorted by sequence, source frame, then the order
of ``offsets``); ``backward_flow=true`` adds ``t → t − o`` to the training split (the paper's
augmentation). ``offsets: [-2, -1, 1, 2]`` gives the flows from a centre frame to its
neighbours, for the central-frame ATE protocol.

Flow, one of:

* **computed** (``flow=dis``, the default): OpenCV's DIS (``cv2.DISOpticalFlow``) on the grey
  images at ``flow.height × flow.width`` (null: the native size), resized to the model's input
  size and cached as ``.npy`` under
  ``<cache_dir>/kitti_flow/<key>/<seq>@<H>x<W>/<src:06d>_<tgt:06d>.npy``
  where ``<key>`` hashes everything that changes the result (estimator, preset and parameters,
  OpenCV version, the output size, the resolved ``data_root``) and ``<H>x<W>`` is the size the
  flow was computed at. :meth:`KittiDataModule.prepare_data` fills the cache once (rank 0, with a
  progress bar); later epochs and runs only read it. Writes are atomic (temporary file then
  ``os.replace``), so concurrent readers and writers are safe. The source image at the input
  size is cached beside it (``<seq>_rgb/<frame:06d>.npy``), so a cached epoch decodes no PNG.
  Default preset ``medium`` at the native size: of the three presets it had the lowest error on
  a synthetic KITTI-sized pair with known flow (end-point error at 48×128 about 3× lower than
  ``fast``), at 25–40 ms per pair on two CPU cores; computed once, it costs nothing afterwards.
* **user-supplied** (``flow=files flow.dir=<flow_dir>``): precomputed files named
  ``<flow_dir>/<seq>/<src:06d>_<tgt:06d>.<ext>`` (e.g. ``flow/09/000000_000001.flo``), one file
  per sample (source → target, any offset), ``ext`` one of ``flo``, ``png`` (KITTI flow PNG),
  ``npy``, ``npz``. The flow may be at any resolution covering the whole image; it is resized
  and its values rescaled. A missing file is an error listing the expected names.

Poses: ``sample['pose'] = T_world_cam(src)^-1 · T_world_cam(tgt)`` (camera at the target in the
camera at the source), from :func:`mfg_lightning.core.geometry.relative_pose`. Intrinsics come from
``P2`` and are scaled to the input size.

Sequences without ground truth (KITTI ships ``poses/`` for 00–10 only): the ``predict`` split
(:mod:`mfg_lightning.predict`) holds the test sequences, every pair ``t → t + 1``, and reads
``poses/XX.txt`` only if it is there; its samples have no ``pose`` when it is not. Training,
validation and test need the pose files and name the missing ones.

This module is the KITTI layout (``calib.txt``, ``poses/XX.txt``, ``times.txt``, the split); the
sample index, flow, its caches, poses and intrinsics at the input size are the engine shared
with a folder of images, :class:`~mfg_lightning.data.sequences.ImageSequenceDataset`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning.core.data_errors import (
    DataFileError,
    DataLineError,
    DataRootError,
    intrinsics_problem,
)
from mfg_lightning.data.base import (
    MFGDataModule,
    check_split,
    normalize_sequence,
    split_sequences,
)
from mfg_lightning.data.file_datasets import (
    check_data_root,
    list_numbered,
    read_text_lines,
    some_of,
)
from mfg_lightning.data.sequences import ImageSequence, ImageSequenceDataset, image_flow_source
from mfg_lightning.flow import io as flow_io

# Re-exported: the flow estimator, presets and cache that KITTI's flow uses, imported from here.
from mfg_lightning.flow.estimators import DIS_PRESETS, DISFlowEstimator, FlowCache, FlowFiles
from mfg_lightning.trajectory import pose_io

log = logging.getLogger(__name__)

__all__ = [
    "DIS_PRESETS",
    "KITTI_LAYOUT",
    "DISFlowEstimator",
    "FlowCache",
    "KittiDataModule",
    "KittiOdometryDataset",
    "normalize_sequence",
    "read_kitti_calib",
    "read_kitti_poses_as_data_file",
    "write_kitti_calib",
]

TRAIN_SEQUENCES = ("00", "01", "02", "03", "04", "05", "06", "07", "08")
TEST_SEQUENCES = ("09", "10")
KITTI_LAYOUT = """\
<data_root>/                      (the unpacked KITTI odometry download)
├── sequences/
│   ├── 00/
│   │   ├── calib.txt             "P2: 12 floats" (and P0, P1, P3, Tr)
│   │   ├── times.txt
│   │   └── image_2/000000.png 000001.png …
│   ├── 01/ …
│   └── 10/
└── poses/
    ├── 00.txt                    one line per frame: 12 floats, T_world_cam
    ├── …
    └── 10.txt"""

# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def read_kitti_calib(
    path: str | os.PathLike, image_hw: tuple[int, int] | None = None
) -> np.ndarray:
    """``(fx, fy, cx, cy)`` of the left colour camera (``P2``) from a KITTI ``calib.txt``.

    Args:
        path: the file.
        image_hw: ``(height, width)`` of the sequence's images, or None.

    Returns:
        ``(4,)`` float64 in pixels of the native image.

    Raises:
        DataFileError: no ``P2`` line; :class:`~mfg_lightning.core.data_errors.DataLineError`
            naming the line of a ``P2`` without 12 finite numbers, with a focal length that is
            not positive or (with ``image_hw``) a principal point outside the image
            (:func:`~mfg_lightning.core.data_errors.intrinsics_problem`).
    """
    for number, line in enumerate(read_text_lines(path), start=1):
        key, _, rest = line.partition(":")
        if key.strip() == "P2":
            try:
                P = np.array([float(x) for x in rest.split()], np.float64)
            except ValueError:
                raise DataLineError(path, number, "P2 has a non-numeric entry") from None
            if P.size != 12:
                raise DataLineError(path, number, f"P2 has {P.size} numbers, expected 12")
            if not np.isfinite(P).all():
                raise DataLineError(path, number, "P2 has a non-finite entry")
            P = P.reshape(3, 4)
            K = np.array([P[0, 0], P[1, 1], P[0, 2], P[1, 2]])
            problem = intrinsics_problem(K, image_hw)
            if problem is not None:
                raise DataLineError(path, number, f"P2: {problem[1]}")
            return K
    raise DataFileError(f"{path}: no 'P2:' line (the left colour camera's projection matrix)")


#: KITTI's stereo baseline (metres, about 0.54 m): the right cameras' P1 and P3 in calib files
#: this project writes (:func:`write_kitti_calib`).
KITTI_STEREO_BASELINE = 0.54


def write_kitti_calib(
    path: str | os.PathLike, intrinsics: Any, baseline: float = KITTI_STEREO_BASELINE
) -> None:
    """Write a KITTI odometry ``calib.txt`` for one pinhole camera (the inverse of
    :func:`read_kitti_calib`).

    ``P0`` and ``P2`` (the left grey and colour cameras) are ``K [I | 0]``: the camera the poses
    and ``image_2`` belong to; ``P1`` and ``P3`` (the right cameras) are ``K [I | (−baseline, 0,
    0)]``, as KITTI's stereo rig; ``Tr`` (Velodyne to camera) is ``[I | 0]``. Numbers are
    written as KITTI writes them (``%.12e``), with more digits where that would not read back
    exactly.

    Args:
        path: the file (replaced atomically).
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)`` in pixels, finite, ``fx, fy > 0``.
        baseline: the stereo baseline in metres.
    """
    from mfg_lightning.core.atomic import atomic_write_text

    fx, fy, cx, cy = (float(v) for v in np.asarray(intrinsics, np.float64).reshape(4))
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise ValueError(f"{path}: intrinsics must be finite (fx, fy, cx, cy), fx, fy > 0")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    left = np.concatenate([K, np.zeros((3, 1))], axis=1)
    right = np.concatenate([K, K @ np.array([[-float(baseline)], [0.0], [0.0]])], axis=1)
    rows = {"P0": left, "P1": right, "P2": left, "P3": right, "Tr": np.eye(3, 4)}
    text = "".join(f"{key}: {' '.join(map(_sci, M.ravel()))}\n" for key, M in rows.items())
    atomic_write_text(path, text)


def _sci(value: float) -> str:
    """KITTI's ``%.12e`` when that reads back exactly, else the 17 digits that always do."""
    text = f"{value:.12e}"
    return text if float(text) == value else f"{value:.16e}"


def read_kitti_poses_as_data_file(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI pose file (``poses/XX.txt``) with
    :func:`mfg_lightning.trajectory.pose_io.read_kitti_poses`, its errors raised as a bad data
    file (:class:`~mfg_lightning.core.data_errors.DataFileError`, not
    :class:`~mfg_lightning.trajectory.pose_io.PoseFileError`).

    Returns:
        ``(N, 4, 4)`` float64 ``T_world_cam`` (camera-to-world, metres).

    Raises:
        DataFileError: naming the file and line, so ``skip_bad_samples`` and the check tool treat
            it like any other bad data file.
    """
    try:
        return pose_io.read_kitti_poses(path)
    except pose_io.PoseFileError as err:
        raise DataFileError(str(err)) from None


# --------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------


def check_kitti_root(
    data_root: str | os.PathLike | None, sequences: Iterable[str], poses: bool = True
) -> Path:
    """Return the resolved root, or raise ONE :class:`DataRootError` listing every missing
    entry and showing the expected layout. ``poses=False``: ``poses/`` is not required."""
    root = check_data_root(
        data_root,
        "the unpacked KITTI odometry download, e.g. dataset.data_root=/data/kitti/dataset",
        KITTI_LAYOUT,
    )
    # List the highest missing level only (a whole sequence, the poses/ directory), so an
    # empty or mistyped root gives a short list.
    missing = []
    for seq in sequences:
        if not (root / "sequences" / seq).is_dir():
            missing.append(f"sequences/{seq}/")
            continue
        for rel in (f"sequences/{seq}/image_2", f"sequences/{seq}/calib.txt"):
            if not (root / rel).exists():
                missing.append(rel)
    if poses and not (root / "poses").is_dir():
        missing.append("poses/")
    elif poses:
        missing += [
            f"poses/{s}.txt" for s in sequences if not (root / "poses" / f"{s}.txt").exists()
        ]
    if missing:
        hint = ""
        if all(m.startswith("poses/") for m in missing):
            hint = (
                "\nTraining and evaluation need ground-truth poses (KITTI has them for 00–10); "
                "python -m mfg_lightning.predict runs on sequences without them."
            )
        raise DataRootError(
            f"dataset.data_root={root} does not look like KITTI odometry; missing:\n"
            f"{some_of([root / m for m in missing], 20)}{hint}\nExpected layout:\n{KITTI_LAYOUT}"
        )
    return root.resolve()


class KittiOdometryDataset(ImageSequenceDataset):
    """Samples ``t → t + o`` of KITTI odometry sequences (see the module docstring): the KITTI
    layout of :class:`~mfg_lightning.data.sequences.ImageSequenceDataset`, which indexes the
    samples and delivers flow, RGB, poses and intrinsics.

    Args:
        data_root: the KITTI odometry root (holding ``sequences/`` and ``poses/``).
        sequences: sequence names (``"00"`` … ``"10"``).
        require_poses: False: a sequence without ``poses/XX.txt`` is read without ground truth.
        The other arguments are those of
        :class:`~mfg_lightning.data.sequences.ImageSequenceDataset`.
    """

    name = "kitti"
    title = "KITTI"

    def _check_root(self, data_root: str | os.PathLike | None) -> Path:
        return check_kitti_root(data_root, self.sequence_names, poses=self.require_poses)

    def _load_sequence(self, seq: str) -> tuple[ImageSequence, list[int], list[str]]:
        """``sequences/<seq>/``: ``image_2/`` frames, ``P2`` of ``calib.txt``, and the poses of
        ``poses/<seq>.txt`` (optional without ``require_poses``); frames beyond the poses are
        dropped and reported."""
        seq_dir = self.root / "sequences" / seq
        image_dir = seq_dir / "image_2"
        pose_file = self.root / "poses" / f"{seq}.txt"
        frames = list_numbered(image_dir)
        if not frames:
            raise DataFileError(f"{image_dir}: no frames (expected 000000.png, 000001.png, …)")
        native_hw = flow_io.image_size(image_dir / f"{frames[0]:06d}.png")
        intrinsics = read_kitti_calib(seq_dir / "calib.txt", native_hw)
        if not self.require_poses and not pose_file.exists():
            info = ImageSequence(seq, image_dir, intrinsics, native_hw, None, frames[-1] + 1)
            return info, frames, []
        poses = read_kitti_poses_as_data_file(pose_file)
        problems = []
        if len(poses) < len(frames) or frames[-1] >= len(poses):
            problems.append(
                f"{pose_file}: {len(poses)} poses for {len(frames)} images in {image_dir} "
                f"(frames ≥ {len(poses)} have no pose and are dropped)"
            )
        missing = sorted(set(range(len(poses))) - set(frames))
        if missing:
            shown = some_of([f"{m:06d}.png" for m in missing], 5, inline=True)
            problems.append(
                f"{image_dir}: {len(missing)} frame(s) listed in {pose_file} are missing: {shown}"
            )
        frames = [f for f in frames if f < len(poses)]
        info = ImageSequence(seq, image_dir, intrinsics, native_hw, poses, len(poses))
        return info, frames, problems

    def image_path(self, seq: str, frame: int) -> Path:
        return self._sequences[seq].image_dir / f"{frame:06d}.png"

    def timestamps(self, seq: str) -> np.ndarray | None:
        """``(n_frames,)`` seconds of frames 0 … n_frames − 1 from ``sequences/XX/times.txt``,
        or None when the file is absent or does not cover every frame."""
        path = self.root / "sequences" / seq / "times.txt"
        if not path.is_file():
            return None
        try:
            times = pose_io.read_kitti_times(path)
        except pose_io.PoseFileError as err:
            raise DataFileError(str(err)) from None
        n = self._sequences[seq].n_frames
        return times[:n] if len(times) >= n else None

    def _missing_poses_note(self) -> str:
        return f"no {self.root / 'poses'}/<seq>.txt"


# --------------------------------------------------------------------------------------------
# DataModule
# --------------------------------------------------------------------------------------------


class KittiDataModule(MFGDataModule):
    """KITTI odometry with the paper's split: train 00–08, test 09 and 10, validation a tail
    of each training sequence (see the module docstring for flow, caching and offsets).

    Args:
        data_root: the KITTI odometry root.
        train_sequences, test_sequences: the split.
        val_fraction: the validation tail of each training sequence (default 5 %).
        offsets: target offsets of every split (``[1]``; ``[-2, -1, 1, 2]`` for central-frame ATE).
        backward_flow: add the reversed offsets (``t → t − o``) to the training split.
        flow, cache_dir, load_rgb, skip_bad_samples: see :class:`KittiOdometryDataset` (``flow``:
            the ``flow`` config group, ``flow=dis`` by default).
        precompute_flow: fill the flow cache in :meth:`prepare_data` (otherwise flow is computed
            on first use by each loader worker).
        kwargs: ``height``, ``width``, ``batch_size``, … of
            :class:`~mfg_lightning.data.base.MFGDataModule`.
    """

    def __init__(
        self,
        data_root: str | None = None,
        train_sequences: Sequence[str] = TRAIN_SEQUENCES,
        test_sequences: Sequence[str] = TEST_SEQUENCES,
        val_fraction: float = 0.05,
        offsets: Sequence[int] = (1,),
        backward_flow: bool = False,
        flow: dict[str, Any] | None = None,
        cache_dir: str | None = None,
        load_rgb: bool = True,
        skip_bad_samples: bool = False,
        precompute_flow: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.data_root = data_root
        self.train_sequences = [normalize_sequence(s) for s in train_sequences]
        self.test_sequences = [normalize_sequence(s) for s in test_sequences]
        self.val_fraction = check_split(
            self.train_sequences, self.test_sequences, val_fraction, "sequences"
        )
        self.offsets = [int(o) for o in offsets]
        self.backward_flow = bool(backward_flow)
        self.precompute = bool(precompute_flow)
        # Parsed once here so that a bad flow config fails before anything is built or written.
        self.flow = image_flow_source(flow)
        self.dataset_kwargs: dict[str, Any] = {
            "height": self.height,
            "width": self.width,
            "flow": self.flow,
            "cache_dir": cache_dir,
            "load_rgb": load_rgb,
            "skip_bad_samples": skip_bad_samples,
            "val_fraction": self.val_fraction,
        }

    def split_offsets(self, split: str) -> list[int]:
        """The offsets of ``split``; training adds the reversed ones with ``backward_flow``."""
        if split == "train" and self.backward_flow:
            return self.offsets + [-o for o in self.offsets if -o not in self.offsets]
        return list(self.offsets)

    def build_dataset(self, split: str) -> KittiOdometryDataset:
        if split == "predict":
            # Trajectories compose consecutive motions: every pair t -> t + 1, poses optional.
            return KittiOdometryDataset(
                self.data_root, self.test_sequences, offsets=(1,), split="predict",
                require_poses=False, **self.dataset_kwargs,
            )  # fmt: skip
        sequences, portion = split_sequences(split, self.train_sequences, self.test_sequences)
        # Training and validation offsets have the same largest |offset| (backward_flow only
        # reverses them), so both parts cut each sequence at the same frame.
        return KittiOdometryDataset(
            self.data_root,
            sequences,
            offsets=self.split_offsets(split),
            split=split,
            portion=portion,
            **self.dataset_kwargs,
        )

    def predict_dataloader(self) -> torch.utils.data.DataLoader:
        """The ``predict`` split: the test sequences, with or without ground truth."""
        return self._loader("predict", shuffle=False, batch_size=self.eval_batch_size)

    def prepare_data(self) -> None:
        """Fill the flow cache for every split (Lightning calls this on one process per node)."""
        if not self.precompute or isinstance(self.flow, FlowFiles):
            return
        for split in ("train", "val", "test"):
            ds = self.build_dataset(split)
            n = ds.precompute_flow(progress=True)
            if n:
                log.info(
                    "computed and cached the %s flow of %d %s pairs under %s",
                    ds.estimator.name,
                    n,
                    split,
                    ds.cache.root,
                )
            if ds.nonfinite_pixels:
                log.warning(
                    "%d estimated flow pixels of the %s split were not finite: masked invalid",
                    ds.nonfinite_pixels,
                    split,
                )
