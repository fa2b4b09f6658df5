"""Train the learned flow: ``python -m mfg_lightning.train_flow [group=option ...] [key=value]``.

The network of :mod:`mfg_lightning.flow.pwc` (PWC-Net's design) on rendered pairs with their
exact flow (:mod:`mfg_lightning.data.flow_pairs`: the training trajectories and their validation
tails, never the test ones), through the same run machinery as ``train``
(:func:`mfg_lightning.run.training.train`: run directory, checkpoints, ``resume=true``, progress
bar, TensorBoard with ``train/flow`` and ``val/flow`` figures). At the end the best checkpoint's
network is exported to ``export`` (``<run dir>/flow_net.pt``) with its provenance, and
``metrics.json`` holds the last validation's EPE: ``flow=learned flow.weights=<that file>``
feeds it to MFG.

The shipped weights come from ``experiment=flow_kitti_worlds`` (``docs/flow.md``).
"""

from __future__ import annotations

import time

import hydra
from omegaconf import DictConfig

from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.run.flow_export import export_best
from mfg_lightning.run.training import train


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train_flow")
@exit_on_user_error
def main(cfg: DictConfig) -> float | None:
    start = time.perf_counter()
    metrics = train(cfg)
    export_best(cfg, metrics, time.perf_counter() - start)
    return metrics.get("val/epe")


if __name__ == "__main__":
    main()
