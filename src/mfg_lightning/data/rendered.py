"""Samples of ``flow=dis`` on the synthetic worlds: frames rendered from one persistent world per
trajectory (:mod:`mfg_lightning.scene`), flow estimated on them and cached, the exact flow and
the ground truth kept beside the estimate, and the estimate's quality per image region."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning.data import transforms
from mfg_lightning.data.driving import TrajectoryDataset
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.data.sample_cache import MemoryBudget, SampleStore, source_digest
from mfg_lightning.flow.estimators import (
    EstimatedFlow,
    FlowCache,
)
from mfg_lightning.scene.camera import kitti_like_intrinsics

#: The render size of ``flow=dis`` when ``flow.height``/``flow.width`` are unset: the released
#: code's image size (its flow, the model input, is a quarter of it).
RENDER_SIZE = (192, 512)


#: The regions flow quality is reported for (the renderer's region map), then all pixels.
QUALITY_REGIONS = ("road", "structure", "moving", "far", "all")


# Bump when the arrays cached per pair change, so old caches are not misread.
_RENDER_CACHE_FORMAT = 2


#: What :class:`RenderedDrivingDataset` caches per pair, at the model input ``h × w``: the
#: float fields as channels of one ``(h, w, 7)`` float32 array and the byte fields of one
#: ``(h, w, 4)`` uint8 array (two array headers to parse per sample instead of eight).
_FLOAT_FIELDS = (
    ("flow", 2),  # estimated flow, NaN where it was not finite
    ("exact_flow", 2),  # exact flow, 0 where unknown
    ("object_flow", 2),  # flow due to object motion alone, 0 off objects
    ("depth", 1),  # metres, 0 where unknown
)


_BYTE_FIELDS = (("rgb", 3), ("object_mask", 1))  # source frame; moving-object mask (0 / 1)


def _renderer():
    """The persistent-world renderer (:mod:`.worlds`, :mod:`.render`), imported on first use so
    that ``flow=exact`` never loads it."""
    from mfg_lightning.scene import render, worlds

    return worlds, render


def _numpy(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _hw2(field: Any) -> np.ndarray:
    """A ``(2, H, W)`` tensor or ``(H, W, 2)`` array → ``(H, W, 2)`` float32."""
    a = _numpy(field)
    if a.ndim == 3 and a.shape[0] == 2 and a.shape[2] != 2:
        a = np.moveaxis(a, 0, 2)
    return np.ascontiguousarray(a, dtype=np.float32)


def region_codes() -> list[tuple[str, int | None]]:
    """``(name, code)`` of every :data:`QUALITY_REGIONS` entry in the renderer's region map
    (``None``: all pixels)."""
    _, render = _renderer()
    codes = {
        "road": render.REGION_ROAD,
        "structure": render.REGION_STRUCTURE,
        "moving": render.REGION_MOVING,
        "far": render.REGION_FAR,
    }
    return [(name, codes.get(name)) for name in QUALITY_REGIONS]


def flow_quality(
    estimated: np.ndarray, exact: np.ndarray, valid: np.ndarray, region: np.ndarray
) -> np.ndarray:
    """End-point error and KITTI's Fl outliers of an estimated flow against the exact one.

    A pixel is an Fl outlier when its end-point error exceeds 3 px *and* 5 % of the exact flow's
    magnitude (the KITTI 2015 flow benchmark's definition).

    Args:
        estimated, exact: ``(H, W, 2)`` pixels (at the image size the flow was estimated at).
        valid: ``(H, W)`` bool, the pixels that count (exact flow known, estimate finite).
        region: ``(H, W)`` the renderer's region code of every pixel.

    Returns:
        ``(len(QUALITY_REGIONS), 3)`` float64: per region, the sum of the end-point errors
        (pixels), the number of outliers and the number of pixels counted; sums, so that pairs
        pool by addition.
    """
    epe = np.linalg.norm(estimated.astype(np.float64) - exact, axis=2)
    outlier = (epe > 3.0) & (epe > 0.05 * np.linalg.norm(exact.astype(np.float64), axis=2))
    out = np.zeros((len(QUALITY_REGIONS), 3))
    for r, (_, code) in enumerate(region_codes()):
        m = valid if code is None else valid & (region == code)
        out[r] = (epe[m].sum(), outlier[m].sum(), m.sum())
    return out


def summarize_quality(stats: np.ndarray) -> dict[str, dict[str, float | None]]:
    """Pooled ``{region: {"epe": px, "fl": %, "pixels": n}}`` from summed per-pair stats
    (``(..., R, 3)``: pairs pooled pixel by pixel; None where a region had no pixel)."""
    total = stats.reshape(-1, len(QUALITY_REGIONS), 3).sum(axis=0)
    out: dict[str, dict[str, float | None]] = {}
    for name, (epe, outliers, n) in zip(QUALITY_REGIONS, total, strict=True):
        out[name] = {
            "epe": float(epe / n) if n else None,
            "fl": float(100.0 * outliers / n) if n else None,
            "pixels": float(n),
        }
    return out


@dataclass
class _Frame:
    """One rendered frame, kept while pairs still need it."""

    rendered: Any  # render.RenderedFrame at the image size
    image: np.ndarray  # the estimator's input (DIS: grey)


class RenderedDrivingDataset(TrajectoryDataset):
    """``flow=dis`` (any estimator): frames rendered from one persistent world per trajectory,
    flow estimated on them at the image size, resized to the model input, cached.

    Each trajectory gets a :class:`~mfg_lightning.scene.worlds.World` from ``(seed, sequence
    name, poses)``; a frame is rendered (:func:`~mfg_lightning.scene.render.render_frame`) at
    ``image_hw`` and its pairs get the exact flow from the same ray casts
    (:func:`~mfg_lightning.scene.render.exact_flow`) and the estimated flow. The sample's ``flow``
    is the estimate (valid where finite); ``exact_flow``, ``depth``, ``object_mask`` and
    ``object_flow`` are the ground truth at the model input. The flow quality (EPE and Fl per
    region, at the image size, against the exact flow) is computed with the estimate and kept
    in the cache beside it.

    Cache: ``<cache_dir>/synthetic_flow/<key>/<seq>/<src:06d>_<tgt:06d>.npz``, ``<key>`` a hash
    of everything that changes a pair (estimator and its settings, image and input size, seed,
    world config, the trajectory's poses, the renderer's source, library versions).
    :func:`prepare_pairs` (:meth:`precompute_flow` for this dataset alone) fills it, on every
    core; ``__getitem__`` computes a missing pair on its own.

    Args:
        flow: the estimator and the image size (``flow.height × flow.width``, default
            :data:`RENDER_SIZE`).
        world: :class:`~mfg_lightning.scene.worlds.WorldConfig` fields (None: its defaults).
        cache_dir: the user cache directory (``paths.cache_dir``).
        input_flow: the sample's ``flow``: ``"source"``, the estimate; ``"exact"``, the exact
            flow (both are in every cached pair: the cache key does not depend on it).
        memory: the process's sample-cache budget
            (:class:`~mfg_lightning.data.sample_cache.MemoryBudget`): the pairs read are kept
            in memory while it has room, so that later epochs read no file; None: none kept.
        args, kwargs: ``trajectories``, ``frames``, ``height``, ``width``, ``seed``, ``offsets``,
            ``name`` of :class:`TrajectoryDataset`.
    """

    def __init__(
        self,
        *args: Any,
        flow: EstimatedFlow,
        world: dict[str, Any] | None = None,
        cache_dir: str | Path | None = None,
        input_flow: str = "source",
        memory: MemoryBudget | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        if input_flow not in ("source", "exact"):
            raise ValueError(f"input_flow must be 'source' or 'exact', got {input_flow!r}")
        self.input_flow = input_flow
        # The memory tier only: the pairs' disk cache is self.cache.
        self.memory = SampleStore({}, memory) if memory is not None else None
        self.flow_source = flow
        self.estimator = flow.estimator
        self.image_hw = flow_render_size(flow, (self.height, self.width))
        self.image_intrinsics = kitti_like_intrinsics(*self.image_hw)
        self.world_fields = dict(world or {})
        self.world_config = world_config(self.world_fields)
        self._worlds: dict[str, Any] = {}
        self.span = max(abs(o) for o in self.offsets)
        if cache_dir is None:
            from mfg_lightning.flow.cache import default_cache_dir

            cache_dir = default_cache_dir()
        self.cache = FlowCache.create(cache_dir, self.cache_key(), namespace=self.cache_namespace)
        # What this object rendered and estimated (the tests count them; a cached run: 0).
        self.rendered_frames = 0
        self.estimated_pairs = 0

    #: The cache directory under ``paths.cache_dir`` (a subclass caching other arrays has its own)
    cache_namespace = "synthetic_flow"
    #: Whether preparation leaves a picture grid per sequence (:meth:`picture_path`)
    pictures = True

    def cache_key(self) -> dict[str, Any]:
        """Everything that changes a cached pair (hashed into the cache directory's name)."""
        worlds, render = _renderer()
        return {
            "format": _RENDER_CACHE_FORMAT,
            "flow": self.flow_source.key(),
            "image_hw": list(self.image_hw),
            "output_hw": [self.height, self.width],
            "seed": self.seed,
            "world": {k: self.world_fields[k] for k in sorted(self.world_fields)},
            "trajectories": {
                seq: hashlib.sha256(
                    np.ascontiguousarray(poses.double().numpy()).tobytes()
                ).hexdigest()[:16]
                for seq, poses in sorted(self.trajectories.items())
            },
            "renderer": source_digest(worlds, render),
            "torch": torch.__version__,
            "numpy": np.__version__,
        }

    # -- cache -------------------------------------------------------------------------------

    def pair_path(self, i: int) -> Path:
        seq, src, tgt = self.samples[i]
        return self.cache.root / seq / f"{src:06d}_{tgt:06d}.npz"

    def missing(self) -> list[int]:
        """Indices of the samples whose pair is not cached yet (stat calls only)."""
        return [i for i in range(len(self.samples)) if not self.pair_path(i).exists()]

    def _cached(self, i: int) -> dict[str, np.ndarray] | None:
        packed = self.cache.load_arrays(self.pair_path(i), ("floats", "bytes"))
        if packed is None or packed["floats"].shape != (self.height, self.width, 7):
            return None
        return _unpack(packed)

    # -- rendering and estimation ------------------------------------------------------------

    def world(self, seq: str) -> Any:
        """The persistent world of trajectory ``seq`` (generated on first use)."""
        if seq not in self._worlds:
            worlds, _ = _renderer()
            self._worlds[seq] = worlds.World.generate(
                self.trajectories[seq], seed=self.seed, name=seq, config=self.world_config
            )
        return self._worlds[seq]

    def render(self, seq: str, frame: int) -> _Frame:
        """Render frame ``frame`` of ``seq`` at the image size, with the estimator's input."""
        _, render = _renderer()
        rendered = render.render_frame(
            self.world(seq), frame, self.image_intrinsics, *self.image_hw
        )
        self.rendered_frames += 1
        rgb = np.ascontiguousarray(_numpy(rendered.rgb).transpose(1, 2, 0))
        return _Frame(rendered, self.estimator.prepare(rgb))

    def exact_pair(
        self, seq: str, src: int, tgt: int, a: _Frame
    ) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
        """The renderer's exact flow ``src → tgt`` at the image size, from the rendered source
        frame ``a``: its fields (:func:`mfg_lightning.scene.render.exact_flow`), the flow
        ``(H, W, 2)`` float32 in pixels (0 where unknown) and where it is known ``(H, W)`` bool
        (valid and finite)."""
        _, render = _renderer()
        exact = render.exact_flow(
            self.world(seq), src, tgt, self.image_intrinsics, *self.image_hw, source=a.rendered
        )
        flow = _hw2(exact["flow"])
        valid = _numpy(exact["flow_valid"]).astype(bool) & np.isfinite(flow).all(2)
        return exact, np.where(valid[..., None], flow, 0.0).astype(np.float32), valid

    def compute_pair(self, seq: str, src: int, tgt: int, a: _Frame, b: _Frame) -> dict:
        """Exact and estimated flow of ``src → tgt`` from the rendered frames ``a``, ``b``: the
        fields of a sample at the model input (``flow`` ``(h, w, 2)``, ``exact_flow``,
        ``object_flow``, ``depth`` ``(h, w)``, ``rgb`` ``(h, w, 3)``, ``object_mask``), the
        ``quality`` (:func:`flow_quality`) and ``nonfinite`` count at the image size, and the
        image-size fields under ``"full"`` (for pictures)."""
        exact, exact_flow, exact_valid = self.exact_pair(seq, src, tgt, a)
        est = np.asarray(self.estimator(a.image, b.image), dtype=np.float32)
        self.estimated_pairs += 1
        finite = np.isfinite(est).all(axis=2)
        est = np.where(finite[..., None], est, 0.0).astype(np.float32)
        region = _numpy(a.rendered.region)
        quality = flow_quality(est, exact_flow, exact_valid & finite, region)
        h, w = self.height, self.width
        flow, flow_ok = transforms.resize_flow(est, finite, h, w)
        exact_small, _ = transforms.resize_flow(exact_flow, exact_valid, h, w)
        mask = _numpy(exact["object_mask"]).astype(bool) & exact_valid
        object_flow = _hw2(exact["object_flow"])
        mask_small = transforms.resize_mask(mask, h, w, defined=exact_valid)
        object_small, _ = transforms.resize_flow(
            np.where(mask[..., None], object_flow, 0.0).astype(np.float32), mask, h, w, 0.0
        )
        rgb = np.ascontiguousarray(_numpy(a.rendered.rgb).transpose(1, 2, 0))
        return {
            "flow": np.where(flow_ok[..., None], flow, np.nan).astype(np.float32),
            "exact_flow": exact_small.astype(np.float32),
            "object_mask": mask_small,
            "object_flow": np.where(mask_small[..., None], object_small, 0.0).astype(np.float32),
            "depth": transforms.resize_depth(_numpy(exact["depth"]).astype(np.float32), h, w),
            "rgb": transforms.resize_rgb(rgb, h, w),
            "quality": quality,
            "nonfinite": np.int64((~finite).sum()),
            "full": {
                "frame": a.rendered,
                "exact": exact,
                "exact_flow": exact_flow,
                "exact_valid": exact_valid,
                "flow": est,
                "flow_valid": finite,
            },
        }

    def _store(self, i: int, pair: dict) -> dict[str, np.ndarray]:
        packed = {
            "floats": np.concatenate(
                [pair[k].reshape(self.height, self.width, n) for k, n in _FLOAT_FIELDS], axis=2
            ).astype(np.float32),
            "bytes": np.concatenate(
                [pair[k].reshape(self.height, self.width, n) for k, n in _BYTE_FIELDS], axis=2
            ).astype(np.uint8),
            "stats": _stats_of(pair),
        }
        self.cache.store_arrays(self.pair_path(i), packed)
        return _unpack(packed)

    def __getstate__(self) -> dict[str, Any]:
        # Worlds are rebuilt where they are needed (a worker renders its own sequences).
        return {**self.__dict__, "_worlds": {}}

    def _compute(self, indices: Sequence[int], bar: Any = None) -> dict[int, np.ndarray]:
        """Render, estimate and cache the pairs ``indices`` in sequence and frame order, each
        frame rendered once and kept while a later pair (up to the largest offset ahead) can
        use it; the middle pair of each sequence also leaves its picture grid
        (:meth:`picture_path`). Returns each pair's quality sums (:func:`_stats_of`), by
        index."""
        frames: dict[tuple[str, int], _Frame] = {}
        stats: dict[int, np.ndarray] = {}
        middle = {ix[len(ix) // 2]: seq for seq, ix in self.sequences().items()}
        for i in sorted(indices, key=lambda k: self.samples[k][:2]):
            seq, src, tgt = self.samples[i]
            for key in [k for k in frames if k[0] != seq or k[1] < src - self.span]:
                del frames[key]
            for f in (src, tgt):
                if (seq, f) not in frames:
                    frames[(seq, f)] = self.render(seq, f)
            pair = self.compute_pair(seq, src, tgt, frames[(seq, src)], frames[(seq, tgt)])
            self._store(i, pair)
            stats[i] = _stats_of(pair)
            if self.pictures and i in middle:
                self.cache.store(self.picture_path(seq), flow_picture(pair["full"]))
            if bar is not None:
                bar.update(1)
        return stats

    def precompute_flow(self, progress: bool = True, workers: int | None = 0) -> int:
        """Render, estimate and cache every pair not cached yet; return how many.

        :func:`prepare_pairs` on this dataset alone: with ``workers > 1`` (None: every usable
        core) the pairs are cut into contiguous chunks of frames shared among that many
        single-threaded processes; 0 or 1 computes them in this process.
        """
        return prepare_pairs([self], workers=workers, progress=progress)[0].pairs

    def picture_path(self, seq: str) -> Path:
        """Where the picture grid of ``seq`` is cached (``(H', W', 3)`` uint8 ``.npy``)."""
        return self.cache.root / f"picture-{seq}.npy"

    def picture(self, seq: str) -> np.ndarray:
        """The picture grid (:func:`flow_picture`) of the middle pair of ``seq``, at the image
        size (renders its two frames)."""
        indices = self.sequences()[seq]
        _, src, tgt = self.samples[indices[len(indices) // 2]]
        pair = self.compute_pair(seq, src, tgt, self.render(seq, src), self.render(seq, tgt))
        return flow_picture(pair["full"])

    def _pair_stats(
        self, i: int, known: Mapping[tuple[str, int, int], np.ndarray] | None = None
    ) -> np.ndarray:
        """Pair ``i``'s quality sums (:func:`flow_quality`, then its non-finite pixels): from
        ``known`` (what :func:`prepare_pairs` returned, keyed by sample), else from its cached
        file."""
        found = None if known is None else known.get(self.samples[i])
        if found is not None:
            return found
        arrays = self.cache.load_arrays(self.pair_path(i), ("stats",))
        if arrays is None:
            raise FileNotFoundError(f"{self.pair_path(i)}: pair not cached yet")
        return arrays["stats"]

    def quality(
        self, known: Mapping[tuple[str, int, int], np.ndarray] | None = None
    ) -> dict[str, Any]:
        """The flow quality of this split (pooled over its pairs) and its non-finite pixels.

        Args:
            known: the quality sums of pairs just computed (:attr:`PreparedPairs.stats`, keyed
                by ``(sequence, source, target)``); every other pair's are read from the cache
                (it must be cached).
        """
        stats = np.zeros((len(QUALITY_REGIONS), 3))
        nonfinite = 0
        for i in range(len(self.samples)):
            pair = self._pair_stats(i, known)
            stats += pair[:-1].reshape(stats.shape)
            nonfinite += int(pair[-1])
        return {"regions": summarize_quality(stats), "nonfinite_pixels": nonfinite}

    def quality_by_offset(
        self, known: Mapping[tuple[str, int, int], np.ndarray] | None = None
    ) -> dict[str, dict[str, Any]]:
        """The flow quality pooled per frame offset (target − source):
        ``{"-2": {"regions": ..., "pairs": n}, "-1": ..., "1": ..., "2": ...}`` (the estimate's
        error grows with the motion it has to find, which the offset scales); ``known`` as in
        :meth:`quality`."""
        stats: dict[int, np.ndarray] = {}
        pairs: dict[int, int] = {}
        for i, (_, src, tgt) in enumerate(self.samples):
            off = int(tgt) - int(src)
            pooled = stats.setdefault(off, np.zeros((len(QUALITY_REGIONS), 3)))
            pooled += self._pair_stats(i, known)[:-1].reshape(pooled.shape)
            pairs[off] = pairs.get(off, 0) + 1
        return {
            str(o): {"regions": summarize_quality(stats[o]), "pairs": pairs[o]}
            for o in sorted(stats)
        }

    # -- samples -----------------------------------------------------------------------------

    def _pair_arrays(self, i: int) -> dict[str, np.ndarray]:
        """The cached fields of pair ``i`` (:func:`_unpack`): from memory, else read from the
        disk cache, else rendered, estimated and cached; kept in memory while the budget has
        room (later epochs then read no file)."""

        def load() -> dict[str, np.ndarray]:
            arrays = self._cached(i)
            if arrays is None:
                seq, src, tgt = self.samples[i]
                a, b = self.render(seq, src), self.render(seq, tgt)
                arrays = self._store(i, self.compute_pair(seq, src, tgt, a, b))
            return arrays

        if self.memory is None:
            return load()
        return self.memory.fetch(self.samples[i], "", load)

    def __getitem__(self, i: int) -> dict:
        self._check_index(i)
        seq, src, tgt = self.samples[i]
        arrays = self._pair_arrays(i)
        key = "exact_flow" if self.input_flow == "exact" else "flow"
        flow = torch.from_numpy(np.ascontiguousarray(arrays[key].transpose(2, 0, 1)))
        flow, valid, _ = sanitize_flow(flow, torch.ones(flow.shape[1:], dtype=torch.bool))
        sample = {
            "flow": flow,
            "flow_valid": valid,
            "depth": torch.from_numpy(np.ascontiguousarray(arrays["depth"])),
            # (a copy: the arrays may be the memory tier's own)
            "object_mask": torch.from_numpy(arrays["object_mask"].copy()),
            "object_flow": transforms.flow_to_tensor(arrays["object_flow"]),
            "exact_flow": transforms.flow_to_tensor(arrays["exact_flow"]),
            "rgb": torch.from_numpy(np.ascontiguousarray(arrays["rgb"].transpose(2, 0, 1))),
        }
        sample.update(self._identity(seq, src, tgt, self._pose(seq, src, tgt)))
        return sample


def _stats_of(pair: dict) -> np.ndarray:
    """A pair's quality sums as cached (``stats``): :func:`flow_quality`'s ``(R, 3)`` flattened,
    then its non-finite pixel count; ``(3 R + 1,)`` float64."""
    return np.append(pair["quality"].ravel(), float(pair["nonfinite"]))


# -- preparation: every missing pair of several datasets, in chunks, on every core ------------

#: Chunks per process, at least, that :func:`prepare_pairs` cuts the pairs into: equal chunks
#: handed out one at a time leave a process idle at the end for at most about one chunk, a
#: quarter of its share.
CHUNKS_PER_PROCESS = 4

#: The least pairs of a chunk (:func:`prepare_pairs`' default). A chunk renders the frames at its
#: border that its neighbour renders too (up to the largest offset), and a spawned process
#: imports torch and OpenCV before its first pair (a few seconds, some 20 pairs at 192 × 512):
#: work below two chunks stays in the calling process.
MIN_CHUNK_PAIRS = 32


@dataclass
class PreparedPairs:
    """What :func:`prepare_pairs` computed for one dataset.

    Attributes:
        pairs: pairs rendered, estimated and cached (0: all were cached).
        frames: frames rendered; a frame at the border of two chunks is rendered by both.
        worlds: worlds generated: once per sequence in this process, or once per sequence and
            worker process that computed a chunk of it.
        processes: the worker processes the call used (0: the calling process alone).
        stats: each computed pair's quality sums (:func:`_stats_of`), by ``(sequence, source,
            target)``: what :meth:`RenderedDrivingDataset.quality` reads from the cache
            otherwise.
    """

    pairs: int = 0
    frames: int = 0
    worlds: int = 0
    processes: int = 0
    stats: dict[tuple[str, int, int], np.ndarray] = field(default_factory=dict)


def plan_chunks(
    datasets: Sequence[RenderedDrivingDataset],
    todo: Sequence[Sequence[int]],
    processes: int,
    min_pairs: int = MIN_CHUNK_PAIRS,
) -> list[tuple[int, list[int]]]:
    """Cut the pairs ``todo[d]`` of every ``datasets[d]`` into contiguous chunks of frames.

    Every sequence is cut apart from the others into ``len // size`` near-equal runs of
    consecutive source frames (one run if it has fewer than ``size`` pairs), ``size`` being
    ``max(min_pairs, total / (CHUNKS_PER_PROCESS × processes))``. A cut never splits the pairs
    of one source frame (its offsets), which share that frame's rendering.

    Returns:
        ``(d, indices)`` per chunk, in dataset, sequence and frame order: the order in which
        :func:`prepare_pairs` hands them out, so that a worker meets each sequence once.
    """
    total = sum(len(ix) for ix in todo)
    size = max(1, min_pairs, math.ceil(total / (CHUNKS_PER_PROCESS * max(1, processes))))
    chunks: list[tuple[int, list[int]]] = []
    for d, (ds, indices) in enumerate(zip(datasets, todo, strict=True)):
        by_seq: dict[str, list[int]] = {}
        for i in sorted(indices, key=lambda k: ds.samples[k][:2]):
            by_seq.setdefault(ds.samples[i][0], []).append(i)
        for ix in by_seq.values():
            n = max(1, len(ix) // size)
            cuts = [0]
            for c in range(1, n):
                at = max(round(c * len(ix) / n), cuts[-1] + 1)
                while at < len(ix) and ds.samples[ix[at]][1] == ds.samples[ix[at - 1]][1]:
                    at += 1
                if at < len(ix):
                    cuts.append(at)
            cuts.append(len(ix))
            chunks.extend((d, ix[a:b]) for a, b in pairwise(cuts))
    return chunks


def _compute_chunk(
    dataset: RenderedDrivingDataset, indices: Sequence[int], bar: Any = None
) -> tuple[dict[int, np.ndarray], int, int]:
    """:meth:`RenderedDrivingDataset._compute` on ``indices``: the pairs' quality sums, the
    frames rendered and the worlds generated (whichever process it runs in)."""
    frames, worlds = dataset.rendered_frames, set(dataset._worlds)
    stats = dataset._compute(indices, bar)
    return stats, dataset.rendered_frames - frames, len(set(dataset._worlds) - worlds)


#: A preparation worker's datasets (:func:`_start_worker`), indexed as the caller's list.
_WORKER_DATASETS: list[RenderedDrivingDataset] = []


def _start_worker(datasets: list[RenderedDrivingDataset]) -> None:
    """A preparation worker's initializer: keep the datasets, received once per process."""
    _WORKER_DATASETS[:] = datasets


def _prepare_chunk(d: int, indices: list[int]) -> tuple[np.ndarray, int, int]:
    """One chunk of dataset ``d`` in a preparation worker: its pairs' quality sums
    (``(len(indices), 3 R + 1)``, in the order of ``indices``), frames rendered, worlds
    generated. The worker's dataset keeps the world of the chunk's sequence for its next chunk
    and drops the others': chunks come in sequence order (:func:`plan_chunks`), so a dropped
    world is not needed again in this process."""
    dataset = _WORKER_DATASETS[d]
    seq = dataset.samples[indices[0]][0]
    for other in [s for s in dataset._worlds if s != seq]:
        del dataset._worlds[other]
    stats, frames, worlds = _compute_chunk(dataset, indices)
    return np.stack([stats[i] for i in indices]), frames, worlds


def prepare_pairs(
    datasets: Sequence[RenderedDrivingDataset],
    workers: int | None = None,
    min_chunk_pairs: int = MIN_CHUNK_PAIRS,
    progress: bool = True,
) -> list[PreparedPairs]:
    """Render, estimate and cache every missing pair of every dataset, on every core.

    The missing pairs of all the datasets (e.g. a data module's train + validation pairs and
    its test pairs) are cut into contiguous chunks of frames (:func:`plan_chunks`) that go into
    one pool of single-threaded spawned processes (:func:`~mfg_lightning.core.processes.
    single_thread_pool`): a split of two long sequences keeps every core busy, and no process
    runs more threads than its core. Each worker receives the datasets once and generates a
    sequence's world once. Where there are fewer than ``2 × min_chunk_pairs`` pairs or two
    chunks, or ``workers`` is 0 or 1, the pairs are computed in this process, each frame
    rendered once.

    The cached files are the same whichever way (the renderer and the estimator are
    deterministic, per frame and per pair; ``tests/test_rendered_flow.py`` compares them).

    Args:
        datasets: the datasets to fill.
        workers: processes at most (None: every usable core,
            :func:`~mfg_lightning.core.machine.usable_cores`).
        min_chunk_pairs: the least pairs of a chunk (:data:`MIN_CHUNK_PAIRS`).
        progress: show a progress bar (advancing per finished chunk).

    Returns:
        What was computed for each dataset, in order, the pairs' quality sums included.
    """
    from tqdm.auto import tqdm

    from mfg_lightning.core.machine import usable_cores

    todo = [ds.missing() for ds in datasets]
    results = [PreparedPairs() for _ in datasets]
    total = sum(len(ix) for ix in todo)
    if not total:
        return results
    workers = usable_cores() if workers is None else int(workers)
    chunks = plan_chunks(datasets, todo, workers, min_chunk_pairs) if workers > 1 else []
    # (no more processes than chunks, nor than chunks of the least size: a small job would
    # spend longer starting processes than computing)
    processes = min(workers, len(chunks), total // max(1, min_chunk_pairs))
    names = ", ".join(ds.name for ds, ix in zip(datasets, todo, strict=True) if ix)
    estimators = sorted({ds.estimator.name for ds in datasets})
    bar = tqdm(
        total=total,
        desc=f"render + {'/'.join(estimators)} flow ({names})",
        unit="pair",
        disable=not progress,
    )

    def record(d: int, indices: Sequence[int], stats: np.ndarray, frames: int, worlds: int):
        ds, result = datasets[d], results[d]
        result.pairs += len(indices)
        result.frames += frames
        result.worlds += worlds
        result.stats.update((ds.samples[i], s) for i, s in zip(indices, stats, strict=True))

    try:
        if processes <= 1:
            for d, (ds, indices) in enumerate(zip(datasets, todo, strict=True)):
                if indices:
                    stats, frames, worlds = _compute_chunk(ds, indices, bar)
                    record(d, list(stats), list(stats.values()), frames, worlds)
        else:
            from concurrent.futures import as_completed

            from mfg_lightning.core.processes import single_thread_pool

            with single_thread_pool(processes, _start_worker, (list(datasets),)) as pool:
                jobs = {pool.submit(_prepare_chunk, d, ix): (d, ix) for d, ix in chunks}
                for job in as_completed(jobs):
                    d, indices = jobs[job]
                    stats, frames, worlds = job.result()
                    record(d, indices, stats, frames, worlds)
                    # the dataset's own counters, of work done in the workers (the log reads them)
                    datasets[d].rendered_frames += frames
                    datasets[d].estimated_pairs += len(indices)
                    bar.update(len(indices))
            for result, indices in zip(results, todo, strict=True):
                result.processes = processes if indices else 0
    finally:
        bar.close()
    return results


def _unpack(packed: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The named fields of a cached pair (views of its two packed arrays)."""
    out: dict[str, np.ndarray] = {}
    for array, fields in ((packed["floats"], _FLOAT_FIELDS), (packed["bytes"], _BYTE_FIELDS)):
        start = 0
        for name, n in fields:
            part = array[..., start : start + n]
            out[name] = part if n > 1 else part[..., 0]
            start += n
    out["object_mask"] = out["object_mask"].astype(bool)
    return out


def flow_render_size(flow: EstimatedFlow, model_hw: tuple[int, int]) -> tuple[int, int]:
    """The image size of estimated synthetic flow, refused (naming ``flow.height``/
    ``flow.width``) when the renderer cannot take it or the flow cannot be resized down to the
    model input from it (a side below ``dataset.height``/``dataset.width``)."""
    hw = flow.image_hw(RENDER_SIZE)
    _, render = _renderer()
    try:
        render.check_render_size(*hw)
    except ValueError as err:
        raise ValueError(f"flow.height={hw[0]}, flow.width={hw[1]}: {err}") from None
    for key, size, need in zip(("height", "width"), hw, model_hw, strict=True):
        if size < need:
            raise ValueError(
                f"flow.{key}={size}: the render size {hw[0]} × {hw[1]} is smaller than the model "
                f"input {model_hw[0]} × {model_hw[1]} (dataset.height × dataset.width); render at "
                "least at the input size (default 192 × 512)"
            )
    return hw


def world_config(fields: dict[str, Any]) -> Any:
    """``dataset.world`` → :class:`~mfg_lightning.scene.worlds.WorldConfig` (None: defaults)."""
    if not fields:
        return None
    worlds, _ = _renderer()
    import dataclasses

    known = {f.name for f in dataclasses.fields(worlds.WorldConfig)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise ValueError(f"unknown dataset.world setting(s) {unknown}; known: {sorted(known)}")
    return worlds.WorldConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}
    )


def quality_line(regions: dict[str, dict[str, float | None]]) -> str:
    """``road EPE 1.23 px Fl 4.5 % · …`` for the log."""

    def one(name: str, q: dict[str, float | None]) -> str:
        if q["epe"] is None:
            return f"{name} –"
        return f"{name} EPE {q['epe']:.2f} px Fl {q['fl']:.1f} %"

    return " · ".join(one(k, v) for k, v in regions.items())


#: End-point errors at or above this many pixels get the brightest colour of the EPE panel.
PICTURE_MAX_EPE = 10.0


def flow_picture(full: dict[str, Any]) -> np.ndarray:
    """The picture grid of one rendered pair at the image size, with the renderer's panels
    (:func:`~mfg_lightning.pictures.rendered_frames.frame_panels`: RGB, exact flow, regions, object
    mask)
    and two more: the estimated flow in the exact flow's colour scale and its end-point error
    against it (magma, 0 to :data:`PICTURE_MAX_EPE` px; black where the exact flow is
    unknown).

    Args:
        full: the ``"full"`` entry of :meth:`RenderedDrivingDataset.compute_pair`.

    Returns:
        ``(H', W', 3)`` uint8.
    """
    from matplotlib import colormaps

    from mfg_lightning.pictures.colours import flow_to_rgb
    from mfg_lightning.pictures.rendered_frames import frame_panels, picture_grid

    valid = full["exact_valid"]
    magnitude = np.linalg.norm(full["exact_flow"], axis=2)[valid]
    max_flow = float(magnitude.max()) if magnitude.size else 1.0
    estimated = flow_to_rgb(np.moveaxis(full["flow"], 2, 0), max_flow)
    estimated[~full["flow_valid"]] = 0
    epe = np.linalg.norm(full["flow"] - full["exact_flow"], axis=2)
    error = (colormaps["magma"](np.clip(epe / PICTURE_MAX_EPE, 0, 1))[..., :3] * 255).astype(
        np.uint8
    )
    error[~(valid & full["flow_valid"])] = 0
    shown = valid & full["flow_valid"]
    mean = float(epe[shown].mean()) if shown.any() else float("nan")
    panels = frame_panels(
        full["frame"],
        full["exact"],
        extra=[
            ("estimated flow (same colours)", estimated),
            (f"end-point error (0-{PICTURE_MAX_EPE:g} px, mean {mean:.2f})", error),
        ],
        max_flow=max_flow,
    )
    return picture_grid([panels])
