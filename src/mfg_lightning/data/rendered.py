"""Samples of ``flow=dis`` on the synthetic worlds: frames rendered from one persistent world per
trajectory (:mod:`mfg_lightning.scene`), flow estimated on them and cached, the exact flow and
the ground truth kept beside the estimate, and the estimate's quality per image region
(computed by :mod:`mfg_lightning.metrics.flow_quality`). Every missing pair of several datasets
is prepared on every core by :mod:`mfg_lightning.data.rendered_preparation`; the picture of a
pair is :func:`mfg_lightning.pictures.rendered_frames.flow_picture`."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning.data import transforms
from mfg_lightning.data.driving import TrajectoryDataset
from mfg_lightning.data.rendered_preparation import prepare_pairs
from mfg_lightning.data.rendered_worlds import (
    crossing_config,
    crossing_module,
    generate_world,
    world_config,
)
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.data.sample_cache import MemoryBudget, SampleStore, source_digest
from mfg_lightning.flow.estimators import (
    EstimatedFlow,
    FlowCache,
)
from mfg_lightning.metrics.flow_quality import (
    OCCLUDED,
    OUT_OF_FRAME,
    VISIBLE,
    flow_quality,
    pair_stats,
    pooled_quality,
    pooled_quality_by_offset,
    visibility_codes,
)
from mfg_lightning.pictures.rendered_frames import flow_picture
from mfg_lightning.scene.camera import kitti_like_intrinsics

#: The render size of ``flow=dis`` when ``flow.height``/``flow.width`` are unset: the released
#: code's image size (its flow, the model input, is a quarter of it).
RENDER_SIZE = (192, 512)


# Bump when the arrays cached per pair change, so old caches are not misread. 3: "stats" holds
# the quality on the non-occluded pixels beside all pixels, and the hidden pixel counts.
_RENDER_CACHE_FORMAT = 3


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
# plus "stats": (PAIR_STATS_SIZE,) float64, the quality (EPE sum, Fl outliers, pixels per set of
# pixels, noc and all, and region, at the image size), the occluded and out-of-frame pixel
# counts and the number of non-finite estimated pixels
# (mfg_lightning.metrics.flow_quality.pair_stats).


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
    in the cache beside it, on the non-occluded pixels and on all pixels
    (:func:`~mfg_lightning.metrics.flow_quality.flow_quality`: the renderer marks the pixels
    whose point leaves the target frame or is hidden in it). The marks change no sample: the
    exact flow of a hidden pixel is known and stays in ``exact_flow`` and ``flow_valid``.

    Cache: ``<cache_dir>/synthetic_flow/<key>/<seq>/<src:06d>_<tgt:06d>.npz``, ``<key>`` a hash
    of everything that changes a pair (estimator and its settings, image and input size, seed,
    world config, the trajectory's poses, the renderer's source, library versions).
    :func:`~mfg_lightning.data.rendered_preparation.prepare_pairs` (:meth:`precompute_flow` for
    this dataset alone) fills it, on every core; ``__getitem__`` computes a missing pair on its
    own.

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
        # plain lists: a range given on the command line arrives as a ListConfig, which the
        # cache key (JSON) cannot hold
        self.world_fields = {
            k: [*v] if isinstance(v, Sequence) and not isinstance(v, str) else v
            for k, v in (world or {}).items()
        }
        self.world_config = world_config(self.world_fields)
        self.crossing = crossing_config(self.world_fields)
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
            # the crossings' module only where there are crossings: a world without them does
            # not depend on it
            "renderer": source_digest(worlds, render, *crossing_module(self.crossing)),
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
            self._worlds[seq] = generate_world(
                self.trajectories[seq], self.seed, seq, self.world_config, self.crossing
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
        self, seq: str, src: int, tgt: int, a: _Frame, b: _Frame
    ) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray]:
        """The renderer's exact flow ``src → tgt`` at the image size, from the rendered source
        and target frames ``a``, ``b``: its fields
        (:func:`mfg_lightning.scene.render.exact_flow`), the flow ``(H, W, 2)`` float32 in
        pixels (0 where unknown), where it is known ``(H, W)`` bool (valid and finite), and
        every pixel's visibility code ``(H, W)`` uint8
        (:func:`~mfg_lightning.metrics.flow_quality.visibility_codes`: unknown, visible,
        occluded in ``b`` or out of its frame)."""
        _, render = _renderer()
        exact = render.exact_flow(
            self.world(seq), src, tgt, self.image_intrinsics, *self.image_hw,
            source=a.rendered, target=b.rendered,
        )  # fmt: skip
        flow = _hw2(exact["flow"])
        valid = _numpy(exact["flow_valid"]).astype(bool) & np.isfinite(flow).all(2)
        codes = visibility_codes(valid, _numpy(exact["out_of_frame"]), _numpy(exact["occluded"]))
        return exact, np.where(valid[..., None], flow, 0.0).astype(np.float32), valid, codes

    def compute_pair(self, seq: str, src: int, tgt: int, a: _Frame, b: _Frame) -> dict:
        """Exact and estimated flow of ``src → tgt`` from the rendered frames ``a``, ``b``: the
        fields of a sample at the model input (``flow`` ``(h, w, 2)``, ``exact_flow``,
        ``object_flow``, ``depth`` ``(h, w)``, ``rgb`` ``(h, w, 3)``, ``object_mask``), the
        ``quality`` (:func:`~mfg_lightning.metrics.flow_quality.flow_quality`, noc and all),
        ``nonfinite``, ``occluded`` and ``out_of_frame`` counts at the image size, and the
        image-size fields under ``"full"`` (for pictures)."""
        exact, exact_flow, exact_valid, visibility = self.exact_pair(seq, src, tgt, a, b)
        est = np.asarray(self.estimator(a.image, b.image), dtype=np.float32)
        self.estimated_pairs += 1
        finite = np.isfinite(est).all(axis=2)
        est = np.where(finite[..., None], est, 0.0).astype(np.float32)
        region = _numpy(a.rendered.region)
        quality = flow_quality(
            est, exact_flow, exact_valid & finite, region, noc=visibility == VISIBLE
        )
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
            "occluded": np.int64((visibility == OCCLUDED).sum()),
            "out_of_frame": np.int64((visibility == OUT_OF_FRAME).sum()),
            "full": {
                "frame": a.rendered,
                "exact": exact,
                "exact_flow": exact_flow,
                "exact_valid": exact_valid,
                "visibility": visibility,
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
            "stats": _stats(pair),
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
        (:meth:`picture_path`). Returns each pair's quality sums
        (:func:`~mfg_lightning.metrics.flow_quality.pair_stats`), by index."""
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
            stats[i] = _stats(pair)
            if self.pictures and i in middle:
                self.cache.store(self.picture_path(seq), flow_picture(pair["full"]))
            if bar is not None:
                bar.update(1)
        return stats

    def precompute_flow(self, progress: bool = True, workers: int | None = 0) -> int:
        """Render, estimate and cache every pair not cached yet; return how many.

        :func:`~mfg_lightning.data.rendered_preparation.prepare_pairs` on this dataset alone:
        with ``workers > 1`` (None: every usable core) the pairs are cut into contiguous chunks
        of frames shared among that many single-threaded processes; 0 or 1 computes them in this
        process.
        """
        return prepare_pairs([self], workers=workers, progress=progress)[0].pairs

    def picture_path(self, seq: str) -> Path:
        """Where the picture grid of ``seq`` is cached (``(H', W', 3)`` uint8 ``.npy``)."""
        return self.cache.root / f"picture-{seq}.npy"

    def picture(self, seq: str) -> np.ndarray:
        """The picture grid (:func:`~mfg_lightning.pictures.rendered_frames.flow_picture`) of
        the middle pair of ``seq``, at the image size (renders its two frames)."""
        indices = self.sequences()[seq]
        _, src, tgt = self.samples[indices[len(indices) // 2]]
        pair = self.compute_pair(seq, src, tgt, self.render(seq, src), self.render(seq, tgt))
        return flow_picture(pair["full"])

    def _pair_stats(
        self, i: int, known: Mapping[tuple[str, int, int], np.ndarray] | None = None
    ) -> np.ndarray:
        """Pair ``i``'s quality sums (:func:`~mfg_lightning.metrics.flow_quality.pair_stats`:
        :func:`~mfg_lightning.metrics.flow_quality.flow_quality`, then its non-finite pixels):
        from ``known`` (what :func:`~mfg_lightning.data.rendered_preparation.prepare_pairs`
        returned, keyed by sample), else from its cached file."""
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
        """The flow quality of this split (pooled over its pairs), by region, on its
        non-occluded pixels (``regions_noc``) and on all (``regions``), with its occluded,
        out-of-frame and non-finite pixel counts.

        Args:
            known: the quality sums of pairs just computed
                (:attr:`~mfg_lightning.data.rendered_preparation.PreparedPairs.stats`, keyed by
                ``(sequence, source, target)``); every other pair's are read from the cache (it
                must be cached).

        Returns:
            :func:`~mfg_lightning.metrics.flow_quality.pooled_quality` of its pairs.
        """
        return pooled_quality(self._pair_stats(i, known) for i in range(len(self.samples)))

    def quality_by_offset(
        self, known: Mapping[tuple[str, int, int], np.ndarray] | None = None
    ) -> dict[str, dict[str, Any]]:
        """The flow quality pooled per frame offset (target − source):
        ``{"-2": {"regions": ..., "regions_noc": ..., "pairs": n}, ...}`` (the estimate's
        error grows with the motion it has to find, which the offset scales); ``known`` as in
        :meth:`quality` (:func:`~mfg_lightning.metrics.flow_quality.pooled_quality_by_offset`)."""
        return pooled_quality_by_offset(
            (int(tgt) - int(src), self._pair_stats(i, known))
            for i, (_, src, tgt) in enumerate(self.samples)
        )

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


def _stats(pair: dict) -> np.ndarray:
    """A computed pair's quality sums and pixel counts
    (:func:`~mfg_lightning.metrics.flow_quality.pair_stats`)."""
    return pair_stats(pair["quality"], pair["nonfinite"], pair["occluded"], pair["out_of_frame"])


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
