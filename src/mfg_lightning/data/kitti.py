"""KITTI odometry as a Lightning DataModule, with optical flow from OpenCV's DIS (cached on
disk) or the user's own files: the ``flow`` config group (``flow=dis``, the default, or
``flow=files``).

Layout read (``../shared/docs/formats.md``; ``data_root`` is the unpacked download, never
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
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from tqdm.auto import tqdm

from mfg_lightning.core import geometry
from mfg_lightning.core.data_errors import DataFileError, DataRootError
from mfg_lightning.data import transforms
from mfg_lightning.data.base import (
    FileMotionDataset,
    MFGDataModule,
    check_data_root,
    check_offsets,
    check_split,
    list_numbered,
    normalize_sequence,
    read_text_lines,
    some_of,
    split_sequences,
)
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.flow import io as flow_io
from mfg_lightning.flow.cache import default_cache_dir
from mfg_lightning.flow.estimators import (
    DIS_PRESETS,
    DISFlowEstimator,
    EstimatedFlow,
    FlowCache,
    FlowFiles,
    FlowSource,
    parse_flow,
)
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
    "read_kitti_poses",
    "write_kitti_calib",
]

TRAIN_SEQUENCES = ("00", "01", "02", "03", "04", "05", "06", "07", "08")
TEST_SEQUENCES = ("09", "10")
FLOW_EXTENSIONS = ("flo", "png", "npy", "npz")

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

# Bump when the cached array layout changes, so old caches are not misread.
_CACHE_FORMAT = 1


def kitti_flow_source(flow: FlowSource | dict[str, Any] | None) -> EstimatedFlow | FlowFiles:
    """The ``flow`` config of ``dataset=kitti`` parsed (default DIS ``medium``); ``flow=exact``
    and ``flow=ground_truth`` are refused: real images have no exact flow, and KITTI odometry
    ships no flow."""
    source = parse_flow(flow, default="dis")
    if not isinstance(source, (EstimatedFlow, FlowFiles)):
        missing = "exact flow (it needs a synthetic scene)"
        if source.source == "ground_truth":
            missing = "ground-truth flow (KITTI odometry ships none)"
        raise ValueError(
            f"flow.source={source.source}: dataset=kitti has no {missing}; use flow=dis (the "
            "default for KITTI) or flow=files flow.dir=<your flow>"
        )
    return source


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def read_kitti_calib(path: str | os.PathLike) -> np.ndarray:
    """``(fx, fy, cx, cy)`` of the left colour camera (``P2``) from a KITTI ``calib.txt``.

    Returns:
        ``(4,)`` float64 in pixels of the native image.
    """
    for number, line in enumerate(read_text_lines(path), start=1):
        key, _, rest = line.partition(":")
        if key.strip() == "P2":
            where = f"{path}: line {number}: P2"
            try:
                P = np.array([float(x) for x in rest.split()], np.float64)
            except ValueError:
                raise DataFileError(f"{where} has a non-numeric entry") from None
            if P.size != 12:
                raise DataFileError(f"{where} has {P.size} numbers, expected 12")
            if not np.isfinite(P).all():
                raise DataFileError(f"{where} has a non-finite entry")
            P = P.reshape(3, 4)
            return np.array([P[0, 0], P[1, 1], P[0, 2], P[1, 2]])
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


def read_kitti_poses(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI pose file (``poses/XX.txt``) with :mod:`mfg_lightning.trajectory.pose_io`.

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


@dataclass
class _Sequence:
    name: str
    image_dir: Path
    intrinsics: np.ndarray  # (4,) native pixels
    native_hw: tuple[int, int]
    poses: np.ndarray | None  # (N, 4, 4) T_world_cam; None: a sequence without ground truth
    n_frames: int  # frames 0 … n_frames − 1 (those with a pose, when there are poses)


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


class KittiOdometryDataset(FileMotionDataset):
    """Samples ``t → t + o`` of KITTI odometry sequences (see the module docstring).

    Args:
        data_root: the KITTI odometry root (holding ``sequences/`` and ``poses/``).
        sequences: sequence names (``"00"`` … ``"10"``).
        offsets: target offsets, ``target = frame + offset`` (non-zero integers).
        val_fraction: fraction of each sequence held out as its validation tail.
        flow: the flow source, a ``conf/flow`` config or its parsed form
            (:func:`~mfg_lightning.flow.estimators.parse_flow`): ``{"source": "dis",
            "preset": …, "params": …, "height": …, "width": …}`` (the default: DIS ``medium``
            at the native size; ``height × width`` is the size the images are resized to before
            estimation) or ``{"source": "files", "dir": <flow_dir>}`` (user-supplied flow,
            ``<flow_dir>/<seq>/<src:06d>_<tgt:06d>.<ext>``).
        cache_dir: the user cache dir (``paths.cache_dir``); flow is cached under ``kitti_flow/``.
        load_rgb: deliver the source image as ``rgb`` (decoded once, then read from the cache).
        require_poses: False: a sequence without ``poses/XX.txt`` is read without ground truth
            (its samples have no ``pose``; :meth:`relative_poses` refuses).
        kwargs: ``height``, ``width`` (the input size flow, RGB and intrinsics are delivered
            at), ``split``, ``portion`` (``"all"`` frames of each sequence, or its ``"train"``
            head / ``"val"`` tail with ``val_fraction``) and ``skip_bad_samples`` of
            :class:`~mfg_lightning.data.base.FileMotionDataset`.
    """

    name = "kitti"
    title = "KITTI"

    def __init__(
        self,
        data_root: str | os.PathLike,
        sequences: Sequence[str],
        offsets: Sequence[int] = (1,),
        val_fraction: float = 0.05,
        flow: FlowSource | dict[str, Any] | None = None,
        cache_dir: str | os.PathLike | None = None,
        load_rgb: bool = True,
        require_poses: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.require_poses = bool(require_poses)
        source = kitti_flow_source(flow)
        offsets = check_offsets(offsets)
        self.sequence_names = [normalize_sequence(s) for s in sequences]
        self.root = self._check_root(data_root)
        self.offsets = offsets
        self.load_rgb = load_rgb
        self.flow_dir = Path(source.dir).expanduser() if isinstance(source, FlowFiles) else None
        self.compute_hw: tuple[int, int] | None = None
        self.estimator: Any = None
        # pixels of estimated flow that were not finite (masked), at the estimation size
        self.nonfinite_pixels = 0
        if isinstance(source, EstimatedFlow):
            self.estimator = source.estimator
            if source.height is not None and source.width is not None:
                self.compute_hw = (int(source.height), int(source.width))
        if self.flow_dir is None:
            flow_key: dict[str, Any] = {
                **self.estimator.key(),
                "compute_hw": list(self.compute_hw) if self.compute_hw else "native",
            }
        else:
            flow_key = {"flow_dir": str(self.flow_dir.resolve())}  # only RGB is cached then
        key = {
            **flow_key,
            "output_hw": [self.height, self.width],
            "data_root": str(self.root),
            "format": _CACHE_FORMAT,
            **self._layout_key(),
        }
        self.cache = FlowCache.create(cache_dir or default_cache_dir(), key)
        if self.flow_dir is not None and not self.flow_dir.is_dir():
            raise DataRootError(
                f"flow.dir={self.flow_dir} is not a directory; expected "
                "<flow_dir>/<seq>/<src:06d>_<tgt:06d>.<flo|png|npy|npz>"
            )

        self._sequences: dict[str, _Sequence] = {}
        problems: list[str] = []
        span = max(abs(o) for o in offsets)
        for seq in self.sequence_names:
            info, frames, seq_problems = self._load_sequence(seq)
            problems += seq_problems
            self._sequences[seq] = info
            allowed = self.portion_frames(info.n_frames, val_fraction, span)
            present = set(frames)
            for src in allowed:
                for o in offsets:
                    tgt = src + o
                    if tgt in allowed and src in present and tgt in present:
                        self.samples.append((seq, src, tgt))
        self._flow_paths: dict[tuple[str, int, int], Path] = {}
        if self.flow_dir is not None:
            problems += self._index_flow_files()
        self.report_problems(problems)

    # -- index -------------------------------------------------------------------------------

    def _check_root(self, data_root: str | os.PathLike | None) -> Path:
        """The resolved ``data_root`` after checking the layout (a hook for other layouts)."""
        return check_kitti_root(data_root, self.sequence_names, poses=self.require_poses)

    def _layout_key(self) -> dict[str, Any]:
        """What else decides which file a frame number means (for the cache key): nothing
        here, the KITTI names are fixed."""
        return {}

    def _load_sequence(self, seq: str) -> tuple[_Sequence, list[int], list[str]]:
        seq_dir = self.root / "sequences" / seq
        image_dir = seq_dir / "image_2"
        pose_file = self.root / "poses" / f"{seq}.txt"
        intrinsics = read_kitti_calib(seq_dir / "calib.txt")
        frames = list_numbered(image_dir)
        if not frames:
            raise DataFileError(f"{image_dir}: no frames (expected 000000.png, 000001.png, …)")
        native_hw = flow_io.image_size(image_dir / f"{frames[0]:06d}.png")
        if not self.require_poses and not pose_file.exists():
            info = _Sequence(seq, image_dir, intrinsics, native_hw, None, frames[-1] + 1)
            return info, frames, []
        poses = read_kitti_poses(pose_file)
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
        info = _Sequence(seq, image_dir, intrinsics, native_hw, poses, len(poses))
        return info, frames, problems

    def _index_flow_files(self) -> list[str]:
        assert self.flow_dir is not None
        listing: dict[str, dict[str, Path]] = {}
        for seq in self.sequence_names:
            d = self.flow_dir / seq
            entries: dict[str, Path] = {}
            if d.is_dir():
                for p in d.iterdir():
                    if p.suffix.lower().lstrip(".") in FLOW_EXTENSIONS:
                        entries.setdefault(p.stem, p)
            listing[seq] = entries
        kept, missing = [], []
        for seq, src, tgt in self.samples:
            p = listing[seq].get(f"{src:06d}_{tgt:06d}")
            if p is None:
                missing.append(self.flow_dir / seq / f"{src:06d}_{tgt:06d}.<flo|png|npy|npz>")
            else:
                self._flow_paths[(seq, src, tgt)] = p
                kept.append((seq, src, tgt))
        self.samples = kept
        if not missing:
            return []
        return [
            f"flow.dir: {len(missing)} flow file(s) missing for the {self.split} split "
            f"(naming: <flow_dir>/<seq>/<src:06d>_<tgt:06d>.<ext>):\n{some_of(missing, 10)}"
        ]

    # -- MotionDataset -----------------------------------------------------------------------

    def relative_poses(self) -> torch.Tensor:
        """``(N, 4, 4)`` float32 ``T_src,tgt`` of every sample, from the pose files only."""
        if not self.samples:
            return torch.zeros(0, 4, 4)
        self._check_poses()
        src = np.stack([self._sequences[s].poses[a] for s, a, _ in self.samples])
        tgt = np.stack([self._sequences[s].poses[b] for s, _, b in self.samples])
        rel = geometry.relative_pose(torch.from_numpy(src), torch.from_numpy(tgt))
        return rel.float()

    def has_poses(self) -> bool:
        """Whether every sequence has ground-truth poses."""
        return all(info.poses is not None for info in self._sequences.values())

    def _check_poses(self) -> None:
        without = sorted(seq for seq, info in self._sequences.items() if info.poses is None)
        if without:
            raise DataRootError(
                f"the {self.split} split has no ground-truth poses for sequence(s) "
                f"{', '.join(without)} (no {self.root / 'poses'}/<seq>.txt); training and "
                "evaluation need them"
            )

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

    def intrinsics(self, seq: str) -> torch.Tensor:
        """``(4,)`` ``(fx, fy, cx, cy)`` of ``seq`` at the input size."""
        info = self._sequences[seq]
        return transforms.resize_intrinsics(
            info.intrinsics, info.native_hw, (self.height, self.width)
        )

    def files(self, index: int) -> list[Path]:
        """The files sample ``index`` reads (for checks): both images, and its flow file."""
        seq, src, tgt = self.samples[index]
        out = [self.image_path(seq, src), self.image_path(seq, tgt)]
        if self.flow_dir is not None:
            out.append(self._flow_paths[(seq, src, tgt)])
        return out

    def describe(self) -> dict[str, dict[str, Any]]:
        """Per sequence: frames, native image size, intrinsics (native and at the input size)."""
        return {
            seq: {
                "frames": info.n_frames,
                "native_size": list(info.native_hw),
                "intrinsics_native": [round(float(v), 4) for v in info.intrinsics],
                "intrinsics_input": [round(float(v), 4) for v in self.intrinsics(seq)],
            }
            for seq, info in self._sequences.items()
        }

    def image_path(self, seq: str, frame: int) -> Path:
        return self._sequences[seq].image_dir / f"{frame:06d}.png"

    def _load(self, index: int) -> dict[str, Any]:
        seq, src, tgt = self.samples[index]
        info = self._sequences[seq]
        flow, valid = self.flow(index)
        flow_t, valid_t, _ = sanitize_flow(
            transforms.flow_to_tensor(flow), torch.from_numpy(np.ascontiguousarray(valid))
        )
        sample: dict[str, Any] = {
            "flow": flow_t,
            "flow_valid": valid_t,
            "intrinsics": self.intrinsics(seq),
            **self.sample_identity(index),
        }
        if info.poses is not None:
            sample["pose"] = geometry.relative_pose(
                torch.from_numpy(info.poses[src]), torch.from_numpy(info.poses[tgt])
            ).float()
        if self.load_rgb:
            rgb = self.cache.load(
                self.cache.rgb_path(seq, src), (self.height, self.width, 3), np.uint8
            )
            if rgb is None:
                rgb = self._decode(seq, src)[0]
            sample["rgb"] = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))
        return sample

    # -- flow --------------------------------------------------------------------------------

    def _compute_hw(self, seq: str) -> tuple[int, int]:
        return self.compute_hw or self._sequences[seq].native_hw

    def cache_path(self, index: int) -> Path | None:
        """Where the computed flow of sample ``index`` is cached (None with ``flow_dir``)."""
        if self.flow_dir is not None:
            return None
        seq, src, tgt = self.samples[index]
        return self.cache.path(seq, self._compute_hw(seq), src, tgt)

    def flow(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Flow of sample ``index`` at the input size: ``(h, w, 2)`` float32, ``(h, w)`` bool.

        From ``flow_dir`` if set, else from the cache, computing (and caching) it on a miss.
        """
        seq, src, tgt = self.samples[index]
        hw = (self.height, self.width)
        if self.flow_dir is not None:
            flow, valid = flow_io.read_flow(self._flow_paths[(seq, src, tgt)], png_format="kitti")
            return transforms.resize_flow(flow, valid, *hw)
        path = self.cache.path(seq, self._compute_hw(seq), src, tgt)
        flow = self.cache.load(path, (*hw, 2), np.float32)
        if flow is None:
            flow = self._estimate(
                seq, src, tgt, self._decode(seq, src)[1], self._decode(seq, tgt)[1]
            )
            self.cache.store(path, flow)
        return flow, np.isfinite(flow).all(axis=2)

    def _decode(self, seq: str, frame: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Decode one frame: ``(rgb, image)``, the ``(h, w, 3)`` uint8 image at the input size
        (also cached, with ``load_rgb``) and the estimator's input (DIS: the uint8 grey image) at
        the flow computation size (None with ``flow=files``)."""
        rgb = flow_io.read_rgb(self.image_path(seq, frame))
        small = transforms.resize_rgb(rgb, self.height, self.width)
        if self.load_rgb:
            path = self.cache.rgb_path(seq, frame)
            if not path.exists():
                self.cache.store(path, small)
        if self.estimator is None:  # flow=files: the image is for the pictures only
            return small, None
        image = self.estimator.prepare(rgb)
        hw = self._compute_hw(seq)
        if image.shape[:2] != hw:
            image = cv2.resize(image, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
        return small, image

    def _estimate(
        self, seq: str, src: int, tgt: int, gray0: np.ndarray, gray1: np.ndarray
    ) -> np.ndarray:
        """The estimator's flow resized to the input size, ``(h, w, 2)`` float32; pixels where it
        was not finite are NaN (masked when read, and counted in ``nonfinite_pixels``)."""
        flow = self.estimator(gray0, gray1)
        finite = np.isfinite(flow).all(axis=2)
        if finite.all():
            resized, _ = transforms.resize_flow(flow, finite, self.height, self.width)
            return resized
        self.nonfinite_pixels += int((~finite).sum())
        resized, valid = transforms.resize_flow(
            np.where(finite[..., None], flow, 0.0).astype(np.float32),
            finite,
            self.height,
            self.width,
        )
        return np.where(valid[..., None], resized, np.nan).astype(np.float32)

    def missing_flow(self) -> list[int]:
        """Indices of the samples whose computed flow is not cached yet (stat calls only)."""
        if self.flow_dir is not None:
            return []
        return [i for i in range(len(self.samples)) if not self.cache_path(i).exists()]

    def precompute_flow(self, progress: bool = True) -> int:
        """Compute and cache the flow of every sample not cached yet; return how many.

        Pairs are processed in sequence and frame order so each image is decoded once even when
        it is the target of one pair and the source of the next (or of backward pairs).
        """
        todo = self.missing_flow()
        if not todo:
            return 0
        span = max(abs(o) for o in self.offsets)
        images: dict[tuple[str, int], np.ndarray] = {}
        done = 0
        bar = tqdm(
            total=len(todo),
            desc=f"{self.estimator.name} flow ({self.split})",
            unit="pair",
            disable=not progress,
        )
        try:
            for i in sorted(todo, key=lambda k: self.samples[k][:2]):
                seq, src, tgt = self.samples[i]
                # Keep only the images that later pairs of this sequence can still use.
                for key in [k for k in images if k[0] != seq or k[1] < src - span]:
                    del images[key]
                try:
                    for f in (src, tgt):
                        if (seq, f) not in images:
                            images[(seq, f)] = self._decode(seq, f)[1]
                except DataFileError as err:
                    self.bad_sample(i, err, "cannot compute flow for")
                    bar.update(1)
                    continue
                flow = self._estimate(seq, src, tgt, images[(seq, src)], images[(seq, tgt)])
                self.cache.store(self.cache_path(i), flow)
                done += 1
                bar.update(1)
        finally:
            bar.close()
        return done


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
        self.flow = kitti_flow_source(flow)
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
