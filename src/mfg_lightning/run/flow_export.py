"""The end of a ``python -m mfg_lightning.train_flow`` run: its best checkpoint's network
exported as a weight file with its provenance (:func:`export_best`), and its ``metrics.json``."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("mfg_lightning.train_flow")

__all__ = ["export_best"]


def export_best(cfg: DictConfig, metrics: dict[str, float], seconds: float) -> Path | None:
    """Export the run's best (else last) checkpoint's network to ``cfg.export`` with its
    provenance; write ``metrics.json``. Returns the exported file. Under DDP only the first
    process writes (every process ends here with the same reduced metrics)."""
    import torch
    from lightning.pytorch.utilities import rank_zero_only

    from mfg_lightning.flow.learned import load_weights, save_weights
    from mfg_lightning.run.runs import run_info, write_metrics

    if rank_zero_only.rank != 0:
        return None
    output_dir = Path(cfg.paths.output_dir)
    checkpoints = sorted((output_dir / "checkpoints").glob("best-*.ckpt"))
    source = checkpoints[-1] if checkpoints else output_dir / "checkpoints" / "last.ckpt"
    info = run_info()
    started = output_dir / "run_info.json"
    if started.is_file():  # the commit the run trained with (a later one may be checked out)
        info["git_commit"] = json.loads(started.read_text()).get("git_commit")
    payload: dict[str, Any] = {
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
    write_metrics(output_dir / "metrics.json", metrics, payload)
    return Path(target) if target and source.is_file() else None
