"""Virtual KITTI 1.3.1 and 2.0.3 as Lightning DataModules with the paper's two splits.

Layouts read (``docs/formats.md``, :mod:`mfg_lightning.data.vkitti_files`; ``data_root`` is the
directory holding the unpacked tarballs, never written to)::

    1.3.1 (version=1)
    vkitti_1.3.1_rgb/<world>/<var>/%05d.png
    vkitti_1.3.1_depthgt/<world>/<var>/%05d.png
    vkitti_1.3.1_flowgt/<world>/<var>/%05d.png
    vkitti_1.3.1_extrinsicsgt/<world>_<var>.txt

    2.0.3 (version=2)
    vkitti_2.0.3_rgb/SceneXX/<var>/frames/rgb/Camera_0/rgb_%05d.jpg
    vkitti_2.0.3_depth/SceneXX/<var>/frames/depth/Camera_0/depth_%05d.png
    vkitti_2.0.3_forwardFlow/SceneXX/<var>/frames/forwardFlow/Camera_0/flow_%05d.png
    vkitti_2.0.3_textgt/SceneXX/<var>/extrinsic.txt, intrinsic.txt   (Camera_0 rows are used)

Worlds are named ``0001 0002 0006 0018 0020`` in both versions (2.0.3's ``Scene01`` … are the same
worlds). Splits (the paper):

* ``split: egomotion`` (``dataset=vkitti``): test 0001, train 0002 0006 0018 0020;
* ``split: objects`` (``dataset=vkitti_objects``): train 0001 0006 0020, test 0002 0018.

Validation: a contiguous tail of each *training* world (``val_fraction``, default 5 %, at least
one pair; :func:`~mfg_lightning.data.transforms.holdout_ranges`), removed from training; test
worlds are never used for validation. The paper counts frames (1679 / 447 for the egomotion
split); a sample here is a pair ``t → t + 1``, so a world of N frames gives N − 1 samples.

Each sample (schema of :mod:`mfg_lightning.data.sample`) at the model's input size:

* ``flow``, ``flow_valid``: the ground-truth forward flow (``B == 0`` pixels invalid), resized by
  :func:`~mfg_lightning.data.transforms.resize_flow`;
* ``depth``: metres along z (:func:`~mfg_lightning.data.transforms.resize_depth`); the far plane
  (sky) keeps its stored 655.35 m;
* ``pose``: ``T_t,t+1 = T_world_cam(t)^-1 · T_world_cam(t+1)`` where ``T_world_cam`` is the
  inverse of the file's world-to-camera extrinsics;
* ``intrinsics``: fx = fy = 725, cx = 620.5, cy = 187 (1.3.1) or the frame's row of
  ``intrinsic.txt`` (2.0.3), scaled to the input size;
* ``object_mask``, ``object_flow``: independently moving pixels, found at the *native*
  resolution as pixels whose ground-truth flow differs from the rigid flow of the camera motion
  (:func:`mfg_lightning.core.geometry.reprojection_flow` of the depth and pose) by more than
  ``object_threshold`` native pixels. Only pixels with valid flow and a real depth count: the far
  plane (sky) and invalid flow are never objects. ``object_flow = flow − rigid flow`` on the mask
  (0 elsewhere), resized like the flow (mean over the object pixels of each output pixel); an
  output pixel is on the mask when at least half of its valid native pixels are;
* ``rgb``: the source image (``load_rgb``).
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning.core import geometry
from mfg_lightning.core.data_errors import DataFileError
from mfg_lightning.data import transforms
from mfg_lightning.data.base import MFGDataModule, check_split, split_sequences
from mfg_lightning.data.file_datasets import FileMotionDataset, list_numbered, some_of
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.data.vkitti_files import (
    check_vkitti_root,
    normalize_version,
    read_vkitti_extrinsics,
    read_vkitti_intrinsics,
)
from mfg_lightning.flow import io as flow_io
from mfg_lightning.flow.estimators import FlowSource, GroundTruthFlow, parse_flow

log = logging.getLogger(__name__)

__all__ = [
    "SPLITS",
    "VKITTI1_INTRINSICS",
    "VirtualKittiDataModule",
    "VirtualKittiDataset",
    "normalize_world",
]

WORLDS = ("0001", "0002", "0006", "0018", "0020")
VARIATIONS = (
    "clone", "15-deg-left", "15-deg-right", "30-deg-left", "30-deg-right",
    "morning", "sunset", "overcast", "fog", "rain",
)  # fmt: skip
#: The paper's splits: name → (train worlds, test worlds).
SPLITS = {
    "egomotion": (("0002", "0006", "0018", "0020"), ("0001",)),
    "objects": (("0001", "0006", "0020"), ("0002", "0018")),
}
#: Virtual KITTI 1.3.1's camera, the same for every frame: (fx, fy, cx, cy) at 1242×375.
VKITTI1_INTRINSICS = (725.0, 725.0, 620.5, 187.0)


def normalize_world(world: Any) -> str:
    """``1``, ``"1"``, ``"0001"``, ``"Scene01"`` → ``"0001"``."""
    text = str(world).strip()
    if text.lower().startswith("scene"):
        text = text[5:]
    if not text.isdigit():
        raise ValueError(f"unknown Virtual KITTI world {world!r}; worlds are {', '.join(WORLDS)}")
    return f"{int(text):04d}"


# --------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------


@dataclass
class _World:
    name: str
    extrinsics: dict[int, np.ndarray]  # frame → world-to-camera
    intrinsics: dict[int, np.ndarray] | None  # frame → (fx, fy, cx, cy) native (2.0.3)
    native_hw: tuple[int, int] | None  # (height, width) of its frames, from a flow file's header


class VirtualKittiDataset(FileMotionDataset):
    """Pairs ``t → t + 1`` of Virtual KITTI worlds (see the module docstring).

    Args:
        data_root: directory holding the unpacked ``vkitti_<version>_*`` directories.
        worlds: world names (``"0001"`` …).
        variation: rendering variation (``clone``, ``fog``, …).
        version: 1 (1.3.1) or 2 (2.0.3).
        val_fraction: fraction of each world held out as its validation tail.
        object_threshold: residual ``‖flow − rigid flow‖`` above which a pixel is moving, in
            pixels of the native (1242 × 375) resolution.
        load_rgb: deliver the source image as ``rgb``.
        kwargs: ``height``, ``width`` (the model's input size), ``split``, ``portion`` (``"all"``
            frames of each world, its ``"train"`` head or its ``"val"`` tail) and
            ``skip_bad_samples`` of :class:`~mfg_lightning.data.file_datasets.FileMotionDataset`.
    """

    name = "vkitti"
    title = "Virtual KITTI"

    def __init__(
        self,
        data_root: str | os.PathLike,
        worlds: Sequence[str],
        variation: str = "clone",
        version: int | str = 1,
        val_fraction: float = 0.05,
        object_threshold: float = 1.0,
        load_rgb: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if object_threshold <= 0:
            raise ValueError(f"dataset.object_threshold must be positive, got {object_threshold}")
        if variation not in VARIATIONS:
            warnings.warn(
                f"dataset.variation={variation!r} is not one of {VARIATIONS}", stacklevel=2
            )
        self.version = normalize_version(version)
        self.world_names = [normalize_world(w) for w in worlds]
        self.variation = str(variation)
        self.layout = check_vkitti_root(data_root, self.version, self.world_names, self.variation)
        self.object_threshold = float(object_threshold)
        self.load_rgb = load_rgb
        self._worlds: dict[str, _World] = {}
        problems: list[str] = []
        for world in self.world_names:
            problems += self._index_world(world, val_fraction)
        self.report_problems(problems)

    def _index_world(self, world: str, val_fraction: float) -> list[str]:
        L, var = self.layout, self.variation
        present = {
            kind: set(list_numbered(L.directory(kind, world, var), *prefix_suffix))
            for kind, prefix_suffix in L.names().items()
        }
        native_hw = self._frame_size(world, present["flow"])
        ext_file = L.extrinsics_file(world, var)
        extrinsics = read_vkitti_extrinsics(ext_file, self.version)
        intr_file = L.intrinsics_file(world, var)
        intrinsics = None if intr_file is None else read_vkitti_intrinsics(intr_file, native_hw)
        self._worlds[world] = _World(world, extrinsics, intrinsics, native_hw)
        n = max(present["rgb"], default=-1) + 1
        problems: list[str] = []
        if n == 0:
            return [f"{L.rgb_dir(world, var)}: no frames"]
        no_pose = [f for f in range(n) if f not in extrinsics]
        if no_pose:
            problems.append(
                f"{ext_file}: no extrinsics for {len(no_pose)} of the {n} frames in "
                f"{L.rgb_dir(world, var)} (first: frame {no_pose[0]})"
            )
        if intrinsics is not None:
            no_k = [f for f in range(n - 1) if f not in intrinsics]
            if no_k:
                problems.append(
                    f"{intr_file}: no intrinsics for {len(no_k)} frames (first: {no_k[0]})"
                )
        # Every source frame needs its depth and flow (and image with load_rgb); the last frame
        # has no successor, so its flow is not needed (2.0.3 does not ship it).
        kinds = ("depth", "flow", "rgb") if self.load_rgb else ("depth", "flow")
        for kind in kinds:
            gone = [f for f in range(n - 1) if f not in present[kind]]
            if gone:
                shown = some_of([L.file(kind, world, var, f).name for f in gone], 5, inline=True)
                problems.append(
                    f"{L.file(kind, world, var, gone[0]).parent}: {len(gone)} {kind} file(s) "
                    f"missing: {shown}"
                )
        allowed = self.portion_frames(n, val_fraction, span=1)
        for src in allowed:
            tgt = src + 1
            if tgt not in allowed or src not in extrinsics or tgt not in extrinsics:
                continue
            if any(src not in present[k] for k in kinds):
                continue
            if intrinsics is not None and src not in intrinsics:
                continue
            self.samples.append((world, src, tgt))
        return problems

    def _frame_size(self, world: str, flow_frames: set[int]) -> tuple[int, int] | None:
        """``(height, width)`` of a world's frames from its first flow file's header (every
        flow, depth and image file of the world must have it), or None when it has no readable
        one (the samples that need it report their files)."""
        if not flow_frames:
            return None
        try:
            return flow_io.image_size(
                self.layout.file("flow", world, self.variation, min(flow_frames))
            )
        except DataFileError:
            return None

    # -- MotionDataset -----------------------------------------------------------------------

    def _T_world_cam(self, world: str, frame: int) -> torch.Tensor:
        return geometry.invert_pose(torch.from_numpy(self._worlds[world].extrinsics[frame]))

    def relative_poses(self) -> torch.Tensor:
        """``(N, 4, 4)`` float32 ``T_src,tgt`` of every sample, from the extrinsics only."""
        if not self.samples:
            return torch.zeros(0, 4, 4)
        src = torch.stack([self._T_world_cam(w, a) for w, a, _ in self.samples])
        tgt = torch.stack([self._T_world_cam(w, b) for w, _, b in self.samples])
        return geometry.relative_pose(src, tgt).float()

    def native_intrinsics(self, world: str, frame: int) -> np.ndarray:
        """``(4,)`` ``(fx, fy, cx, cy)`` of ``frame`` in native pixels."""
        intrinsics = self._worlds[world].intrinsics
        if intrinsics is None:
            return np.array(VKITTI1_INTRINSICS, np.float64)
        return intrinsics[frame]

    def files(self, index: int) -> list[Path]:
        """The files sample ``index`` reads (for checks): flow, depth and (``load_rgb``) image."""
        world, src, _ = self.samples[index]
        kinds = ("flow", "depth", "rgb") if self.load_rgb else ("flow", "depth")
        return [self.layout.file(k, world, self.variation, src) for k in kinds]

    def describe(self) -> dict[str, dict[str, Any]]:
        """Per world: frames, native size (from the first flow file's header), intrinsics of the
        first sample (native and at the input size)."""
        out: dict[str, dict[str, Any]] = {}
        for world, indices in self.sequences().items():
            _, src, _ = self.samples[indices[0]]
            native_hw = flow_io.image_size(self.layout.file("flow", world, self.variation, src))
            K = self.native_intrinsics(world, src)
            K_in = transforms.resize_intrinsics(K, native_hw, (self.height, self.width))
            out[world] = {
                "frames": len(self._worlds[world].extrinsics),
                "native_size": list(native_hw),
                "intrinsics_native": [round(float(v), 4) for v in K],
                "intrinsics_input": [round(float(v), 4) for v in K_in],
            }
        return out

    def _load(self, index: int) -> dict[str, Any]:
        world, src, tgt = self.samples[index]
        L, var = self.layout, self.variation
        flow_path = L.file("flow", world, var, src)
        depth_path = L.file("depth", world, var, src)
        size = self._worlds[world].native_hw
        flow, valid = flow_io.read_vkitti_flow_png(flow_path, size)
        depth, far = flow_io.read_vkitti_depth(depth_path, size)
        if depth.shape != flow.shape[:2]:
            raise DataFileError(
                f"{depth_path}: depth is {depth.shape[1]}×{depth.shape[0]} but the flow "
                f"{flow_path} is {flow.shape[1]}×{flow.shape[0]}"
            )
        native_hw = depth.shape
        K = self.native_intrinsics(world, src)
        pose64 = geometry.relative_pose(
            self._T_world_cam(world, src), self._T_world_cam(world, tgt)
        )
        mask, residual = moving_object_mask(
            flow, valid, depth, far, pose64.numpy(), K, self.object_threshold
        )
        hw = (self.height, self.width)
        flow_lr, valid_lr = transforms.resize_flow(flow, valid, *hw)
        defined = valid & ~far & (depth > 0)
        mask_lr = transforms.resize_mask(mask, *hw, defined=defined) & valid_lr
        obj_lr, _ = transforms.resize_flow(residual, mask, *hw, min_valid_fraction=1e-6)
        obj_lr[~mask_lr] = 0.0
        flow_t, valid_t, _ = sanitize_flow(
            transforms.flow_to_tensor(flow_lr), torch.from_numpy(valid_lr)
        )
        sample: dict[str, Any] = {
            "flow": flow_t,
            "flow_valid": valid_t,
            "pose": pose64.float(),
            "intrinsics": transforms.resize_intrinsics(K, native_hw, hw),
            "depth": torch.from_numpy(transforms.resize_depth(depth, *hw)),
            "object_mask": torch.from_numpy(mask_lr),
            "object_flow": transforms.flow_to_tensor(obj_lr),
            **self.sample_identity(index),
        }
        if self.load_rgb:
            rgb = flow_io.read_rgb(L.file("rgb", world, var, src), size)
            rgb = transforms.resize_rgb(rgb, *hw)
            sample["rgb"] = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))
        return sample


def moving_object_mask(
    flow: np.ndarray,
    valid: np.ndarray,
    depth: np.ndarray,
    far: np.ndarray,
    pose: np.ndarray,
    intrinsics: np.ndarray,
    threshold: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth moving pixels: where the flow is not explained by the camera's motion.

    Args:
        flow: ``(H, W, 2)`` ground-truth flow ``t → t+1`` in pixels; valid: ``(H, W)`` bool.
        depth: ``(H, W)`` metres of frame t; far: ``(H, W)`` bool far-plane (sky) pixels.
        pose: ``(4, 4)`` ``T_t,t+1`` (camera t+1 in camera t).
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)`` at this resolution.
        threshold: pixels; a residual norm above it marks a moving pixel.

    Returns:
        ``(mask, residual)``: ``(H, W)`` bool, and ``(H, W, 2)`` float32 ``flow − rigid flow``
        (the rigid flow from :func:`mfg_lightning.core.geometry.reprojection_flow`; 0 where the
        pixel has no valid flow or no real depth).
    """
    defined = valid & ~far & (depth > 0)
    rigid = geometry.reprojection_flow(
        torch.from_numpy(np.where(defined, depth, 1.0).astype(np.float64))[None],
        torch.from_numpy(np.asarray(pose, np.float64))[None],
        torch.from_numpy(np.asarray(intrinsics, np.float64))[None],
    )[0]
    residual = flow - rigid.permute(1, 2, 0).numpy().astype(np.float32)
    residual[~defined] = 0.0
    mask = defined & (np.linalg.norm(residual, axis=2) > threshold)
    return mask, residual


# --------------------------------------------------------------------------------------------
# DataModule
# --------------------------------------------------------------------------------------------


class VirtualKittiDataModule(MFGDataModule):
    """Virtual KITTI with the paper's splits (``split``: ``egomotion`` or ``objects``).

    Args:
        data_root: directory holding the unpacked ``vkitti_*`` tarballs.
        version: 1 (1.3.1, default) or 2 (2.0.3).
        variation: rendering variation (default ``clone``).
        split: ``"egomotion"`` (test 0001) or ``"objects"`` (test 0002, 0018).
        train_worlds, test_worlds: override the split's worlds (None: the paper's).
        val_fraction: the validation tail of each training world (default 5 %).
        object_threshold: moving-pixel threshold in native pixels (default 1.0).
        load_rgb, skip_bad_samples: see :class:`VirtualKittiDataset`.
        flow: the ``flow`` config group: ``flow=ground_truth`` (the default, and the only source:
            the input flow is the ground-truth flow the dataset ships); any other source is
            refused naming ``flow.source``, never silently replaced.
        kwargs: ``height``, ``width``, ``batch_size``, … of
            :class:`~mfg_lightning.data.base.MFGDataModule`.
    """

    def __init__(
        self,
        data_root: str | None = None,
        version: int | str = 1,
        variation: str = "clone",
        split: str = "egomotion",
        train_worlds: Sequence[str] | None = None,
        test_worlds: Sequence[str] | None = None,
        val_fraction: float = 0.05,
        object_threshold: float = 1.0,
        load_rgb: bool = True,
        skip_bad_samples: bool = False,
        flow: FlowSource | dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.flow = parse_flow(flow, default="ground_truth")
        if not isinstance(self.flow, GroundTruthFlow):
            raise ValueError(
                f"flow.source={self.flow.source}: dataset=vkitti feeds the model Virtual KITTI's "
                "ground-truth flow (its flowgt / forwardFlow files); flow=ground_truth, its "
                "default, is the only flow source it has"
            )
        if split not in SPLITS:
            raise ValueError(f"dataset.split must be one of {sorted(SPLITS)}, got {split!r}")
        default_train, default_test = SPLITS[split]
        self.train_worlds = [normalize_world(w) for w in (train_worlds or default_train)]
        self.test_worlds = [normalize_world(w) for w in (test_worlds or default_test)]
        val_fraction = check_split(self.train_worlds, self.test_worlds, val_fraction, "worlds")
        self.split_name = split
        self.dataset_kwargs: dict[str, Any] = {
            "data_root": data_root,
            "variation": variation,
            "version": normalize_version(version),
            "height": self.height,
            "width": self.width,
            "val_fraction": val_fraction,
            "object_threshold": float(object_threshold),
            "load_rgb": load_rgb,
            "skip_bad_samples": skip_bad_samples,
        }

    def build_dataset(self, split: str) -> VirtualKittiDataset:
        worlds, portion = split_sequences(split, self.train_worlds, self.test_worlds)
        return VirtualKittiDataset(
            worlds=worlds, split=split, portion=portion, **self.dataset_kwargs
        )
