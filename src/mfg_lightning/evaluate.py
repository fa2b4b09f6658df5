"""Evaluate a checkpoint: ``python -m mfg_lightning.evaluate ckpt_path=… [dataset=…]``.

``task=egomotion`` (default) tests every k of ``eval.top_k_sweep`` (Table 1, supplementary
Figure 4) and writes ``metrics.json``, tables (:mod:`~mfg_lightning.analysis.result_tables`),
trajectories
(:mod:`~mfg_lightning.trajectory.pose_io`) and figures (:mod:`~mfg_lightning.pictures.plots`);
``task=object_motion``
scores the object masks of section 4 and draws Figure 1
(:mod:`~mfg_lightning.pictures.object_motion`).
``eval.align=<mode>`` (``none``, the default: as predicted; ``se3``, ``sim3``, ``scale``,
``scale_7dof``: :mod:`~mfg_lightning.metrics.alignment`) aligns each sequence's predicted
trajectory before the figures are drawn (their titles name it) and before the whole-trajectory
metrics are computed: ``ate_traj*``, RPE and drift are then those of the aligned trajectory of each
sequence (:func:`~mfg_lightning.metrics.aligned_trajectory_metrics`, as ``mfg-eval-poses
--align``), the snippet ATE (which aligns each snippet itself) and the pose files are unchanged.
``docs/evaluation.md`` lists the files. Trainer and loggers are configured as in training; the
tasks themselves are :mod:`mfg_lightning.analysis.evaluation`'s."""

from __future__ import annotations

from pathlib import Path

import hydra
import lightning as L
from omegaconf import DictConfig

from mfg_lightning.analysis.evaluation import evaluate
from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.run import runs


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="evaluate")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    L.seed_everything(cfg.seed, workers=True)
    metrics, table, extra = evaluate(cfg)
    print(table.markdown())
    info = {"ckpt_path": str(cfg.ckpt_path), "task": cfg.task, **runs.run_info(), **extra}
    runs.write_metrics(Path(cfg.paths.output_dir) / "metrics.json", metrics, info)


if __name__ == "__main__":
    main()
