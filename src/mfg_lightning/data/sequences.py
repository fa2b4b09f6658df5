"""The engine shared by the datasets of real image sequences (KITTI odometry, a folder of
images): samples ``t → t + o`` of numbered frames, with optical flow from OpenCV's DIS (cached
on disk) or the user's own files, and ground-truth poses where the layout has them.

A dataset of image sequences is its layout only: an :class:`ImageSequenceDataset` subclass that
checks its root (:meth:`~ImageSequenceDataset._check_root`), reads one sequence into an
:class:`ImageSequence` (:meth:`~ImageSequenceDataset._load_sequence`) and names the file of a
frame (:meth:`~ImageSequenceDataset.image_path`); everything else (the sample index, flow, its
cache, the RGB cache, poses and intrinsics at the input size) is here.

Samples: for every source frame ``t`` and offset ``o`` in ``offsets`` whose target ``t + o``
exists, one sample ``t → t + o`` (sorted by sequence, source frame, then the order of
``offsets``), restricted to the frames of the ``portion`` (training head or validation tail).

Flow, one of:

* **computed** (``flow=dis``, the default): OpenCV's DIS (``cv2.DISOpticalFlow``) on the grey
  images at ``flow.height × flow.width`` (null: the native size), resized to the model's input
  size and cached as ``.npy`` under
  ``<cache_dir>/kitti_flow/<key>/<seq>@<H>x<W>/<src:06d>_<tgt:06d>.npy``
  where ``<key>`` hashes everything that changes the result (estimator, preset and parameters,
  OpenCV version, the output size, the resolved ``data_root``, what else of the layout decides
  which file a frame is) and ``<H>x<W>`` is the size the flow was computed at.
  :meth:`ImageSequenceDataset.precompute_flow` fills the cache; later reads only load it.
  Writes are atomic (temporary file then ``os.replace``), so concurrent readers and writers are
  safe. The source image at the input size is cached beside it (``<seq>_rgb/<frame:06d>.npy``),
  so a cached epoch decodes no image.
* **user-supplied** (``flow=files flow.dir=<flow_dir>``): precomputed files named
  ``<flow_dir>/<seq>/<src:06d>_<tgt:06d>.<ext>``, one per sample (source → target, any offset),
  ``ext`` one of :data:`FLOW_EXTENSIONS`. The flow may be at any resolution covering the whole
  image; it is resized and its values rescaled. A missing file is an error listing the expected
  names.

Poses: ``sample['pose'] = T_world_cam(src)^-1 · T_world_cam(tgt)`` (camera at the target in the
camera at the source), from :func:`mfg_lightning.core.geometry.relative_pose`, for sequences with
poses; intrinsics are scaled from the native image size to the input size.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
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
from mfg_lightning.data.base import check_offsets, normalize_sequence
from mfg_lightning.data.file_datasets import FileMotionDataset, some_of
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.flow import io as flow_io
from mfg_lightning.flow.cache import default_cache_dir
from mfg_lightning.flow.estimators import (
    EstimatedFlow,
    FlowCache,
    FlowFiles,
    FlowSource,
    parse_flow,
)

__all__ = [
    "FLOW_EXTENSIONS",
    "ImageSequence",
    "ImageSequenceDataset",
    "image_flow_source",
]

#: The extensions of user-supplied flow files (``flow=files``).
FLOW_EXTENSIONS = ("flo", "png", "npy", "npz")

# Bump when the cached array layout changes, so old caches are not misread.
_CACHE_FORMAT = 1


def image_flow_source(flow: FlowSource | dict[str, Any] | None) -> EstimatedFlow | FlowFiles:
    """The ``flow`` config of a dataset of real images parsed (default DIS ``medium``);
    ``flow=exact`` and ``flow=ground_truth`` are refused: real images have no exact flow, and
    KITTI odometry ships no flow.

    The message names ``dataset=kitti``, the dataset whose flow rules every image sequence
    follows (a folder of images too)."""
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


@dataclass
class ImageSequence:
    """One sequence of numbered frames, as a layout reads it.

    Attributes:
        name: the sequence name in samples and outputs (``"09"``).
        image_dir: the directory of its frames.
        intrinsics: ``(4,)`` float64 ``(fx, fy, cx, cy)`` in pixels of the native image size.
        native_hw: ``(height, width)`` of the files, pixels.
        poses: ``(N, 4, 4)`` float64 ``T_world_cam`` (camera-to-world, metres); None: a sequence
            without ground truth.
        n_frames: frames 0 … n_frames − 1 (those with a pose, when there are poses).
    """

    name: str
    image_dir: Path
    intrinsics: np.ndarray
    native_hw: tuple[int, int]
    poses: np.ndarray | None
    n_frames: int


class ImageSequenceDataset(FileMotionDataset):
    """Samples ``t → t + o`` of sequences of images, with estimated or user-supplied flow (see
    the module docstring); subclasses give the layout.

    Subclasses implement :meth:`_check_root`, :meth:`_load_sequence` and :meth:`image_path`,
    and may override :meth:`_layout_key` (what else names a frame's file, for the cache key),
    :meth:`timestamps` and :meth:`_missing_poses_note`.

    Args:
        data_root: the dataset's root, checked by :meth:`_check_root`.
        sequences: sequence names.
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
        require_poses: False: a sequence without poses is read without ground truth (its samples
            have no ``pose``; :meth:`relative_poses` refuses).
        kwargs: ``height``, ``width`` (the input size flow, RGB and intrinsics are delivered
            at), ``split``, ``portion`` (``"all"`` frames of each sequence, or its ``"train"``
            head / ``"val"`` tail with ``val_fraction``) and ``skip_bad_samples`` of
            :class:`~mfg_lightning.data.file_datasets.FileMotionDataset`.
    """

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
        source = image_flow_source(flow)
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

        self._sequences: dict[str, ImageSequence] = {}
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

    # -- the layout (subclasses) -------------------------------------------------------------

    def _check_root(self, data_root: str | os.PathLike | None) -> Path:
        """The resolved ``data_root`` after checking the layout (raise
        :class:`~mfg_lightning.core.data_errors.DataRootError` naming what is missing)."""
        raise NotImplementedError

    def _layout_key(self) -> dict[str, Any]:
        """What else decides which file a frame number means (for the cache key): nothing
        by default, the names are fixed."""
        return {}

    def _load_sequence(self, seq: str) -> tuple[ImageSequence, list[int], list[str]]:
        """Read sequence ``seq``: its record, the frame numbers present (sorted) and problems
        to report (:meth:`~mfg_lightning.data.file_datasets.FileMotionDataset.report_problems`)."""
        raise NotImplementedError

    def image_path(self, seq: str, frame: int) -> Path:
        """The image file of frame ``frame`` of ``seq``."""
        raise NotImplementedError

    def timestamps(self, seq: str) -> np.ndarray | None:
        """``(n_frames,)`` seconds of frames 0 … n_frames − 1, or None when the layout has no
        clock (the default)."""
        return None

    def _missing_poses_note(self) -> str:
        """Where the layout's poses would be, for the error when a sequence has none."""
        return f"no ground-truth poses under {self.root}"

    # -- index -------------------------------------------------------------------------------

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
                f"{', '.join(without)} ({self._missing_poses_note()}); training and "
                "evaluation need them"
            )

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
