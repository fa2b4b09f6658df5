"""Train MFG: ``python -m mfg_lightning.train [group=option ...] [key=value ...]``.

Builds everything from the config with ``hydra.utils.instantiate``, fits, tests the best
checkpoint and writes ``metrics.json`` into the run directory (``hydra.run.dir``), which also
holds ``checkpoints/`` (last and best), the TensorBoard event files and the resolved config.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import hydra
import lightning as L
from hydra.utils import instantiate
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.config import CONFIG_DIR
from mfg_lightning.runs import (
    atomic_write_text,
    build_model,
    exit_on_user_error,
    instantiate_list,
    run_info,
    write_metrics,
)

log = logging.getLogger("mfg_lightning.train")


def resolve_ckpt_path(ckpt_path: str | None, output_dir: Path) -> str | None:
    """``"last"`` → ``<run dir>/checkpoints/last.ckpt``; a missing file is a clear error."""
    if ckpt_path is None:
        return None
    path = output_dir / "checkpoints" / "last.ckpt" if ckpt_path == "last" else Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path: checkpoint not found: {path}")
    return str(path)


def flat_hparams(cfg: DictConfig) -> dict[str, Any]:
    """The run's settings as ``{"model.loss.w_s": 100.0, ...}`` scalars for TensorBoard HParams.

    Hydra's own settings and paths are left out; lists become strings.
    """
    container = OmegaConf.to_container(cfg, resolve=True)
    flat: dict[str, Any] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                if prefix == "" and key in ("paths", "hydra", "callbacks", "logger"):
                    continue
                walk(f"{prefix}{key}.", value)
        else:
            key = prefix[:-1]
            flat[key] = node if isinstance(node, (int, float, str, bool)) else str(node)

    walk("", container)
    return flat


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit and test as configured. Returns the final metrics (``val/*`` and ``test/*``)."""
    output_dir = Path(cfg.paths.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(output_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    L.seed_everything(cfg.seed, workers=True)

    datamodule: L.LightningDataModule = instantiate(cfg.dataset)
    model = build_model(cfg)
    callbacks = instantiate_list(cfg.get("callbacks"))
    loggers = instantiate_list(cfg.get("logger"))
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)
    hparams = flat_hparams(cfg)

    start = time.perf_counter()
    trainer.fit(
        model, datamodule=datamodule, ckpt_path=resolve_ckpt_path(cfg.get("ckpt_path"), output_dir)
    )
    train_seconds = time.perf_counter() - start
    metrics = {k: v for k, v in trainer.callback_metrics.items() if k.startswith("val/")}

    if cfg.get("test"):
        best = getattr(trainer.checkpoint_callback, "best_model_path", "") or None
        if best is None:
            log.warning("no best checkpoint (no validation ran?): testing the current weights")
        trainer.test(model, datamodule=datamodule, ckpt_path=best, weights_only=False)
        metrics.update({k: v for k, v in trainer.callback_metrics.items() if k.startswith("test/")})
        for lg in loggers:
            if isinstance(lg, TensorBoardLogger):
                # TensorBoard's HParams view: this run's settings beside its final metrics.
                lg.log_hyperparams(hparams, metrics={k: float(v) for k, v in metrics.items()})
        if trainer.is_global_zero:
            write_metrics(
                output_dir / "metrics.json",
                metrics,
                {
                    "train_seconds": train_seconds,
                    "global_step": trainer.global_step,
                    "best_checkpoint": best,
                    **run_info(),
                },
            )
    return {k: float(v) for k, v in metrics.items()}


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
@exit_on_user_error
def main(cfg: DictConfig) -> float | None:
    metrics = train(cfg)
    return metrics.get(cfg.get("optimized_metric") or "")


if __name__ == "__main__":
    main()
