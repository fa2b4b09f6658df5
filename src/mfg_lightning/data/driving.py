"""Datasets of camera motions along trajectories: the index of ``(sequence, source, target)``
pairs and their poses (:class:`TrajectoryDataset`), and the samples of ``flow=exact``, each
drawn from a per-frame box scene (:class:`SyntheticDrivingDataset`,
:mod:`mfg_lightning.scene.boxes`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from mfg_lightning.core import geometry
from mfg_lightning.data.base import (
    MotionDataset,
    check_offsets,
)
from mfg_lightning.scene.boxes import SceneConfig, render_sample
from mfg_lightning.scene.camera import kitti_like_intrinsics
from mfg_lightning.scene.seeding import seeded_rng


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
        self.samples = []
        for seq, (first, last) in frames.items():
            n = trajectories[seq].shape[0]
            for k in range(first + (-first) % stride, last + 1, stride):
                for off in self.offsets:
                    if 0 <= k + off < n:
                        self.samples.append((seq, k, k + off))

    def _pose(self, seq: str, src: int, tgt: int) -> torch.Tensor:
        traj = self.trajectories[seq]
        return geometry.relative_pose(traj[src], traj[tgt])

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

    Args:
        noise_std, outlier_fraction: flow corruption (pixels, fraction).
        scene: ranges of the procedural scene.
        args, kwargs: ``trajectories``, ``frames``, ``height``, ``width``, ``seed``, ``offsets``,
            ``name`` of :class:`TrajectoryDataset`.
    """

    def __init__(
        self,
        *args: Any,
        noise_std: float = 0.3,
        outlier_fraction: float = 0.01,
        scene: SceneConfig | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.noise_std, self.outlier_fraction = noise_std, outlier_fraction
        self.scene = scene or SceneConfig()

    def __getitem__(self, i: int) -> dict:
        self._check_index(i)
        seq, src, tgt = self.samples[i]
        pose = self._pose(seq, src, tgt)
        rng = seeded_rng(self.seed, seq, src, tgt)
        sample = render_sample(
            pose,
            self.intrinsics,
            self.height,
            self.width,
            rng,
            self.scene,
            self.noise_std,
            self.outlier_fraction,
        )
        sample.update(self._identity(seq, src, tgt, pose))
        return sample
