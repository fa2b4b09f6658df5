"""Within a multirun, jobs whose training configs are equal share one training.

A job's training config is its resolved config without the settings that change only what is
evaluated (:data:`EVALUATION_ONLY`: ``model.top_k``, the test, figures, loggers, the best
checkpoint's rule) and without its own directory. The first such job trains, under a file lock
in ``<sweep dir>/.trainings/``, as an independent run would, and also keeps the weights of every
validation. The other jobs wait for the lock, then evaluate: each validates every kept
checkpoint with its own settings, picks its best by its own ``callbacks.model_checkpoint`` rule
(as Lightning's ``ModelCheckpoint`` does), tests it and writes its own ``metrics.json``. On a
CPU that file equals an independent run's of the same job (tests/test_sweeps.py).

A failed training releases the lock, and the next waiting job trains. Jobs share only where
the trainer runs one process and a validation metric picks the best checkpoint; others train
on their own. ``share_trainings=false`` turns sharing off.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("mfg_lightning.train")

#: Settings that change what a job evaluates, not what it trains.
EVALUATION_ONLY = (
    "model.top_k", "model.image_log_every_n_steps", "test", "optimized_metric", "task_name",
    "logger", "callbacks.model_checkpoint", "callbacks.figures", "callbacks.rich_progress_bar",
    "dataset.eval_batch_size", "trainer.limit_test_batches",
)  # fmt: skip
#: Of those, the ones a validation metric depends on: training settings where a callback other
#: than the best checkpoint's stops the training on a validation metric (the convergence rule).
VALIDATION = ("model.top_k", "dataset.eval_batch_size")
#: Where the first job keeps the weights of every validation, in its run directory.
VALIDATIONS_DIR = "checkpoints/validations"


def _relative(node: Any, run_dir: str) -> Any:
    """``node`` with the job's own directory written as ``<run dir>``."""
    if isinstance(node, dict):
        return {k: _relative(v, run_dir) for k, v in node.items()}
    if isinstance(node, list):
        return [_relative(v, run_dir) for v in node]
    if isinstance(node, str) and (node == run_dir or node.startswith(run_dir + "/")):
        return "<run dir>" + node[len(run_dir) :]
    return node


def training_config(cfg: DictConfig) -> dict[str, Any]:
    """What the job trains: its config without :data:`EVALUATION_ONLY` and its directory."""
    plain = _relative(OmegaConf.to_container(cfg, resolve=True), str(cfg.paths.output_dir))
    callbacks = plain.get("callbacks") or {}
    stops_on_validation = any(
        isinstance(c, dict) and c.get("monitor") for k, c in callbacks.items()
        if k != "model_checkpoint"
    )  # fmt: skip
    for key in EVALUATION_ONLY:
        if stops_on_validation and key in VALIDATION:
            continue
        *parents, last = key.split(".")
        node = plain
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(last, None)
    return plain


def shared_folder(cfg: DictConfig) -> Path | None:
    """``<sweep dir>/.trainings`` where this job may share its training, else None: outside a
    multirun, with ``share_trainings=false``, a trainer of several processes, or no validation
    metric to pick the best checkpoint by."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not (HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN):
        return None
    trainer, best = cfg.trainer, OmegaConf.select(cfg, "callbacks.model_checkpoint.monitor")
    one_process = str(trainer.get("devices", 1)) == "1" and int(trainer.get("num_nodes") or 1) == 1
    if not (cfg.get("share_trainings", True) and one_process and best):
        return None
    return Path(HydraConfig.get().sweep.dir) / ".trainings"


def training_id(cfg: DictConfig) -> str:
    """A digest of :func:`training_config`: jobs with equal ones share a training."""
    text = json.dumps(training_config(cfg), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def keep_validation_weights(run_dir: Path) -> ModelCheckpoint:
    """The callback that keeps the weights of every validation of the training."""
    return ModelCheckpoint(
        dirpath=run_dir / VALIDATIONS_DIR, filename="step-{step:06d}", monitor=None,
        save_top_k=-1, save_weights_only=True, auto_insert_metric_name=False,
    )  # fmt: skip


def read_training(folder: Path, key: str) -> dict[str, Any] | None:
    """The record of a finished shared training (None: none yet)."""
    path = folder / f"{key}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def best_checkpoint(
    paths: list[str], scores: list[dict[str, float]], monitor: str, mode: str = "min"
) -> str | None:
    """The checkpoint Lightning's ``ModelCheckpoint(monitor, mode, save_top_k=1)`` keeps: the
    first validation's, replaced by each later one strictly better (a NaN counts as the worst)."""
    best, best_value = None, math.nan
    for path, score in zip(paths, scores, strict=True):
        value = score.get(monitor)
        if value is None:
            continue
        if best is None:
            best = path
            best_value = value if not math.isnan(value) else math.inf * (1 if mode == "min" else -1)
        elif (value < best_value) if mode == "min" else (value > best_value):
            best, best_value = path, value
    return best
