"""Image pairs with MFG's targets (``dataset=image_pairs``): what the flow network and MFG train
on together (``experiment=end_to_end``, :mod:`mfg_lightning.models.end_to_end`).

The worlds, trajectories and splits of ``dataset=synthetic flow=dis``
(:class:`~mfg_lightning.data.synthetic.SyntheticDataModule`, whose :meth:`split_spec` picks
them) rendered as the learned flow's training pairs are
(:class:`~mfg_lightning.data.flow_pairs.FlowPairsDataset`: two frames and the exact flow at the
render size, cached under ``paths.cache_dir/flow_pairs``, the same files as ``train_flow``'s
pairs of the same worlds). Unlike those, every split is here (train, the validation tails, the
test trajectories), and each pair is also an MFG sample at the model input: its pose,
intrinsics and the exact flow resized to the model input as every rendered dataset resizes it
(:func:`~mfg_lightning.data.transforms.resize_flow`). No data to download.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from mfg_lightning.data import sample as keys
from mfg_lightning.data import transforms
from mfg_lightning.data.base import MFGDataModule
from mfg_lightning.data.flow_pairs import FlowPairsDataset, render_pairs
from mfg_lightning.data.sample_cache import MemoryBudget
from mfg_lightning.scene.camera import kitti_like_intrinsics

__all__ = [
    "IMAGE0",
    "IMAGE1",
    "IMAGE_FLOW",
    "REGION",
    "VISIBILITY",
    "ImagePairsDataModule",
    "ImagePairsDataset",
]

#: The source frame at the render size, ``(3, H, W)`` uint8 RGB.
IMAGE0 = "image0"
#: The target frame at the render size, ``(3, H, W)`` uint8 RGB.
IMAGE1 = "image1"
#: The exact flow at the render size, ``(2, H, W)`` float32 pixels of the image, NaN where
#: unknown (``image0(x) ≈ image1(x + flow(x))``).
IMAGE_FLOW = "image_flow"
#: The renderer's region code of every pixel of the source frame, ``(H, W)`` uint8.
REGION = "region"
#: The visibility code of every pixel of the source frame in the target frame, ``(H, W)`` uint8
#: (:func:`~mfg_lightning.metrics.flow_quality.visibility_codes`).
VISIBILITY = "visibility"


class ImagePairsDataset(FlowPairsDataset):
    """A :class:`FlowPairsDataset` pair that is also an MFG sample.

    A sample: the keys of :mod:`mfg_lightning.data.sample` at the model input ``model_hw``
    (``flow``: the exact flow resized to it, 0 where unknown, ``flow_valid``; ``pose``;
    ``intrinsics`` of the model input; ``sequence``, ``frame``, ``target``, ``sample_id``), and at
    the render size ``image_hw``: :data:`IMAGE0`, :data:`IMAGE1`, :data:`IMAGE_FLOW`,
    :data:`REGION`, :data:`VISIBILITY` (where the pairs carry it); ``offset`` (target − source
    frame).

    Args:
        trajectories, frames: as :class:`~mfg_lightning.data.driving.TrajectoryDataset`.
        model_hw: the model input ``(height, width)``, pixels (the parent's ``height`` and
            ``width`` are the render size).
        image_hw: the render size (at least the model input; multiples of 32, the flow
            network's coarsest stride).
        memory: the process's sample-cache budget: pairs read are kept in memory while it has
            room (None: none kept).
        kwargs: ``world``, ``cache_dir``, ``seed``, ``offsets``, ``name``, ``stride`` of
            :class:`FlowPairsDataset`.
    """

    def __init__(
        self,
        trajectories: dict[str, torch.Tensor],
        frames: dict[str, tuple[int, int]],
        model_hw: tuple[int, int],
        image_hw: Sequence[int] = (192, 512),
        memory: MemoryBudget | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(trajectories, frames, image_hw=image_hw, memory=memory, **kwargs)
        self.model_hw = (int(model_hw[0]), int(model_hw[1]))
        if self.model_hw[0] > self.image_hw[0] or self.model_hw[1] > self.image_hw[1]:
            raise ValueError(
                f"dataset.image_hw {list(self.image_hw)} is smaller than the model input "
                f"{self.model_hw[0]} × {self.model_hw[1]}"
            )
        self.model_intrinsics = kitti_like_intrinsics(*self.model_hw).float()

    def __getitem__(self, i: int) -> dict[str, Any]:
        pair = super().__getitem__(i)
        seq, src, tgt = self.samples[i]
        full = pair["flow"]
        known = torch.isfinite(full).all(dim=0)
        # the model input's flow as every rendered dataset makes it (area mean of the known
        # vectors, rescaled): the exact twin's input, and what the batch checks read
        small, valid = transforms.resize_flow(
            full.permute(1, 2, 0).numpy(), known.numpy(), *self.model_hw
        )
        sample = self._identity(seq, src, tgt, self._pose(seq, src, tgt))
        sample.update({
            keys.FLOW: transforms.flow_to_tensor(small),
            keys.FLOW_VALID: torch.from_numpy(valid),
            keys.INTRINSICS: self.model_intrinsics,
            IMAGE0: pair["image0"],
            IMAGE1: pair["image1"],
            IMAGE_FLOW: full,
            REGION: pair["region"],
            "offset": pair["offset"],
        })  # fmt: skip
        if VISIBILITY in pair:  # (KITTI's noc pixels: the pairs' visibility codes)
            sample[VISIBILITY] = pair[VISIBILITY]
        return sample


class ImagePairsDataModule(MFGDataModule):
    """``dataset=image_pairs``: rendered image pairs with MFG's targets and the exact flow.

    Args:
        height, width: the model input (MFG's), pixels.
        image_hw: the render size, ``[height, width]`` multiples of 32 (None: four times the
            model input, where the flow network's quarter-size output is the model input:
            192 × 512 for 48 × 128).
        trajectory, poses_dir, train_sequences, test_sequences, sequence_length, max_frames,
            val_fraction, world, scene_seed, offsets, frame_stride: the worlds and splits, as
            ``dataset=synthetic``'s (:class:`~mfg_lightning.data.synthetic.SyntheticDataModule`;
            validation and test read every frame).
        cache_dir: ``paths.cache_dir``.
        prepare_workers: processes rendering the pairs in :meth:`prepare_data` (None: every
            usable core; 0 or 1: this one).
        memory_mb: the pairs kept in memory, training and validation together, MB (about
            1.1 MB a pair at 192 × 512); 0: every read from the disk cache.
        kwargs: :class:`MFGDataModule`'s (``batch_size``, ``eval_batch_size``, ``num_workers``,
            ``seed``, …).
    """

    def __init__(
        self,
        height: int = 48,
        width: int = 128,
        image_hw: Sequence[int] | None = None,
        trajectory: str = "procedural",
        poses_dir: str | None = None,
        train_sequences: int | Sequence[str] = 8,
        test_sequences: int | Sequence[str] = 2,
        sequence_length: int = 400,
        max_frames: int | None = None,
        val_fraction: float = 0.05,
        world: dict[str, Any] | None = None,
        scene_seed: int | None = None,
        offsets: Sequence[int] = (1,),
        frame_stride: int = 1,
        cache_dir: str | Path | None = None,
        prepare_workers: int | None = None,
        memory_mb: float = 1024,
        **kwargs: Any,
    ) -> None:
        super().__init__(height=height, width=width, **kwargs)
        from mfg_lightning.data.synthetic import SyntheticDataModule

        hw = (4 * height, 4 * width) if image_hw is None else tuple(int(v) for v in image_hw)
        if len(hw) != 2 or min(hw) < 32 or hw[0] % 32 or hw[1] % 32:
            raise ValueError(
                f"dataset.image_hw must be [height, width], multiples of 32, got {list(hw)}"
            )
        self.image_hw = hw
        # the splits and worlds of dataset=synthetic flow=dis (its estimator is never run)
        self.splits = SyntheticDataModule(
            height=height, width=width, trajectory=trajectory, poses_dir=poses_dir,
            train_sequences=train_sequences, test_sequences=test_sequences,
            sequence_length=sequence_length, max_frames=max_frames, val_fraction=val_fraction,
            flow={"source": "dis", "height": hw[0], "width": hw[1]}, offsets=offsets,
            frame_stride=frame_stride, world=world, scene_seed=scene_seed, seed=self.seed,
        )  # fmt: skip
        self.world = dict(world or {})
        self.cache_dir = cache_dir
        self.prepare_workers = prepare_workers
        self._memory = MemoryBudget(float(memory_mb)) if memory_mb and memory_mb > 0 else None

    def build_dataset(self, split: str) -> ImagePairsDataset:
        trajs, frames, common = self.splits.split_spec(split)
        # test pairs are read once a run: memory would hold them for nothing
        memory = self._memory if split in ("train", "val") else None
        return ImagePairsDataset(
            trajs, frames, (self.height, self.width), image_hw=self.image_hw, world=self.world,
            cache_dir=self.cache_dir, memory=memory,
            **{**common, "name": f"image_pairs/{split}"},
        )  # fmt: skip

    def prepare_data(self) -> None:
        """Render every missing pair of every split into the cache, on every core."""
        render_pairs([self.build_dataset(split) for split in ("train", "val", "test")],
                     self.prepare_workers)  # fmt: skip
