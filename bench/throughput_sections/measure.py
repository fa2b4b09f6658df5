"""What the throughput sections share: the composed train config and fresh models built from it,
the synthetic samples held in memory and their batches, interleaved repeats, and the run a full
``bench/throughput.py`` hands from section to section (:class:`Run`)."""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import torch
from _common import TINY_OVERRIDES, Report

TITLE = "Throughput: training, inference, data, memory"
#: The precisions compared: the row label → ``trainer.precision``.
PRECISIONS = {"float32": "32-true", "bf16-mixed": "bf16-mixed"}
SAMPLE_KEYS = ("flow", "flow_valid", "pose", "intrinsics", "sequence", "frame", "target")
#: Overrides that turn the sample cache and its prefetch off: what the other sections' data
#: rows measure (the generator itself).
UNCACHED_SAMPLES = [
    "dataset.sample_cache.memory_mb=0",
    "dataset.sample_cache.disk=false",
    "dataset.prefetch=none",
]


def throughput_report(out: Path | None) -> Report:
    """An empty report for ``<out>/throughput.md`` (default ``bench/results``)."""
    return Report("throughput", TITLE, out)


def base_overrides(tiny: bool) -> list[str]:
    """The quick-start model (or the tiny test model) with nothing logged per step, on PyTorch's
    own convolutions (section 7 compares the others)."""
    # A constant learning rate: the bare loop has no scheduler, and a scheduler step costs the
    # same in either loop.
    ov = ["paths.output_dir=.", "model.image_log_every_n_steps=0", "model.scheduler=null"]
    # The data rows measure the generator itself (the sample cache has its own section).
    ov += UNCACHED_SAMPLES
    ov += ["model.net.conv_impl=native"]
    if tiny:
        ov += TINY_OVERRIDES
    return ov


def with_overrides(overrides: list[str], extra: list[str]) -> list[str]:
    """``overrides`` then ``extra``, an earlier value of a key that ``extra`` sets left out."""
    keys = {o.split("=", 1)[0] for o in extra}
    return [o for o in overrides if o.split("=", 1)[0] not in keys] + extra


@cache
def _config(overrides: tuple[str, ...]) -> Any:
    """The composed train config (composing is slow; every measurement builds a fresh model)."""
    from mfg_lightning.core.config import compose

    return compose("train", list(overrides))


def build_model(overrides: list[str], seed: int = 0) -> tuple[Any, Any]:
    """An ``MFGLitModule`` from the train config with these overrides, seeded, and the config."""
    from mfg_lightning.run.runs import build_model as build

    cfg = _config(tuple(overrides))
    torch.manual_seed(seed)
    return build(cfg), cfg


def datamodule(overrides: list[str]) -> Any:
    """The train config's DataModule with these overrides (composed anew: not cached)."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    return instantiate(compose("train", overrides).dataset)


def render(cfg: Any, n_samples: int) -> list[dict]:
    """``n_samples`` training samples of the configured synthetic dataset, rendered once."""
    from hydra.utils import instantiate

    dataset = instantiate(cfg.dataset).dataset("train")
    return [{k: dataset[i][k] for k in SAMPLE_KEYS} for i in range(n_samples)]


def make_batches(samples: list[dict], batch_size: int) -> list[dict]:
    """The samples collated into consecutive batches (the remainder is dropped)."""
    from mfg_lightning.data.base import collate_samples

    return [
        collate_samples(samples[i : i + batch_size])
        for i in range(0, len(samples) - batch_size + 1, batch_size)
    ]


def interleaved(fns: dict[Any, Callable[[], float]], repeats: int) -> dict[Any, list[float]]:
    """Call every function ``repeats`` times, interleaved (a, b, a, b, …): every value."""
    values: dict[Any, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            values[k].append(fn())
    return values


def median_of(fns: dict[Any, Callable[[], float]], repeats: int) -> dict[Any, float]:
    """Call every function ``repeats`` times, interleaved, and keep the median of each."""
    return {k: statistics.median(v) for k, v in interleaved(fns, repeats).items()}


@dataclass
class Run:
    """What the sections of a full run share.

    Attributes:
        args: the command line (``--tiny`` already applied to the sizes and repeats).
        base: the overrides of every model (:func:`base_overrides`).
        cfg: the train config they compose.
        samples: the synthetic training samples held in memory (at least the largest batch).
        report: the report every section adds to, written once at the end.
    """

    args: argparse.Namespace
    base: list[str]
    cfg: Any
    samples: list[dict]
    report: Report

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """(batch size, timed steps) of each ``--batch-sizes``."""
        return list(zip(self.args.batch_sizes, self.args.steps_per_batch_size, strict=True))

    @property
    def largest(self) -> int:
        """The largest batch size: the profiles and the per-layer kernels run at it."""
        return max(self.args.batch_sizes)
