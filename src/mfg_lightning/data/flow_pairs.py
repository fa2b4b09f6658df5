"""Training pairs for the learned flow (``python -m mfg_lightning.train_flow``): two rendered
frames of a persistent world and the exact flow between them, at the render size.

The pairs come from the same persistent worlds, trajectories and splits as ``dataset=synthetic
flow=dis`` (:class:`~mfg_lightning.data.synthetic.SyntheticDataModule`): the training pairs from
the training trajectories without their validation tails, the validation pairs from those
tails; the test trajectories are never read (the flow is measured on them afterwards,
``bench/flow_estimators.py``). With ``trajectory=kitti`` and KITTI's sequences 00–08 these are
the study's MFG training worlds.

Cache: ``<cache_dir>/flow_pairs/<key>/<seq>/<src:06d>_<tgt:06d>.npz`` holding ``images``
``(H, W, 6)`` uint8 (both RGB frames), ``flow`` ``(H, W, 2)`` float16 (input pixels, NaN where
the exact flow is unknown: a point behind the target camera, which the renderer's worlds
almost never have), ``region`` ``(H, W)`` uint8 (the renderer's region map of the source frame)
and ``visibility`` ``(H, W)`` uint8 (:func:`~mfg_lightning.metrics.flow_quality.visibility_codes`:
visible, occluded in the target frame, out of its frame, or unknown), filled on every core by
:meth:`prepare_data` (:func:`~mfg_lightning.data.rendered_preparation.prepare_pairs`).

Occluded and out-of-frame pixels keep their exact flow (it is known: where the point goes) and
count in the training loss, as every pixel with known flow did before they were marked; the
marks only split the validation's scores into KITTI's non-occluded (``noc``) and all pixels
(:func:`~mfg_lightning.models.flow_module.score_flow`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning.data.base import MFGDataModule
from mfg_lightning.data.rendered import RenderedDrivingDataset
from mfg_lightning.data.rendered_preparation import MIN_CHUNK_PAIRS, prepare_pairs
from mfg_lightning.data.resumable_loader import ResumableDataLoader
from mfg_lightning.flow.estimators import EstimatedFlow
from mfg_lightning.metrics.flow_quality import (
    OCCLUDED,
    OUT_OF_FRAME,
    QUALITY_REGIONS,
    QUALITY_SETS,
)

log = logging.getLogger(__name__)

__all__ = ["FlowPairsDataModule", "FlowPairsDataset", "render_pairs"]

# Bump when the arrays cached per pair change. 2: the visibility codes.
_PAIRS_CACHE_FORMAT = 2
#: The arrays cached per pair.
_ARRAYS = ("images", "flow", "region", "visibility")


class _RGBFrames:
    """The frames as they are rendered: what :class:`FlowPairsDataset` keeps of a frame (no
    estimator runs on the training pairs; the exact flow is the target)."""

    name = "rgb"

    def key(self) -> dict[str, Any]:
        return {"estimator": self.name}

    def prepare(self, rgb: np.ndarray) -> np.ndarray:
        return rgb

    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        raise TypeError("flow pairs carry the exact flow; nothing is estimated")


class FlowPairsDataset(RenderedDrivingDataset):
    """Rendered frame pairs with their exact flow at the render size (``image_hw``).

    A sample: ``image0``, ``image1`` ``(3, H, W)`` uint8 RGB; ``flow`` ``(2, H, W)`` float32
    input pixels with ``image0(x) ≈ image1(x + flow(x))`` where the point is visible in
    ``image1``, NaN where unknown; ``region`` ``(H, W)`` uint8 (the renderer's codes);
    ``visibility`` ``(H, W)`` uint8 (:func:`~mfg_lightning.metrics.flow_quality.visibility_codes`:
    the flow of an occluded or out-of-frame pixel is kept, marked); ``offset`` (target − source
    frame), ``sample_id``.

    Args:
        trajectories, frames, seed, offsets, name, stride: as
            :class:`~mfg_lightning.data.driving.TrajectoryDataset`.
        image_hw: the render size (multiples of the network's divisor).
        world: :class:`~mfg_lightning.scene.worlds.WorldConfig` fields.
        cache_dir: ``paths.cache_dir``.
        every: keep only the source frames whose index is a multiple of it (a validation
            subset; counted from frame 0, as ``stride``).
    """

    cache_namespace = "flow_pairs"
    pictures = False

    def __init__(
        self,
        trajectories: dict[str, torch.Tensor],
        frames: dict[str, tuple[int, int]],
        image_hw: Sequence[int] = (192, 512),
        world: dict[str, Any] | None = None,
        cache_dir: str | Path | None = None,
        every: int = 1,
        **kwargs: Any,
    ) -> None:
        h, w = (int(v) for v in image_hw)
        source = EstimatedFlow(_RGBFrames(), h, w)  # type: ignore[arg-type]
        super().__init__(
            trajectories, frames, h, w, flow=source, world=world, cache_dir=cache_dir, **kwargs
        )
        if every > 1:
            self.samples = [s for s in self.samples if s[1] % every == 0]

    def cache_key(self) -> dict[str, Any]:
        key = super().cache_key()
        for dropped in ("flow", "output_hw"):
            key.pop(dropped)
        return {**key, "format": f"flow-pairs-{_PAIRS_CACHE_FORMAT}"}

    def _cached(self, i: int) -> dict[str, np.ndarray] | None:
        arrays = self.cache.load_arrays(self.pair_path(i), _ARRAYS)
        if arrays is None or arrays["images"].shape != (*self.image_hw, 6):
            return None
        return arrays

    def compute_pair(self, seq: str, src: int, tgt: int, a: Any, b: Any) -> dict:
        """The two frames (rendered, with their RGB as ``image``), the exact flow ``src → tgt``
        at the render size and its visibility codes."""
        _, flow, valid, visibility = self.exact_pair(seq, src, tgt, a, b)
        return {
            "images": np.concatenate((a.image, b.image), axis=2),
            "flow": np.where(valid[..., None], flow, np.nan).astype(np.float16),
            "region": a.rendered.region.detach().cpu().numpy().astype(np.uint8),
            "visibility": visibility,
            # (the preparation's per-pair statistics: this dataset estimates nothing)
            "quality": np.zeros((len(QUALITY_SETS), len(QUALITY_REGIONS), 3)),
            "nonfinite": np.int64(0),
            "occluded": np.int64((visibility == OCCLUDED).sum()),
            "out_of_frame": np.int64((visibility == OUT_OF_FRAME).sum()),
        }

    def _store(self, i: int, pair: dict) -> dict[str, np.ndarray]:
        arrays = {k: pair[k] for k in _ARRAYS}
        self.cache.store_arrays(self.pair_path(i), arrays)
        return arrays

    def __getitem__(self, i: int) -> dict[str, Any]:
        self._check_index(i)
        seq, src, tgt = self.samples[i]
        arrays = self._pair_arrays(i)  # (cached, else rendered and stored)
        images = torch.from_numpy(np.ascontiguousarray(arrays["images"].transpose(2, 0, 1)))
        return {
            "image0": images[:3],
            "image1": images[3:],
            "flow": torch.from_numpy(arrays["flow"].transpose(2, 0, 1).astype(np.float32)),
            "region": torch.from_numpy(np.ascontiguousarray(arrays["region"])),
            "visibility": torch.from_numpy(np.ascontiguousarray(arrays["visibility"])),
            "offset": tgt - src,
            "sample_id": f"{self.name}/{seq}/{src:06d}->{tgt:06d}",
        }


def render_pairs(datasets: Sequence[FlowPairsDataset], workers: int | None) -> None:
    """Render every missing pair of ``datasets`` into the cache on ``workers`` processes (None:
    every usable core), and log what was rendered."""
    done = prepare_pairs(datasets, workers=workers, min_chunk_pairs=MIN_CHUNK_PAIRS)
    for ds, result in zip(datasets, done, strict=True):
        if result.pairs:
            log.info("rendered %d frames and the exact flow of %d %s pairs under %s",
                     result.frames, result.pairs, ds.name, ds.cache.root)  # fmt: skip


class FlowPairsDataModule(MFGDataModule):
    """The learned flow's training and validation pairs (``dataset=flow_pairs``).

    Args:
        trajectory, poses_dir, train_sequences, sequence_length, max_frames, val_fraction,
            world, scene_seed: the worlds and splits, as ``dataset=synthetic``
            (:class:`~mfg_lightning.data.synthetic.SyntheticDataModule`); only its training
            trajectories are read.
        offsets: target offsets of every pair (the study's ±1, ±2).
        frame_stride: training pairs from every ``frame_stride``-th source frame.
        val_every: validation pairs from every ``val_every``-th frame of the validation tails.
        image_hw: the render size (``[192, 512]``, ``flow=dis``'s), multiples of 32.
        batch_size, eval_batch_size, num_workers, seed: :class:`MFGDataModule`'s (the workers
            persist across epochs).
        prepare_workers: processes rendering the pairs in :meth:`prepare_data` (None: every
            usable core).
        cache_dir: ``paths.cache_dir``.
    """

    def __init__(
        self,
        trajectory: str = "procedural",
        poses_dir: str | None = None,
        train_sequences: int | Sequence[str] = 8,
        sequence_length: int = 400,
        max_frames: int | None = None,
        val_fraction: float = 0.05,
        world: dict[str, Any] | None = None,
        scene_seed: int | None = None,
        offsets: Sequence[int] = (-2, -1, 1, 2),
        frame_stride: int = 8,
        val_every: int = 4,
        image_hw: Sequence[int] = (192, 512),
        batch_size: int = 8,
        eval_batch_size: int = 8,
        num_workers: int = 1,
        prepare_workers: int | None = None,
        cache_dir: str | None = None,
        seed: int = 0,
    ) -> None:
        hw = tuple(int(v) for v in image_hw)
        if len(hw) != 2 or min(hw) < 32 or hw[0] % 32 or hw[1] % 32:
            raise ValueError(
                f"dataset.image_hw must be [height, width], multiples of 32, got {list(image_hw)}"
            )
        super().__init__(height=hw[0], width=hw[1], batch_size=int(batch_size),
                         eval_batch_size=int(eval_batch_size), num_workers=int(num_workers),
                         seed=int(seed), persistent_workers=True)  # fmt: skip
        from mfg_lightning.data.synthetic import SyntheticDataModule

        for key, value in (("frame_stride", frame_stride), ("val_every", val_every)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"dataset.{key} must be a positive integer, got {value!r}")
        self.image_hw = hw
        # the splits and worlds of dataset=synthetic flow=dis (the estimator is never run)
        self.splits = SyntheticDataModule(
            trajectory=trajectory, poses_dir=poses_dir, train_sequences=train_sequences,
            sequence_length=sequence_length, max_frames=max_frames, val_fraction=val_fraction,
            flow={"source": "dis", "height": hw[0], "width": hw[1]}, offsets=offsets,
            frame_stride=frame_stride, world=world, scene_seed=scene_seed, seed=seed,
        )  # fmt: skip
        self.world = dict(world or {})
        self.val_every = val_every
        self.prepare_workers = prepare_workers
        self.cache_dir = cache_dir

    def build_dataset(self, split: str) -> FlowPairsDataset:  # type: ignore[override]
        """The ``train`` or ``val`` pairs."""
        if split not in ("train", "val"):
            raise ValueError(f"flow pairs have a train and a val split, not {split!r}")
        trajs, frames, common = self.splits.split_spec(split)
        ds = FlowPairsDataset(
            trajs, frames, image_hw=self.image_hw, world=self.world, cache_dir=self.cache_dir,
            every=self.val_every if split == "val" else 1,
            **{**common, "name": f"flow_pairs/{split}"},
        )  # fmt: skip
        if not ds.samples:
            raise ValueError(
                f"{ds.name}: no pairs (dataset.frame_stride, dataset.val_every or "
                "dataset.val_fraction leave none)"
            )
        return ds

    def setup(self, stage: str | None = None) -> None:
        # the flow network is fit and validated, never tested: no test split
        for split in ("train", "val") if stage in ("fit", None) else ("val",):
            self.dataset(split)

    def prepare_data(self) -> None:
        """Render every missing pair of both splits into the cache, on every core."""
        render_pairs([self.dataset("train"), self.dataset("val")], self.prepare_workers)

    def ordinary_train_loader(self) -> ResumableDataLoader:
        # whole batches only, where the split holds one
        loader = self._loader("train", shuffle=True, batch_size=self.batch_size,
                              drop_last=len(self.dataset("train")) >= self.batch_size)  # fmt: skip
        return ResumableDataLoader.like(loader, seed=self.seed)
