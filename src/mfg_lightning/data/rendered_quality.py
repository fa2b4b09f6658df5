"""The flow quality of ``flow=dis``'s splits beside their flow cache: where a split's is written
(:func:`quality_path`, named by the pair set it measures) and how it reaches the trainer's
loggers with the split's picture grids (:func:`log_split_quality`).

The quality itself is computed by
:meth:`~mfg_lightning.data.rendered.RenderedDrivingDataset.quality`
(:mod:`mfg_lightning.metrics.flow_quality`) and written by
:meth:`~mfg_lightning.data.synthetic.SyntheticDataModule.prepare_data`."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from mfg_lightning.data.rendered import RenderedDrivingDataset


def quality_path(ds: RenderedDrivingDataset, split: str) -> Path:
    """Where the flow quality of ``ds`` (split ``split``) is written: beside the cache, named by
    the pair set it measures (the split, its pair count and a digest of its (sequence, source,
    target) list), so that runs with other offsets, strides or frame counts on the same worlds
    do not share it."""
    digest = hashlib.sha256(repr(sorted(ds.samples)).encode()).hexdigest()[:12]
    return ds.cache.root / f"quality-{split}-{len(ds.samples)}pairs-{digest}.json"


def log_split_quality(
    loggers: Iterable[Any], split: str, ds: RenderedDrivingDataset, path: Path
) -> None:
    """Log the flow quality written at ``path`` to ``loggers`` (Lightning loggers):
    ``<split>/flow_epe/<region>`` (pixels) and ``<split>/flow_fl/<region>`` (%) on all pixels,
    ``<split>/flow_epe_noc/<region>`` and ``<split>/flow_fl_noc/<region>`` on the non-occluded
    ones, and ``<split>/flow_nonfinite_pixels`` at step 0, then, except for ``val`` (the
    validation tails share the training split's pictures), the picture grid of each sequence
    of ``ds`` that is cached
    (:meth:`~mfg_lightning.data.rendered.RenderedDrivingDataset.picture_path`) as the image
    ``<split>/flow_picture/<seq>`` of every logger that takes images."""
    loggers = list(loggers)
    quality = json.loads(path.read_text())
    metrics = {}
    for key, suffix in (("regions", ""), ("regions_noc", "_noc")):
        for region, q in quality.get(key, {}).items():
            if q["epe"] is not None:
                metrics[f"{split}/flow_epe{suffix}/{region}"] = q["epe"]
                metrics[f"{split}/flow_fl{suffix}/{region}"] = q["fl"]
    metrics[f"{split}/flow_nonfinite_pixels"] = float(quality["nonfinite_pixels"])
    for logger in loggers:
        logger.log_metrics(metrics, step=0)
    if split == "val":
        return  # the validation tails share the training split's pictures
    for seq in ds.sequences():
        picture = ds.picture_path(seq)
        if not picture.exists():
            continue
        grid = np.load(picture)
        for logger in loggers:
            add_image = getattr(getattr(logger, "experiment", None), "add_image", None)
            if add_image is not None:
                add_image(f"{split}/flow_picture/{seq}", grid, 0, dataformats="HWC")
