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

import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.run.training import train

log = logging.getLogger("mfg_lightning.train_flow")


def export_best(cfg: DictConfig, metrics: dict[str, float], seconds: float) -> Path | None:
    """Export the run's best (else last) checkpoint's network to ``cfg.export`` with its
    provenance; write ``metrics.json``. Returns the exported file."""
    import torch

    from mfg_lightning.core.atomic import atomic_write_text
    from mfg_lightning.flow.learned import load_weights, save_weights
    from mfg_lightning.run.runs import run_info

    output_dir = Path(cfg.paths.output_dir)
    checkpoints = sorted((output_dir / "checkpoints").glob("best-*.ckpt"))
    source = checkpoints[-1] if checkpoints else output_dir / "checkpoints" / "last.ckpt"
    info = run_info()
    started = output_dir / "run_info.json"
    if started.is_file():  # the commit the run trained with (a later one may be checked out)
        info["git_commit"] = json.loads(started.read_text()).get("git_commit")
    payload: dict[str, Any] = {
        "metrics": dict(sorted(metrics.items())),
        "checkpoint": source.name,
        "train_seconds": seconds,
        **info,
    }
    target = cfg.get("export")
    if target and source.is_file():
        net, from_ckpt = load_weights(source)
        provenance = {
            "command": "python -m mfg_lightning.train_flow " + " ".join(sys.argv[1:]),
            "commit": info.get("git_commit"),
            "global_step": from_ckpt.get("global_step"),
            "data": OmegaConf.to_container(cfg.dataset, resolve=True),
            "model": OmegaConf.to_container(cfg.model, resolve=True),
            "validation": {k: v for k, v in metrics.items() if k.startswith("val/")},
            "train_seconds": round(seconds, 1),
            "cpu_kind": info.get("cpu_kind"),
            "torch": str(torch.__version__),
            "threads": torch.get_num_threads(),
        }
        for key in ("poses_dir", "cache_dir"):  # (no absolute path of this machine)
            if provenance["data"].get(key):
                provenance["data"][key] = f"<{key}>"
        payload["exported"] = str(save_weights(target, net, provenance))
        log.info("exported %s (step %s) to %s", source.name, provenance["global_step"], target)
    atomic_write_text(
        output_dir / "metrics.json", json.dumps(payload, indent=2, default=str) + "\n"
    )
    return Path(target) if target and source.is_file() else None


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
