"""Train MFG: ``python -m mfg_lightning.train [group=option ...] [key=value ...]``.

Builds everything from the config with ``hydra.utils.instantiate``, fits, tests the best
checkpoint and writes ``metrics.json`` into the run directory (``hydra.run.dir``), which also
holds ``checkpoints/`` (last and best), the TensorBoard event files, the resolved config
(``config.yaml``) and ``run_info.json`` (package version, git commit, seed, what it resumed from).

A run stopped at any point (SIGKILL, SIGTERM, a crash) continues exactly where its last
checkpoint left it with ``ckpt_path=last`` or ``resume=true`` and the same ``hydra.run.dir``
(:mod:`mfg_lightning.run.callbacks`: atomic checkpoints, a data order that resumes mid-epoch,
a checkpoint on SIGTERM and Ctrl-C). A resume inside an epoch with another batch size, dataset
or seed is refused unless ``resume_restart_epoch=true``
(:mod:`mfg_lightning.data.resumable_loader`).
"""

from __future__ import annotations

import errno
import logging
import math

import hydra
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.run.callbacks import storage_error
from mfg_lightning.run.training import train

log = logging.getLogger("mfg_lightning.train")


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
@exit_on_user_error
def main(cfg: DictConfig) -> float | None:
    try:
        metrics = train(cfg)
    except OSError as err:
        # A full disk anywhere (flow cache, logs, metrics) is one clear line, not a traceback.
        if err.errno not in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
            raise
        where = [
            OmegaConf.select(cfg, f"paths.{k}", default=None) for k in ("output_dir", "cache_dir")
        ]
        hint = "this run writes to " + " and ".join(str(w) for w in where if w)
        raise storage_error(err.filename, err, hint=hint) from err
    name = cfg.get("optimized_metric")
    if not name:
        return None
    value = metrics.get(name)
    if value is None or not math.isfinite(value):
        # a sweeper (Optuna) records the trial as failed; say why in the job's log
        log.warning(
            "optimized_metric %r is %s after this run (e.g. validation sequences shorter than "
            "one 5-frame ATE snippet); logged metrics: %s",
            name,
            "missing" if value is None else value,
            ", ".join(sorted(k for k in metrics if k.startswith("val/"))) or "none",
        )
    return value


if __name__ == "__main__":
    main()
