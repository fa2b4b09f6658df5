"""The report's statistics constants, read once from ``conf/reproduce.yaml``'s ``statistics``
block (the bootstrap's draws and block length, the floors of a judged ratio, the thresholds of
the conclusion words), where they sit beside the study's other thresholds. The report only reads
them, so they are read from the file as shipped, not from a run's command line."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from mfg_lightning.core.config import CONFIG_DIR

__all__ = ["STATISTICS"]

#: ``conf/reproduce.yaml``'s ``statistics`` block.
STATISTICS: DictConfig = OmegaConf.load(Path(CONFIG_DIR) / "reproduce.yaml").statistics
