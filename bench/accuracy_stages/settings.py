"""What the stages of ``bench/accuracy.py`` share: the Hydra overrides of a flow source's run
(the quick-start optimiser on the KITTI trajectories), its DataModule, and the JSON files under
``--work`` in which each stage caches its result so that a rerun resumes."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from _common import TINY_OVERRIDES


def flow_overrides(args: argparse.Namespace, flow: str) -> list[str]:
    """The ``flow`` group overrides of one source."""
    if flow == "exact":
        return ["flow=exact"]
    cache = args.flow_cache or args.work / "cache"
    ov = ["flow=dis", f"flow.preset={args.dis_preset}", f"dataset.cache_dir={cache}"]
    if args.render_size:
        ov += [f"flow.height={args.render_size[0]}", f"flow.width={args.render_size[1]}"]
    return ov


def overrides(
    args: argparse.Namespace, output_dir: Path, flow: str = "exact", max_frames: int | None = None
) -> list[str]:
    """The Hydra overrides of the training run (the quick-start optimiser, KITTI trajectories)."""
    ov = [
        *flow_overrides(args, flow),
        "dataset.trajectory=kitti",
        f"dataset.poses_dir={args.poses_dir}",
        "dataset.train_sequences=[0,1,2,3,4,5,6,7,8]",
        "dataset.test_sequences=[9,10]",
        f"dataset.batch_size={args.batch_size}",
        f"dataset.eval_batch_size={args.eval_batch_size}",
        f"trainer.max_steps={args.steps}",
        # Validation is not what this benchmark measures: no validation loop, no checkpoints.
        "trainer.limit_val_batches=0",
        "++trainer.num_sanity_val_steps=0",
        "++trainer.enable_progress_bar=false",
        "++trainer.enable_checkpointing=false",
        "trainer.enable_model_summary=false",
        "logger=none",
        "callbacks=none",
        "model.image_log_every_n_steps=0",
        f"seed={args.seed}",
        f"paths.output_dir={output_dir}",
    ]
    if max_frames:
        ov.append(f"dataset.max_frames={max_frames}")
    if args.tiny:
        ov += TINY_OVERRIDES
    return ov


def datamodule_for(args: argparse.Namespace, flow: str, max_frames: int | None) -> tuple[Any, Any]:
    """The config and the DataModule of one flow source, as ``mfg_lightning.train`` builds them."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    cfg = compose("train", overrides(args, args.work / "run", flow, max_frames))
    return cfg, instantiate(cfg.dataset)


def read_stage(path: Path) -> dict | None:
    """A stage's cached result, or None where it has not finished (no file, or a torn one)."""
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def write_stage(path: Path, payload: dict) -> None:
    """Cache a stage's result (atomically: an interrupted write leaves the old file or none)."""
    from mfg_lightning.core.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(payload, indent=2) + "\n")


def frames_tag(max_frames: int | None) -> str:
    """The part of a stage's file name that says how many frames of each sequence it used."""
    return "all" if not max_frames else str(max_frames)
