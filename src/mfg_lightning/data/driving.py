"""Datasets of camera motions along trajectories: the index of ``(sequence, source, target)``
pairs and their poses (:class:`TrajectoryDataset`), and the samples of ``flow=exact``, each
drawn from a per-frame box scene (:class:`SyntheticDrivingDataset`,
:mod:`mfg_lightning.scene.boxes`)."""

from __future__ import annotations

import dataclasses
import hashlib
import sys
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning.core import geometry
from mfg_lightning.data.base import (
    MotionDataset,
    check_offsets,
)
from mfg_lightning.data.sample_cache import (
    Arrays,
    Codec,
    FieldSpec,
    MemoryBudget,
    SampleStore,
    source_digest,
)
from mfg_lightning.flow.estimators import FlowCache
from mfg_lightning.scene.boxes import SceneConfig, render_sample
from mfg_lightning.scene.camera import kitti_like_intrinsics
from mfg_lightning.scene.seeding import seeded_rng

# Bump when what the sample cache stores per sample, or how it encodes it, changes.
_SAMPLE_CACHE_FORMAT = 1


class TrajectoryDataset(MotionDataset):
    """Samples ``frame → frame + offset`` along given trajectories: the index, the poses.

    Args:
        trajectories: sequence name → ``(N, 4, 4)`` float64 ``T_world_cam`` poses.
        frames: sequence name → ``(first, last)`` range of source frames to use (inclusive).
        height, width: output resolution.
        seed: seed of the scene content.
        offsets: target frame offsets from each source frame (``[1]``: consecutive frames;
            ``[-2, -1, 1, 2]``: the central-frame snippets).
        name: dataset name used in sample ids.
        stride: use the source frames whose index is a multiple of ``stride`` (1: all); counted
            from frame 0 of the sequence, so that a split's frames are those of the union.
    """

    def __init__(
        self,
        trajectories: dict[str, torch.Tensor],
        frames: dict[str, tuple[int, int]],
        height: int,
        width: int,
        seed: int = 0,
        offsets: Sequence[int] = (1,),
        name: str = "synthetic",
        stride: int = 1,
    ) -> None:
        self.height, self.width, self.seed, self.name = height, width, seed, name
        self.trajectories = trajectories
        self.intrinsics = kitti_like_intrinsics(height, width)
        self.offsets = check_offsets(offsets)
        self._poses: dict[tuple[str, int, int], torch.Tensor] = {}  # _pose's, once computed
        self.samples = []
        for seq, (first, last) in frames.items():
            n = trajectories[seq].shape[0]
            for k in range(first + (-first) % stride, last + 1, stride):
                for off in self.offsets:
                    if 0 <= k + off < n:
                        self.samples.append((seq, k, k + off))

    def _pose(self, seq: str, src: int, tgt: int) -> torch.Tensor:
        """The ``(4, 4)`` float64 ``T_src_tgt`` of a sample (callers do not modify it)."""
        # Kept once computed: 50 µs a sample, a quarter of the loader's time once the samples
        # themselves come from the sample cache (python bench/throughput.py --sample-cache).
        # A race between the prefetch thread and the loader computes the same value twice.
        pose = self._poses.get((seq, src, tgt))
        if pose is None:
            traj = self.trajectories[seq]
            pose = self._poses[seq, src, tgt] = geometry.relative_pose(traj[src], traj[tgt])
        return pose

    def relative_poses(self) -> torch.Tensor:
        if not self.samples:
            return torch.zeros(0, 4, 4, dtype=torch.float64)
        return torch.stack([self._pose(s, a, b) for s, a, b in self.samples])

    def _check_index(self, i: int) -> None:
        if not 0 <= i < len(self.samples):
            raise IndexError(f"{self.name}: sample {i} out of range (0 … {len(self.samples) - 1})")

    def _identity(self, seq: str, src: int, tgt: int, pose: torch.Tensor) -> dict:
        """The fields every sample carries besides its images and flow."""
        return {
            "pose": pose.float(),
            "intrinsics": self.intrinsics.float(),
            "sequence": seq,
            "frame": src,
            "target": tgt,
            "sample_id": f"{self.name}/{seq}/{src:06d}->{tgt:06d}",
        }


class SyntheticDrivingDataset(TrajectoryDataset):
    """``flow=exact``: sample ``i`` is generated from ``(seed, sequence, frame)`` on a scene drawn
    for that frame, with the exact flow corrupted by noise and outliers.

    A sample is a pure function of its index and the settings, so it can be computed once: with
    a ``memory`` budget or a ``cache_dir``, the tensors of each sample are kept (in memory while
    the budget has room, and on disk under
    ``<cache_dir>/synthetic_samples/<key>/<seq>@<poses>/<src:06d>_<tgt:06d>.sample``) and read
    back, bit for bit, on later reads; the identity fields (pose, intrinsics, names) are rebuilt
    on every read. ``<key>`` hashes everything that changes a sample (:meth:`cache_key`),
    ``<poses>`` the sequence's poses. Without either, every read generates the sample anew.

    Args:
        noise_std, outlier_fraction: flow corruption (pixels, fraction).
        scene: ranges of the procedural scene.
        memory: the process's sample-cache budget (None: nothing kept in memory).
        cache_dir: the user cache directory (``paths.cache_dir``) of the disk tier (None: no
            disk tier).
        args, kwargs: ``trajectories``, ``frames``, ``height``, ``width``, ``seed``, ``offsets``,
            ``name`` of :class:`TrajectoryDataset`.
    """

    def __init__(
        self,
        *args: Any,
        noise_std: float = 0.3,
        outlier_fraction: float = 0.01,
        scene: SceneConfig | None = None,
        memory: MemoryBudget | None = None,
        cache_dir: str | Path | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.noise_std, self.outlier_fraction = noise_std, outlier_fraction
        self.scene = scene or SceneConfig()
        self.store: SampleStore | None = None
        self._pose_digests: dict[str, str] = {}
        if memory is not None or cache_dir is not None:
            root = None
            if cache_dir is not None:
                key = self.cache_key()
                root = FlowCache.create(cache_dir, key, namespace="synthetic_samples").root
            h, w = self.height, self.width
            self.store = SampleStore(
                _fields(h, w), memory, root, partial(_check_entry, h, w), _SampleCodec(h, w)
            )

    def cache_key(self) -> dict[str, Any]:
        """Everything but the sequence's poses that changes a sample (the poses name each
        sequence's folder, so that datasets sharing a sequence share its entries)."""
        return {
            "format": _SAMPLE_CACHE_FORMAT,
            "sample": "box scene, exact flow",
            "seed": self.seed,
            "height": self.height,
            "width": self.width,
            "noise_std": float(self.noise_std),
            "outlier_fraction": float(self.outlier_fraction),
            "scene": _plain(dataclasses.asdict(self.scene)),
            # this module (the draw of each sample), the scene modules it reaches, the geometry
            # of the flow
            "source": source_digest(sys.modules[__name__], geometry),
            "torch": torch.__version__,
            "numpy": np.__version__,
        }

    def entry_name(self, i: int) -> str:
        """Sample ``i``'s entry below the disk tier's root: ``<seq>@<poses>/<src>_<tgt>.sample``,
        ``<poses>`` a digest of the sequence's float64 poses."""
        seq, src, tgt = self.samples[i]
        if seq not in self._pose_digests:
            poses = np.ascontiguousarray(self.trajectories[seq].double().numpy())
            self._pose_digests[seq] = hashlib.sha256(poses.tobytes()).hexdigest()[:16]
        return f"{seq}@{self._pose_digests[seq]}/{src:06d}_{tgt:06d}.sample"

    def _generate(self, seq: str, src: int, tgt: int, pose: torch.Tensor) -> dict:
        """The tensor fields of ``src → tgt`` of ``seq`` (:func:`render_sample`)."""
        return render_sample(
            pose,
            self.intrinsics,
            self.height,
            self.width,
            seeded_rng(self.seed, seq, src, tgt),
            self.scene,
            self.noise_std,
            self.outlier_fraction,
        )

    def __getitem__(self, i: int) -> dict:
        self._check_index(i)
        seq, src, tgt = self.samples[i]
        pose = self._pose(seq, src, tgt)
        if self.store is None:
            sample = self._generate(seq, src, tgt, pose)
        else:
            kept = self.store.fetch(
                (seq, src, tgt), self.entry_name(i), lambda: self._generate(seq, src, tgt, pose)
            )
            # Copies (in the same memory layout): the kept tensors are never handed out.
            sample = {name: t.clone() for name, t in kept.items()}
        sample.update(self._identity(seq, src, tgt, pose))
        return sample

    def prefetch(self, i: int) -> bool:
        """Compute and keep sample ``i`` ahead of ``__getitem__`` (the
        :class:`~mfg_lightning.data.sample_cache.Prefetcher`'s ``fill``); False when nothing
        more can be kept."""
        if self.store is None:
            return False
        seq, src, tgt = self.samples[i]

        def compute() -> dict[str, torch.Tensor]:
            return self._generate(seq, src, tgt, self._pose(seq, src, tgt))

        return self.store.prefetch((seq, src, tgt), self.entry_name(i), compute)


def _plain(value: Any) -> Any:
    """``value`` with its sequences as lists (tuples, or a config's lists) for the JSON key."""
    if value is None or isinstance(value, str | int | float | bool):
        return value
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    return [_plain(v) for v in value]


# -- the sample cache's encoding of a flow=exact sample ------------------------------------------
#
# Every tensor of the sample, losslessly: the two masks as bits (np.packbits), and the object
# flow, zero off the moving objects (about 1 % of the pixels), as the bit map of its non-zero
# pixels and their vectors; about 94 kB a sample at 48 × 128 instead of 154 kB. The memory
# layout of each (C, H, W) field is kept too: the generator returns some of them channels-last
# (which ones depends on the settings), and a batch stacked from them keeps that layout, which
# can change the rounding of a reduction over it; a cached sample must not.

#: The ``(C, H, W)`` fields whose layout an entry records, in the order of its ``layout`` array.
_CHW_FIELDS = ("flow", "object_flow", "rgb")
#: Their layouts: C-contiguous, or channels-last (strides ``(1, W·C, C)``).
_CONTIGUOUS, _CHANNELS_LAST = 0, 1


def _fields(height: int, width: int) -> FieldSpec:
    """The arrays of an encoded sample at ``height × width``: name → (dtype, shape)."""
    bits = (height * width + 7) // 8
    f32, u8 = np.dtype(np.float32), np.dtype(np.uint8)
    return {
        "flow": (f32, (2, height, width)),
        "flow_valid": (u8, (bits,)),
        "depth": (f32, (height, width)),
        "object_mask": (u8, (bits,)),
        "object_flow_where": (u8, (bits,)),
        "object_flow_values": (f32, (2, None)),
        "rgb": (u8, (3, height, width)),
        "layout": (u8, (len(_CHW_FIELDS),)),
    }


def _check_entry(height: int, width: int, arrays: Arrays) -> str | None:
    """What is wrong with an entry beyond its dtypes and shapes: not as many object-flow
    vectors as pixels in its bit map, or an unknown layout (else None)."""
    n = int(np.unpackbits(arrays["object_flow_where"], count=height * width).sum())
    if arrays["object_flow_values"].shape[1] != n:
        return f"{arrays['object_flow_values'].shape[1]} object-flow vectors for {n} pixels"
    if arrays["layout"].max() > _CHANNELS_LAST:
        return f"unknown layout {arrays['layout'].tolist()}"
    return None


def _layout(name: str, t: torch.Tensor) -> int:
    """The layout code of the ``(C, H, W)`` field ``name``."""
    if t.is_contiguous():
        return _CONTIGUOUS
    if t.permute(1, 2, 0).is_contiguous():
        return _CHANNELS_LAST
    # A new layout from the generator: the cache would hand out another one (bump the format).
    raise ValueError(f"{name}: strides {t.stride()} of {tuple(t.shape)}: no layout code")


def _encode(sample: dict[str, torch.Tensor]) -> Arrays:
    """The tensor fields of a generated sample as the cache stores them (:func:`_fields`)."""
    for name in ("flow_valid", "depth", "object_mask"):
        if not sample[name].is_contiguous():
            raise ValueError(f"{name}: strides {sample[name].stride()}: not contiguous")
    obj = np.ascontiguousarray(sample["object_flow"].numpy())
    # Non-zero bit patterns: a -0.0 vector is stored as it is, so the decoding is bit-exact.
    where = (obj.view(np.uint32) != 0).any(axis=0)
    return {
        "flow": np.ascontiguousarray(sample["flow"].numpy()),
        "flow_valid": np.packbits(sample["flow_valid"].numpy()),
        "depth": np.ascontiguousarray(sample["depth"].numpy()),
        "object_mask": np.packbits(sample["object_mask"].numpy()),
        "object_flow_where": np.packbits(where),
        "object_flow_values": np.ascontiguousarray(obj[:, where]),
        "rgb": np.ascontiguousarray(sample["rgb"].numpy()),
        "layout": np.array([_layout(k, sample[k]) for k in _CHW_FIELDS], dtype=np.uint8),
    }


def _decode(arrays: Arrays, height: int, width: int) -> dict[str, torch.Tensor]:
    """The tensor fields of a sample from its cached arrays: new tensors (the arrays may be the
    memory tier's own), equal bit for bit and in memory layout to the generated ones, in
    :func:`render_sample`'s order: ``flow`` ``(2, H, W)`` float32 pixels, ``flow_valid``
    ``(H, W)`` bool, ``depth`` ``(H, W)`` float32 metres, ``object_mask`` ``(H, W)`` bool,
    ``object_flow`` ``(2, H, W)`` float32 pixels, ``rgb`` ``(3, H, W)`` uint8."""
    n = height * width
    layout = dict(zip(_CHW_FIELDS, arrays["layout"].tolist(), strict=True))

    def mask(name: str) -> torch.Tensor:
        return torch.from_numpy(np.unpackbits(arrays[name], count=n).reshape(height, width) != 0)

    def chw(name: str, values: np.ndarray) -> torch.Tensor:
        """A copy of the ``(C, H, W)`` array ``values`` in the field's layout."""
        if layout[name] == _CONTIGUOUS:
            return torch.from_numpy(values.copy())
        return torch.from_numpy(np.ascontiguousarray(values.transpose(1, 2, 0))).permute(2, 0, 1)

    where = np.unpackbits(arrays["object_flow_where"], count=n).reshape(height, width) != 0
    object_flow = np.zeros((2, height, width), dtype=np.float32)
    object_flow[:, where] = arrays["object_flow_values"]
    return {
        "flow": chw("flow", arrays["flow"]),
        "flow_valid": mask("flow_valid"),
        "depth": torch.from_numpy(arrays["depth"].copy()),
        "object_mask": mask("object_mask"),
        "object_flow": chw("object_flow", object_flow),
        "rgb": chw("rgb", arrays["rgb"]),
    }


class _SampleCodec(Codec[dict[str, torch.Tensor]]):
    """A ``flow=exact`` sample's tensor fields in the memory tier, :func:`_encode`'s arrays on
    disk.

    A later epoch's read is then a copy of each tensor instead of a decoding (its rate: the
    "loader alone, epoch 2" column of bench/results/throughput.md), for 153 kB a sample in
    memory instead of 94 kB."""

    def __init__(self, height: int, width: int) -> None:
        self.height, self.width = height, width

    def encode(self, value: dict[str, torch.Tensor]) -> Arrays:
        return _encode(value)

    def decode(self, arrays: Arrays) -> dict[str, torch.Tensor]:
        return _decode(arrays, self.height, self.width)
