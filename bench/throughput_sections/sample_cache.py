"""The sample cache (``dataset.sample_cache``, ``dataset.prefetch``): the training loader alone
and training on it in the first epoch (samples computed: no cache, the cache with each prefetch,
the disk tier of an earlier run) and the later ones (read back), against training on the same
batches held in memory. A marked section of throughput.md of its own: ``--sample-cache`` reruns
only it."""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from _common import NOISY, fmt, markdown_table, ratio_cell

from .measure import (
    UNCACHED_SAMPLES,
    base_overrides,
    datamodule,
    throughput_report,
    with_overrides,
)
from .training import InMemory, training_epochs

#: The marker of the sample cache's block in throughput.md (:meth:`Report.write_section`).
SAMPLE_CACHE_MARKER = "sample-cache"
#: The loaders the sample cache section compares: label → (dataset overrides, whether an
#: earlier run filled the disk tier first).
CACHE_LOADERS: dict[str, tuple[list[str], bool]] = {
    "no cache: every sample generated when the loader asks": (UNCACHED_SAMPLES, False),
    "cache, `prefetch=none`": (["dataset.prefetch=none"], False),
    "cache, `prefetch=thread` (the default)": (["dataset.prefetch=thread"], False),
    "cache, `prefetch=worker`": (["dataset.prefetch=worker"], False),
    "cache on disk only, filled by an earlier run (`memory_mb=0`)": (
        ["dataset.sample_cache.memory_mb=0", "dataset.prefetch=none"],
        True,
    ),
}


def cache_datamodule(
    base: list[str], extra: list[str], cache_dir: Path, frames: int, batch: int
) -> Any:
    """The synthetic DataModule of ``base`` + ``extra`` on 2 training trajectories of
    ``frames`` frames, batch ``batch``, its sample cache's disk tier in ``cache_dir``."""
    size = [
        "dataset.train_sequences=2",
        f"dataset.sequence_length={frames}",
        f"dataset.batch_size={batch}",
        f"dataset.cache_dir={cache_dir}",
    ]
    return datamodule(with_overrides(base, [*size, *extra]))


def served(dm: Any, before: dict[str, int] | None = None) -> dict[str, int]:
    """How this process's training dataset has served its samples (memory, disk, computed:
    :attr:`~mfg_lightning.data.sample_cache.SampleStore.counts`), less ``before``; empty without
    a cache. A loader worker's own counts are not seen here."""
    store = getattr(dm.dataset("train"), "store", None)
    counts = {} if store is None else dict(store.counts)
    counts.pop("prefetched", None)
    return {k: v - (before or {}).get(k, 0) for k, v in counts.items()}


def served_text(counts: dict[str, int], workers: bool) -> str:
    """A table cell for :func:`served`'s counts."""
    if workers:
        return "(in the worker)"
    if not counts:
        return "computed (no cache)"
    return ", ".join(f"{k} {v}" for k, v in counts.items() if v) or "nothing"


def loader_epochs(dm: Any) -> tuple[float, float, dict[str, int]]:
    """Samples per second of iterating ``dm``'s training loader through its first epoch (after
    its first batch: a worker's start-up) and its second, and how epoch 2's samples were served
    (:func:`served`)."""
    loader = dm.train_dataloader()
    rates, counts = [], served(dm)
    for epoch in (0, 1):
        loader.order.set_epoch(epoch)  # what Lightning does at the start of each epoch
        batches = iter(loader)
        if epoch == 0:
            next(batches)
        else:
            counts = served(dm)
        start, n = time.perf_counter(), 0
        for batch in batches:
            n += batch["flow"].shape[0]
        rates.append(n / (time.perf_counter() - start))
    epoch2 = served(dm, counts)
    dm.teardown("fit")
    return rates[0], rates[1], epoch2


def loader_row(
    base: list[str],
    extra: list[str],
    prefilled: bool,
    frames: int,
    batch: int,
    warmup: int,
    epochs: int,
) -> tuple[list[float], str, int]:
    """One loader of :data:`CACHE_LOADERS` (``extra``, ``prefilled``), each measurement on an
    empty cache: the loader alone in epochs 1 and 2 (:func:`loader_epochs`), training on it in
    epoch 1 and the later ones (:func:`~.training.training_epochs`); where epoch 2's samples came
    from (:func:`served_text`); the training samples per epoch."""
    row: list[float] = []
    for measure in ("loader", "training"):
        with tempfile.TemporaryDirectory() as cache:
            if prefilled:  # an earlier run's first epoch
                loader_epochs(cache_datamodule(base, [], Path(cache), frames, batch))
            dm = cache_datamodule(base, extra, Path(cache), frames, batch)
            n_train = len(dm.dataset("train"))
            if measure == "loader":
                *loader_rates, counts = loader_epochs(dm)
                row += loader_rates
                source = served_text(
                    counts, dm.num_workers > 0 or "dataset.prefetch=worker" in extra
                )
            else:
                row += training_epochs(base, dm, warmup, epochs)
    return row, source, n_train


def table_rows(
    rates: dict[str, list[tuple[float, ...]]],
    held: list[tuple[float, float]],
    sources: dict[str, str],
) -> list[list[str]]:
    """The section's table: per loader the medians of its repeats (:func:`loader_row`'s rates,
    then the in-memory pair's), the share of the time waiting on data and the ratio to memory;
    the batches held in memory last."""
    rows = []
    for label, runs in rates.items():
        loader1, loader2, train1, train2 = (statistics.median(r[k] for r in runs) for k in range(4))
        pairs1 = [r[2] / r[4] for r in runs]
        pairs2 = [r[3] / r[5] for r in runs]
        rows.append(
            [label, fmt(loader1, 0), fmt(loader2, 0), sources[label], fmt(train1, 1),
             f"{100 * (1 - statistics.median(pairs1)):.0f} %", fmt(train2, 1),
             f"{100 * (1 - statistics.median(pairs2)):.0f} %", ratio_cell(pairs2)]
        )  # fmt: skip
    mem1, mem2 = (statistics.median(r[k] for r in held) for k in range(2))
    rows.append(
        ["the same batches, collated once, in memory", "-", "-", "-", fmt(mem1, 1), "0 %",
         fmt(mem2, 1), "0 %", "1"]
    )  # fmt: skip
    return rows


def section(args: argparse.Namespace, cfg: Any) -> Path:
    """Every loader of :data:`CACHE_LOADERS` alone and under training, each beside training on
    the same batches held in memory; written as its own section of throughput.md (the rest
    kept). The quick start without and with the cache is :mod:`.quick_start`'s."""
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    # The dataset's own cache settings underneath each row: base_overrides turns the cache off
    # (for the other sections), and a row's overrides only change the keys they name.
    base = [o for o in base_overrides(args.tiny) if o not in UNCACHED_SAMPLES]
    frames = 12 if args.tiny else args.cache_frames
    batch = 4 if args.tiny else int(cfg.dataset.batch_size)
    warmup = 1 if args.tiny else 3
    repeats = 1 if args.tiny else args.candidate_repeats
    epochs = 2 if args.tiny else max(2, args.cache_epochs)
    later = "epoch 2" if epochs == 2 else f"epochs 2–{epochs}"
    report = throughput_report(args.out)
    # What the loaders are measured against: training on the training loader's own batches
    # (every field, the short last one too), collated once and held in memory, for as many
    # epochs, timed the same way, right after each loader's training (a pair: a change of the
    # machine's speed between pairs cancels out of their ratio).
    with tempfile.TemporaryDirectory() as cache:  # (no cache: nothing is written there)
        loader = cache_datamodule(base, UNCACHED_SAMPLES, Path(cache), frames, batch)
        loader = loader.train_dataloader()
        batches = list(loader)
    rates: dict[str, list[tuple[float, ...]]] = {label: [] for label in CACHE_LOADERS}
    held: list[tuple[float, float]] = []
    sources: dict[str, str] = {}
    n_train = 0
    for _ in range(repeats):
        for label, (extra, prefilled) in CACHE_LOADERS.items():
            row, sources[label], n_train = loader_row(
                base, extra, prefilled, frames, batch, warmup, epochs
            )
            memory = InMemory(batches, len(batches))
            held.append(training_epochs(base, memory, warmup, epochs))
            rates[label].append((*row, *held[-1]))
    report.add(
        f"MFG {cfg.dataset.height} × {cfg.dataset.width}, M = {cfg.model.net.hidden_units}, "
        f"float32, batch {batch}; 2 training trajectories of {frames} frames ({n_train} training "
        f"samples per epoch); {torch.get_num_threads()} torch threads; medians of {repeats} "
        "repeats, each on an empty cache.\n\n"
        + markdown_table(
            [
                "loader",
                "loader alone, epoch 1 (samples/s)",
                "loader alone, epoch 2",
                "epoch 2's samples served from",
                "training, epoch 1 (samples/s)",
                "epoch 1 waiting on data",
                f"training, {later}",
                f"{later} waiting on data",
                f"{later} / in memory",
            ],
            table_rows(rates, held, sources),
        )
        + "\n*Loader alone*: iterating the training loader (shuffled, collated) through epoch 1 "
        "after its first batch (a worker's start-up excluded) and through epoch 2; *served from*: "
        "the training dataset's own count of where epoch 2's samples came from in the loader-"
        "alone run (memory, its disk files, computed). *Training*: "
        f"`lightning.Trainer.fit` for {epochs} epochs on the DataModule, epoch 1 after "
        f"{warmup} steps, {later} whole; *waiting on data* = 1 − rate / the rate of the same "
        "epochs on the training loader's own batches (every field, the short last batch too) "
        "collated once and held in memory, timed the same way right after it (the median of the "
        f"repeats' pairs; *{later} / in memory*: their median (range), *noisy* where the range "
        f"leaves ±{100 * NOISY:.0f} % of it). Epoch 1 computes every sample (the disk row "
        "reads an earlier run's entries); from epoch 2 on the cached loaders read memory (the "
        "disk row: its files). `prefetch=thread` computes ahead in a thread of the training "
        "process, in the loader's order; `prefetch=worker` in one persistent loader process. "
        "Both compete with the training step's threads for the cores."
    )
    return report.write_section(SAMPLE_CACHE_MARKER, "The sample cache: samples computed once")
