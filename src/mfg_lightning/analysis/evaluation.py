"""Evaluating a checkpoint on a test split: what ``python -m mfg_lightning.evaluate`` runs (its
docstring says what each task writes; ``docs/evaluation.md`` lists the files).

:func:`evaluate` builds the model from the checkpoint, the DataModule (the config's, else the
checkpoint's) and the Trainer, then runs one task: :func:`evaluate_egomotion` (every k of
``eval.top_k_sweep``; poses, figures, tables) or :func:`evaluate_object_motion` (the object
masks of section 4 and Figure 1's grid).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig

from mfg_lightning.analysis.result_tables import object_motion_table, sequence_table, top_k_table
from mfg_lightning.core.atomic import atomic_write_bytes
from mfg_lightning.core.tables import Table, finite_or_none
from mfg_lightning.metrics.alignment import configured_align
from mfg_lightning.metrics.ate_traj import aligned_trajectory_metrics
from mfg_lightning.metrics.evaluator import EvaluationResult
from mfg_lightning.models.mfg import validate_top_k
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.pictures import plots
from mfg_lightning.run import runs
from mfg_lightning.run.checkpoints import module_from_checkpoint
from mfg_lightning.trajectory.pose_io import frame_times, write_trajectory

log = logging.getLogger("mfg_lightning.evaluate")

#: What a task returns: the ``test/`` metrics, the table to print and extra keys of
#: ``metrics.json``.
TaskResult = tuple[dict[str, Any], Table, dict[str, Any]]


def build(cfg: DictConfig) -> tuple[MFGLitModule, L.LightningDataModule, L.Trainer]:
    """The model from the checkpoint, the dataset (given, or the checkpoint's), the Trainer."""
    model = module_from_checkpoint(cfg.ckpt_path, top_k=validate_top_k(cfg.model.top_k))
    datamodule = runs.checkpoint_datamodule(
        cfg.get("dataset"), model.dataset_config, cfg.ckpt_path, eval_batch_size=cfg.eval.batch_size
    )
    return model, datamodule, runs.build_trainer(cfg, [], runs.instantiate_list(cfg.get("logger")))


def aligned_metrics(evaluation: EvaluationResult | None, align: str) -> dict[str, float]:
    """The ``test/`` whole-trajectory metrics of each sequence's trajectory after ``align``
    (nothing for ``none``: the test loop's own, unaligned, stand)."""
    if evaluation is None or align == "none":
        return {}
    sequences = {s: (sp.pred, sp.gt) for s, sp in sorted(evaluation.sequences.items())}
    return {f"test/{k}": v for k, v in aligned_trajectory_metrics(sequences, align).items()}


def evaluate_egomotion(
    cfg: DictConfig, model: MFGLitModule, datamodule: L.LightningDataModule, trainer: L.Trainer
) -> TaskResult:
    """Test every k of the sweep; write poses, figures, tables. Returns the metrics and extra
    keys for ``metrics.json`` and the table to print (the sweep's, else the sequences')."""
    align = configured_align(cfg.eval.get("align"), "eval.align")
    out, extra = Path(cfg.paths.output_dir), {"eval_align": align}
    given = cfg.eval.get("top_k_sweep")
    sweep = [validate_top_k(k, "eval.top_k_sweep") for k in given] if given else [model.top_k]
    # every k from one pass of the encoder per batch (MFGLitModule.test_at)
    model.test_at(sweep)
    trainer.test(model, datamodule=datamodule, verbose=len(sweep) == 1)
    results: dict[float, dict[str, Any]] = {}  # k → test metrics
    evaluations: dict[float, EvaluationResult | None] = {}  # k → per-sequence trajectories
    for k in sweep:
        metrics, evaluations[k] = model.evaluation["test"].results[k]
        results[k] = {name: finite_or_none(v) for name, v in metrics.items()}
        results[k].update(aligned_metrics(evaluations[k], align))
        log.info("top_k=%s: ATE %s m", k, results[k].get("test/ate"))
    # Everything is computed; only now are files written (each atomically). metrics.json, the
    # sequence table and the pose files all describe the full model (k = 1) when the sweep has
    # it, else its largest k: never whichever k happened to run last.
    final, evaluation = results[k := 1.0 if 1.0 in results else max(results)], evaluations[k]
    per_sequence = dict(sorted(evaluation.sequences.items())) if evaluation else {}
    if cfg.eval.write_poses and per_sequence:
        # the test split's clock, so that mfg-eval-poses matches the TUM files to KITTI's by time
        test_split = datamodule.dataset("test") if hasattr(datamodule, "dataset") else None
        for s, sp in per_sequence.items():
            times = frame_times(test_split, s, sp.frames.numpy(), float(cfg.eval.frame_rate))
            write_trajectory(out, s, times, sp.pred.numpy())
            write_trajectory(out, f"{s}_gt", times, sp.gt.numpy())
    trajectories = {s: (sp.pred, sp.gt) for s, sp in per_sequence.items()}
    plots.write_trajectory_figures(
        trajectories, out / "trajectories", runs.tensorboard_writer(trainer), align=align
    )
    (table := sequence_table(final, seqs := list(per_sequence))).write(out / "sequences")
    if len(results) > 1:
        (table := top_k_table(results, seqs)).write(out / "top_k")
        atomic_write_bytes(out / "top_k.png", plots.figure_png(plots.top_k_figure(results, seqs)))
        extra["top_k_sweep"] = {f"{k:g}": m for k, m in sorted(results.items(), reverse=True)}
    return final, table, extra


def evaluate_object_motion(
    cfg: DictConfig, model: MFGLitModule, datamodule: L.LightningDataModule, trainer: L.Trainer
) -> TaskResult:
    """Score the object masks and fields; draw the first test batch in Figure 1's layout."""
    from mfg_lightning.motion.object_motion import require_ground_truth
    from mfg_lightning.pictures.grids import save_png
    from mfg_lightning.pictures.object_motion import object_motion_pictures

    model.object_motion = instantiate(cfg.object_motion)
    datamodule.setup("test")
    require_ground_truth(datamodule.dataset("test")[0])
    trainer.test(model, datamodule=datamodule, verbose=False)
    metrics = runs.test_metrics(trainer)
    batch, n = next(iter(datamodule.test_dataloader())), int(cfg.eval.num_pictures)
    grid = object_motion_pictures(model.eval(), batch, model.object_motion, n)
    (table := object_motion_table(metrics)).write(Path(cfg.paths.output_dir) / "object_motion")
    save_png(grid, Path(cfg.paths.output_dir) / "pictures" / "object_motion.png")
    if (writer := runs.tensorboard_writer(trainer)) is not None:
        writer.add_image("test/object_motion", grid, 0, dataformats="HWC")
    return metrics, table, {}


TASKS: dict[str, Callable[..., TaskResult]] = {
    "egomotion": evaluate_egomotion,
    "object_motion": evaluate_object_motion,
}


def evaluate(cfg: DictConfig) -> TaskResult:
    """Run ``cfg.task`` (:data:`TASKS`) on the checkpoint ``cfg.ckpt_path``; its files are
    written, ``metrics.json`` is left to the caller.

    Raises:
        ValueError: an unknown task, before anything is built.
    """
    if cfg.task not in TASKS:
        raise ValueError(f"task must be 'egomotion' or 'object_motion', got {cfg.task!r}")
    return TASKS[cfg.task](cfg, *build(cfg))
