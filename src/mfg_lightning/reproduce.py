"""Reproduce the paper's claims: ``python -m mfg_lightning.reproduce poses_dir=<KITTI poses/>``.

Runs the stages of ``conf/reproduce.yaml``'s stage table (:mod:`mfg_lightning.study.run`; each
cached as JSON under ``results_dir``, which starts from the committed results of
``start_from`` and refuses results of other settings, and skipped when cached; the trained
models under ``work_dir``; ``fresh=true`` starts over, ``stages=[...]`` selects,
``refresh_classical=[...]`` computes the classical rows of cached results again) and, after
every stage, rewrites ``report`` with one row per claim (:mod:`mfg_lightning.study.claims`) and
the PNG of its evidence beside it. Everything goes under ``outputs/`` unless a key names another
file. ``reproduce=tiny`` runs the whole study in about a minute on procedural trajectories.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.study import stages as S
from mfg_lightning.study.classical_refresh import refresh_classical
from mfg_lightning.study.plan import check, claim_results, write_procedural_poses
from mfg_lightning.study.run import run


def reproduce(cfg: DictConfig, trainer_choice: str = "default") -> Path:
    """Check the config, start over when ``fresh``, claim the results folder (its settings
    are this run's), run the study, return the report's path."""
    check(cfg)
    study = S.Study(cfg, trainer_choice)
    if cfg.fresh:
        # the trained models and the stage results (git restores committed ones)
        for d in (study.work, study.results):
            if d.exists():
                shutil.rmtree(d)
    poses = write_procedural_poses(cfg)
    if poses is not None:
        # set once, before any stage reads it: the study's worlds follow these poses
        cfg.poses_dir = str(poses)
    claim_results(cfg, study.results)
    for group in ("sparsity", "seeds"):
        (study.results / group).mkdir(parents=True, exist_ok=True)
    for name in cfg.refresh_classical:
        refresh_classical(study, name)
    return run(study, Path(cfg.report))


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="reproduce")
@exit_on_user_error
def main(cfg: DictConfig) -> Any:
    from hydra.core.hydra_config import HydraConfig

    from mfg_lightning.core.denormals import flush_denormals

    # the study trains in this process after computing its data, so subnormals are flushed here,
    # before torch's thread pool starts (mfg_lightning.core.denormals; train() does the same)
    flush_denormals()
    choice = HydraConfig.get().runtime.choices.get("trainer") or "default"
    reproduce(cfg, choice)


if __name__ == "__main__":
    main()
