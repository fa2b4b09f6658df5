"""The built-in synthetic driving dataset: procedural scenes, exact flow, no download.

A car-mounted camera (KITTI-like intrinsics, 1.65 m above a ground plane) drives along a
continuous trajectory: either a procedural driving model (speed, yaw rate, small pitch and roll,
bumps; all smooth AR(1) processes) or the real KITTI ground-truth poses
(``trajectory=kitti``, ``poses_dir`` pointing at KITTI's ``poses/XX.txt``). Around it: building
facades and parked boxes at random distances, sky at the far plane (655.35 m, as Virtual KITTI),
and a random number of independently moving objects (cars and pedestrians) with their own 3D
velocity.

Every sample is generated from ``(seed, sequence, frame)``: the same index always yields the
same sample, in any worker, so it is generated once and then read back from the sample cache
(:mod:`mfg_lightning.data.sample_cache`; ``dataset.sample_cache``). The input flow is the
*exact* reprojection flow (:func:`mfg_lightning.core.geometry.reprojection_flow`, not the
linearised field) plus Gaussian noise and a fraction of outliers. Each sample also carries
depth, the relative pose, intrinsics, the ground-truth moving-object mask and the flow due to
object motion alone (see :mod:`mfg_lightning.data.sample`).

Scenes are drawn anew for every frame (the world does not persist along a trajectory): the flow of
a frame depends only on the relative pose and the scene in front of the camera at that moment,
which is what egomotion and object motion are evaluated on.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from mfg_lightning.data import rendered_quality
from mfg_lightning.data.base import (
    MFGDataModule,
    check_offsets,
    normalize_sequence,
)
from mfg_lightning.data.driving import SyntheticDrivingDataset
from mfg_lightning.data.prefetch import Prefetcher, check_prefetch
from mfg_lightning.data.rendered import RenderedDrivingDataset, flow_render_size
from mfg_lightning.data.rendered_preparation import MIN_CHUNK_PAIRS, prepare_pairs
from mfg_lightning.data.rendered_worlds import crossing_config, world_config
from mfg_lightning.data.resumable_loader import ResumableDataLoader
from mfg_lightning.data.sample_cache import MemoryBudget, SampleCacheSettings
from mfg_lightning.flow.estimators import (
    EstimatedFlow,
    ExactFlow,
    FlowSource,
    parse_flow,
)
from mfg_lightning.metrics.flow_quality import quality_line
from mfg_lightning.scene.boxes import SceneConfig
from mfg_lightning.scene.camera import procedural_trajectory
from mfg_lightning.scene.seeding import seeded_rng
from mfg_lightning.trajectory.pose_io import read_kitti_poses

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Scenes and rendering
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Dataset and DataModule
# --------------------------------------------------------------------------------------------


class SyntheticDataModule(MFGDataModule):
    """The default dataset: procedural driving or real KITTI trajectories, no download.

    Splits: ``train`` and ``test`` are disjoint sets of trajectories; ``val`` is the last
    ``val_fraction`` of every training trajectory (held out from training).

    Flow (the ``flow`` config group): ``flow=exact`` (default) generates every sample, once, on
    a scene drawn for its frame (:class:`SyntheticDrivingDataset`); ``flow=dis`` renders
    persistent worlds and estimates the flow on the frames (:class:`RenderedDrivingDataset`),
    precomputed into the cache by :meth:`prepare_data`, whose flow quality (EPE, Fl per region)
    is logged when training starts (``<split>/flow_epe/<region>``, ``<split>/flow_fl/<region>``
    and a picture grid, to TensorBoard) and written beside the cache
    (``quality-<split>-<pairs>pairs-<digest>.json``, named by the pair set it measures:
    :mod:`mfg_lightning.data.rendered_quality`).

    Args:
        trajectory: ``"procedural"`` or ``"kitti"``.
        poses_dir: directory of KITTI ``XX.txt`` pose files (``trajectory=kitti``).
        train_sequences, test_sequences: procedural: how many trajectories; kitti: lists of
            sequence names (paper split: train 00–08, test 09, 10).
        sequence_length: frames per procedural trajectory.
        max_frames: use at most this many frames of each KITTI sequence (None: all).
        val_fraction: tail of each training trajectory used for validation.
        flow: the ``flow`` config (:func:`~mfg_lightning.flow.estimators.parse_flow`):
            ``{"source": "exact", "noise_std": …, "outlier_fraction": …}`` (the default) or an
            estimator (``{"source": "dis", "preset": …, "height": …, "width": …}``).
        world: :class:`~mfg_lightning.scene.worlds.WorldConfig` fields of the rendered worlds.
        cache_dir: where estimated flow is cached (``paths.cache_dir``).
        precompute_flow: fill the cache in :meth:`prepare_data` (else on first use).
        prepare_workers: processes of :meth:`prepare_data`'s rendering and estimation
            (:func:`~mfg_lightning.data.rendered_preparation.prepare_pairs`: chunks of frames
            from every
            sequence of every split in one pool of single-threaded processes); None: every
            usable core; 0 or 1: the calling process. The cached pairs are the same whichever.
        prepare_chunk_pairs: the least pairs of one such chunk (fewer pairs than two chunks
            are prepared in the calling process, which costs no process start).
        offsets: target offsets of every split, ``target = frame + offset`` (``[1]``; ``[-2, -1,
            1, 2]``: the flows from a centre frame to its neighbours, for central-frame ATE), as
            ``dataset=kitti``'s.
        frame_stride: training uses the source frames whose index is a multiple of it (1: all;
            3: a third of the training pairs to render, on the same worlds and cache).
            Validation and test always use every frame (validation's frame-by-frame ATE needs
            five consecutive frames; the test split is the published protocols').
        scene: :class:`SceneConfig` fields.
        scene_seed: seed of the trajectories and scenes (None: ``seed``, which then also sets
            the training order); the config fixes it so that runs differing in ``seed`` see the
            same samples, in a different order.
        input_flow: the flow the model reads. ``"source"``: the flow group's (the DIS estimate,
            or the exact flow with its noise and outliers); ``"exact"``: the exact flow of the
            same samples (``flow=dis``: the rendered worlds' exact flow, cached beside the
            estimate, so switching renders nothing; ``flow=exact``: without noise or outliers),
            the ground-truth flow the paper trained and tested on for Virtual KITTI.
        sample_cache: ``{"memory_mb": …, "disk": …}``
            (:class:`~mfg_lightning.data.sample_cache.SampleCacheSettings`; None: 1024 MB,
            disk on): every sample is computed once, then read back bit for bit. Training and
            validation samples are kept in memory up to ``memory_mb`` per process (test samples,
            read once a run, are not); with ``disk``, every split's samples are also written
            under ``cache_dir`` (none: no disk tier) and read by later epochs beyond the memory
            and by later runs. ``flow=exact``: the generated samples
            (``synthetic_samples/<key>/``); ``flow=dis``: the pairs read from the flow cache
            (memory only: they are on disk already).
        prefetch: who computes the first epoch of ``flow=exact`` ahead of the training step:
            ``"thread"`` (a background thread of the training process, in the loader's order;
            only with ``num_workers=0``), ``"worker"`` (the training loader gets at least one
            persistent worker process, whose memory cache survives the epochs) or ``"none"``.
            The same samples in the same order whichever: the results do not change. The config
            sets ``thread``; constructed directly the default is ``"none"`` (no thread unless
            asked for).
        Remaining arguments: see :class:`MFGDataModule`.
    """

    def __init__(
        self,
        trajectory: str = "procedural",
        poses_dir: str | None = None,
        train_sequences: int | Sequence[str] = 8,
        test_sequences: int | Sequence[str] = 2,
        sequence_length: int = 400,
        max_frames: int | None = None,
        val_fraction: float = 0.05,
        flow: FlowSource | dict[str, Any] | None = None,
        offsets: Sequence[int] = (1,),
        frame_stride: int = 1,
        scene: dict | None = None,
        scene_seed: int | None = None,
        world: dict[str, Any] | None = None,
        cache_dir: str | None = None,
        precompute_flow: bool = True,
        prepare_workers: int | None = None,
        prepare_chunk_pairs: int = MIN_CHUNK_PAIRS,
        input_flow: str = "source",
        sample_cache: SampleCacheSettings | dict[str, Any] | None = None,
        prefetch: str = "none",
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        self.sample_cache = SampleCacheSettings.parse(sample_cache)
        self.prefetch = check_prefetch(prefetch)
        # One budget for the splits of this process (each DataLoader worker gets its share).
        self._memory = (
            MemoryBudget(self.sample_cache.memory_mb) if self.sample_cache.memory_mb > 0 else None
        )
        self._prefetchers: dict[str, Prefetcher] = {}
        if input_flow not in ("source", "exact"):
            raise ValueError(f"dataset.input_flow must be 'source' or 'exact', got {input_flow!r}")
        self.input_flow = input_flow
        self.scene_seed = self.seed if scene_seed is None else int(scene_seed)
        if trajectory not in ("procedural", "kitti"):
            raise ValueError(
                f"dataset.trajectory must be 'procedural' or 'kitti', got {trajectory!r}"
            )
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"dataset.val_fraction must be in [0, 1), got {val_fraction}")
        self.flow = parse_flow(flow, default="exact")
        if not isinstance(self.flow, (ExactFlow, EstimatedFlow)):
            raise ValueError(
                f"flow.source={self.flow.source}: dataset=synthetic makes its own flow; use "
                "flow=exact (the default) or an estimator on rendered frames (flow=dis)"
            )
        if isinstance(self.flow, EstimatedFlow):
            flow_render_size(self.flow, (self.height, self.width))
            # a bad world setting fails here, not later
            world_config(dict(world or {}))
            crossing_config(dict(world or {}))
        self.trajectory = trajectory
        self.poses_dir = poses_dir
        self.train_sequences = train_sequences
        self.test_sequences = test_sequences
        self.sequence_length = sequence_length
        if max_frames is not None and (
            isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 2
        ):
            raise ValueError(
                f"dataset.max_frames must be an integer ≥ 2 or null, got {max_frames!r}"
            )
        self.max_frames = max_frames
        if isinstance(frame_stride, bool) or not isinstance(frame_stride, int) or frame_stride < 1:
            raise ValueError(
                f"dataset.frame_stride must be a positive integer, got {frame_stride!r}"
            )
        self.frame_stride = frame_stride
        self.val_fraction = val_fraction
        self.world = dict(world or {})
        self.cache_dir = cache_dir
        self.precompute = bool(precompute_flow)
        if prepare_workers is not None and (
            isinstance(prepare_workers, bool)
            or not isinstance(prepare_workers, int)
            or prepare_workers < 0
        ):
            raise ValueError(
                f"dataset.prepare_workers must be an integer ≥ 0 or null, got {prepare_workers!r}"
            )
        if (
            isinstance(prepare_chunk_pairs, bool)
            or not isinstance(prepare_chunk_pairs, int)
            or prepare_chunk_pairs < 1
        ):
            raise ValueError(
                "dataset.prepare_chunk_pairs must be a positive integer, got "
                f"{prepare_chunk_pairs!r}"
            )
        self.prepare_workers = prepare_workers
        self.prepare_chunk_pairs = prepare_chunk_pairs
        self.offsets = check_offsets(offsets)
        self.scene = SceneConfig(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in (scene or {}).items()}
        )
        self._trajectories: dict[str, dict[str, torch.Tensor]] = {}
        self._logged_quality: set[str] = set()

    def _load(self, which: str) -> dict[str, torch.Tensor]:
        """``which`` in ``{"train", "test"}`` → sequence name → poses."""
        if which in self._trajectories:
            return self._trajectories[which]
        spec = self.train_sequences if which == "train" else self.test_sequences
        trajs: dict[str, torch.Tensor] = {}
        if self.trajectory == "procedural":
            if not isinstance(spec, int) or spec <= 0:
                raise ValueError(
                    f"dataset.{which}_sequences must be a positive count (procedural trajectories)"
                )
            if self.sequence_length < 6:
                raise ValueError("dataset.sequence_length must be at least 6 frames")
            for s in range(spec):
                name = f"{which}{s:02d}"
                trajs[name] = procedural_trajectory(
                    seeded_rng(self.scene_seed, "trajectory", name), self.sequence_length
                )
        else:
            if self.poses_dir is None:
                raise ValueError(
                    "dataset.trajectory=kitti needs dataset.poses_dir (KITTI's poses/ directory)"
                )
            root = Path(self.poses_dir).expanduser()
            if isinstance(spec, int):
                raise ValueError(
                    f"dataset.{which}_sequences must list KITTI sequences for trajectory=kitti"
                )
            for seq in map(normalize_sequence, spec):
                path = root / f"{seq}.txt"
                if not path.is_file():
                    raise FileNotFoundError(
                        f"KITTI pose file not found: {path} (dataset.poses_dir={root})"
                    )
                poses = torch.from_numpy(read_kitti_poses(path))
                trajs[seq] = poses[: self.max_frames] if self.max_frames else poses
        self._trajectories[which] = trajs
        return trajs

    def split_spec(
        self, split: str
    ) -> tuple[dict[str, torch.Tensor], dict[str, tuple[int, int]], dict[str, Any]]:
        """What a split samples: its trajectories (sequence → poses), the ``(first, last)``
        source frames of each, and the :class:`~mfg_lightning.data.driving.TrajectoryDataset`
        arguments ``seed``, ``offsets``, ``name`` and ``stride`` (``split`` in ``train``,
        ``val``, ``train+val``, ``test``)."""
        trajs = self._load("test" if split == "test" else "train")
        frames: dict[str, tuple[int, int]] = {}
        for seq, poses in trajs.items():
            last = poses.shape[0] - 2  # the last source frame with a successor
            n_val = round(self.val_fraction * (last + 1))
            if split == "train":
                frames[seq] = (0, last - n_val)
            elif split == "val":
                if n_val:
                    frames[seq] = (last - n_val + 1, last)
            elif split == "train+val":  # every pair of both: what prepare_data computes
                frames[seq] = (0, last)
            else:
                frames[seq] = (0, poses.shape[0] - 1)
        # Every split samples the same offsets (train+val: the pairs of both, for the cache).
        # The stride thins training only: validation keeps every frame of the held-out tails,
        # so that its frame-by-frame ATE (five consecutive frames) is defined.
        common = {
            "seed": self.scene_seed + (7919 if split == "test" else 0),
            "offsets": self.offsets,
            "name": f"synthetic/{split}",
            "stride": self.frame_stride if split == "train" else 1,
        }
        return trajs, frames, common

    def build_dataset(self, split: str) -> SyntheticDrivingDataset | RenderedDrivingDataset:
        trajs, frames, common = self.split_spec(split)
        exact = self.input_flow == "exact"
        # Test samples are read once a run (memory would hold them for nothing) and train+val
        # is prepare_data's pass over the flow cache: neither is kept in memory.
        memory = self._memory if split in ("train", "val") else None
        if isinstance(self.flow, EstimatedFlow):
            ds = RenderedDrivingDataset(
                trajs, frames, self.height, self.width, flow=self.flow, world=self.world,
                cache_dir=self.cache_dir, input_flow=self.input_flow, memory=memory, **common,
            )  # fmt: skip
        else:
            ds = SyntheticDrivingDataset(
                trajs, frames, self.height, self.width,
                noise_std=0.0 if exact else self.flow.noise_std,
                outlier_fraction=0.0 if exact else self.flow.outlier_fraction,
                scene=self.scene, memory=memory,
                cache_dir=self.cache_dir if self.sample_cache.disk else None, **common,
            )  # fmt: skip
        if split == "train+val" and self.frame_stride > 1:
            val_first = {seq: first for seq, (first, _) in self._val_frames(trajs).items()}
            ds.samples = [
                (seq, k, t)
                for seq, k, t in ds.samples
                if k % self.frame_stride == 0 or k >= val_first.get(seq, k + 1)
            ]
        return ds

    # -- the training loader: the first epoch computed ahead of the step ---------------------

    def ordinary_train_loader(self) -> ResumableDataLoader:
        """The training loader (:class:`MFGDataModule`'s), with ``flow=exact``'s prefetch:
        ``thread`` hooks a :class:`~mfg_lightning.data.prefetch.Prefetcher` to its sampler
        (each pass's order, a resumed one's remaining indices included), ``worker`` gives it at
        least one persistent worker process."""
        exact = not isinstance(self.flow, EstimatedFlow)
        if exact and self.prefetch == "worker":
            base = self._loader(
                "train", True, self.batch_size, num_workers=max(1, self.num_workers),
                persistent_workers=True,
            )  # fmt: skip
            return ResumableDataLoader.like(base, seed=self.seed)
        loader = super().ordinary_train_loader()
        dataset = self.dataset("train")
        if exact and self.prefetch == "thread" and loader.order is not None:
            assert isinstance(dataset, SyntheticDrivingDataset)
            if self.num_workers > 0:
                # The loader's workers would read their own copies of the cache, not the one a
                # thread of this process fills.
                log.info("dataset.prefetch=thread needs dataset.num_workers=0: no prefetch thread")
            elif dataset.store is not None:
                self._stop_prefetch("train")
                prefetcher = Prefetcher(dataset.prefetch, name="prefetch synthetic/train")
                self._prefetchers["train"] = prefetcher
                loader.order.on_order = prefetcher.follow
        return loader

    def _stop_prefetch(self, split: str) -> None:
        prefetcher = self._prefetchers.pop(split, None)
        if prefetcher is not None:
            prefetcher.stop()

    def teardown(self, stage: str | None = None) -> None:
        # The thread holds the dataset: stop it with the stage (a multirun's next job, in the
        # same process, then starts from a clean slate).
        for split in list(self._prefetchers):
            self._stop_prefetch(split)
        super().teardown(stage)

    def _val_frames(self, trajs: dict[str, torch.Tensor]) -> dict[str, tuple[int, int]]:
        """Sequence → (first, last) source frame of its validation tail (none: absent)."""
        out = {}
        for seq, poses in trajs.items():
            last = poses.shape[0] - 2
            n_val = round(self.val_fraction * (last + 1))
            if n_val:
                out[seq] = (last - n_val + 1, last)
        return out

    # -- estimated flow: precompute, quality, pictures ---------------------------------------

    def quality_path(self, split: str) -> Path:
        """Where a split's flow quality is written: beside the cache, named by the pair set it
        measures (:func:`mfg_lightning.data.rendered_quality.quality_path` of its dataset)."""
        ds = self.dataset(split)
        assert isinstance(ds, RenderedDrivingDataset)
        return rendered_quality.quality_path(ds, split)

    def prepare_data(self) -> None:
        """``flow=dis``: render and estimate every missing pair of every split into the cache,
        then write each split's flow quality and a picture per trajectory beside it.

        The train + validation pairs and the test pairs go into one pool
        (:func:`~mfg_lightning.data.rendered_preparation.prepare_pairs`,
        ``dataset.prepare_workers``
        processes, every usable core by default), in contiguous chunks of frames; the quality
        sums of the pairs computed come back from the workers, so that only pairs cached by an
        earlier run are read for the quality. Lightning calls this on one process per node;
        ``flow=exact`` has nothing to prepare."""
        if not isinstance(self.flow, EstimatedFlow) or not self.precompute:
            return
        import json

        from mfg_lightning.core.atomic import atomic_write_text

        parts = ("train+val", "test")
        datasets = [self.build_dataset(part) for part in parts]
        prepared = prepare_pairs(
            datasets, workers=self.prepare_workers, min_chunk_pairs=self.prepare_chunk_pairs
        )
        for part, ds, done in zip(parts, datasets, prepared, strict=True):
            if done.pairs:
                log.info(
                    "rendered %d frames and estimated the %s flow of %d %s pairs under %s "
                    "(%d worker processes; 0: this one)",
                    done.frames,
                    ds.estimator.name,
                    done.pairs,
                    part,
                    ds.cache.root,
                    done.processes,
                )
            for seq in ds.sequences():
                # (the middle pair was cached before without its picture: a run that read it)
                if not ds.picture_path(seq).exists():
                    ds.cache.store(ds.picture_path(seq), ds.picture(seq))
        for split in ("train", "val", "test"):
            path = self.quality_path(split)
            if path.exists():
                continue
            known = prepared[parts.index("test" if split == "test" else "train+val")].stats
            quality = self.dataset(split).quality(known)
            atomic_write_text(path, json.dumps(quality, indent=2) + "\n")
            if quality["nonfinite_pixels"]:
                log.warning(
                    "%d estimated flow pixels of the %s split were not finite: masked invalid",
                    quality["nonfinite_pixels"],
                    split,
                )
            log.info("flow quality (%s): %s", split, quality_line(quality["regions"]))

    def setup(self, stage: str | None = None) -> None:
        super().setup(stage)
        # the estimate's quality says nothing of the flow the model reads with input_flow=exact
        if isinstance(self.flow, EstimatedFlow) and self.input_flow == "source":
            self._log_flow_quality()

    def _log_flow_quality(self) -> None:
        """Log each built split's flow quality and pictures to the trainer's loggers (once):
        ``<split>/flow_epe/<region>`` (pixels) and ``<split>/flow_fl/<region>`` (%) at step 0,
        the picture grids as ``<split>/flow_picture/<seq>`` images
        (:func:`~mfg_lightning.data.rendered_quality.log_split_quality`)."""
        trainer = self.trainer
        if trainer is None or not trainer.loggers:
            return
        for split, ds in self.datasets.items():
            path = self.quality_path(split)
            if split in self._logged_quality or not path.exists():
                continue
            self._logged_quality.add(split)
            assert isinstance(ds, RenderedDrivingDataset)
            rendered_quality.log_split_quality(trainer.loggers, split, ds, path)
