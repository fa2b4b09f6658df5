"""Preparation of ``flow=dis``'s rendered pairs: every missing pair of several datasets
(:class:`~mfg_lightning.data.rendered.RenderedDrivingDataset` and its subclasses) rendered,
estimated and cached in contiguous chunks of frames, on every core, by one pool of
single-threaded spawned processes (:func:`prepare_pairs`, :func:`plan_chunks`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any, Protocol

import numpy as np


class PreparableDataset(Protocol):
    """What :func:`prepare_pairs` uses of a dataset
    (:class:`~mfg_lightning.data.rendered.RenderedDrivingDataset`): its pairs, the ones not
    cached yet, the computation of some of them and its counters."""

    name: str
    #: ``(sequence, source, target)`` per sample, sorted by sequence then source frame.
    samples: list[tuple[str, int, int]]
    #: The flow estimator (its ``name`` labels the progress bar).
    estimator: Any
    #: Frames rendered and pairs estimated by this object (or, after :func:`prepare_pairs`,
    #: for it in the workers).
    rendered_frames: int
    estimated_pairs: int
    #: The persistent world of each sequence generated so far, by sequence name.
    _worlds: dict[str, Any]

    def missing(self) -> list[int]:
        """Indices of the samples whose pair is not cached yet."""

    def _compute(self, indices: Sequence[int], bar: Any = None) -> dict[int, np.ndarray]:
        """Render, estimate and cache the pairs ``indices``; each pair's quality sums by index
        (:func:`~mfg_lightning.metrics.flow_quality.pair_stats`)."""


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
        stats: each computed pair's quality sums
            (:func:`~mfg_lightning.metrics.flow_quality.pair_stats`), by ``(sequence, source,
            target)``: what :meth:`~mfg_lightning.data.rendered.RenderedDrivingDataset.quality`
            reads from the cache otherwise.
    """

    pairs: int = 0
    frames: int = 0
    worlds: int = 0
    processes: int = 0
    stats: dict[tuple[str, int, int], np.ndarray] = field(default_factory=dict)


def plan_chunks(
    datasets: Sequence[PreparableDataset],
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
    dataset: PreparableDataset, indices: Sequence[int], bar: Any = None
) -> tuple[dict[int, np.ndarray], int, int]:
    """:meth:`~mfg_lightning.data.rendered.RenderedDrivingDataset._compute` on ``indices``: the
    pairs' quality sums, the frames rendered and the worlds generated (whichever process it runs
    in)."""
    frames, worlds = dataset.rendered_frames, set(dataset._worlds)
    stats = dataset._compute(indices, bar)
    return stats, dataset.rendered_frames - frames, len(set(dataset._worlds) - worlds)


#: A preparation worker's datasets (:func:`_start_worker`), indexed as the caller's list.
_WORKER_DATASETS: list[PreparableDataset] = []


def _start_worker(datasets: list[PreparableDataset]) -> None:
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
    datasets: Sequence[PreparableDataset],
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
