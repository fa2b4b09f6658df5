"""Analyse the egomotion basis of a trained MFG and its population sparsity.

``python -m mfg_lightning.analyze_basis ckpt_path=… [dataset=…] [n_units=100] [out_dir=…]``
(config: ``conf/analyze_basis.yaml``). Loads the checkpoint (:mod:`mfg_lightning.run.checkpoints`),
builds the dataset (given, or the checkpoint's) and runs
:func:`mfg_lightning.analysis.basis_report.analyze`,
whose module docstring lists every file written into ``out_dir``.
"""

from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.analysis.basis_report import analyze
from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.run.checkpoints import (
    build_module,
    dataset_config,
    load_checkpoint,
    model_size,
    stored_model_config,
)
from mfg_lightning.run.runs import checkpoint_datamodule

log = logging.getLogger("mfg_lightning.analyze_basis")


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="analyze_basis")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "ckpt_path"):
        raise ValueError(
            "ckpt_path is required: python -m mfg_lightning.analyze_basis "
            "ckpt_path=<run dir>/checkpoints/last.ckpt"
        )
    ckpt = load_checkpoint(cfg.ckpt_path)
    # The run directory's config.yaml is read only when no dataset is given.
    stored = None if cfg.get("dataset") is not None else dataset_config(ckpt, cfg.ckpt_path)
    size = model_size(stored_model_config(ckpt) or {})
    datamodule = checkpoint_datamodule(cfg.get("dataset"), stored, cfg.ckpt_path, size)
    module = build_module(ckpt, cfg.ckpt_path)
    summary = analyze(
        module, datamodule, cfg.out_dir, n_units=int(cfg.n_units),
        n_examples=int(cfg.n_examples), top_units=int(cfg.top_units),
        max_test_batches=cfg.get("max_test_batches"), device=str(cfg.device),
        ckpt_path=str(cfg.ckpt_path),
    )  # fmt: skip
    pop = summary["population"]
    log.info(
        "%d test inputs: %.1f active units per input on average (median %s) of %d; wrote %s",
        pop["n_inputs"], pop["active_units_mean"] or float("nan"), pop["active_units_median"],
        pop["hidden_units"], cfg.out_dir,
    )  # fmt: skip
    print(f"analyze_basis: wrote {len(summary['files'])} files to {cfg.out_dir}")


if __name__ == "__main__":
    main()
