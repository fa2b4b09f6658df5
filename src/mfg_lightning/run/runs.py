"""Building the parts of a run from a config, and writing what a run produced.

Shared by the entry points (train, evaluate) so that each of them stays thin.
"""

from __future__ import annotations

import json
import logging
import subprocess
from pathlib import Path
from typing import Any

import lightning as L
from hydra.utils import instantiate
from lightning.fabric.plugins.environments import ClusterEnvironment
from lightning.fabric.plugins.io.checkpoint_io import CheckpointIO
from omegaconf import DictConfig, ListConfig, OmegaConf

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.core.machine import cpu_kind
from mfg_lightning.core.tables import finite_or_none
from mfg_lightning.run.callbacks import AtomicCheckpointIO
from mfg_lightning.run.precision import PRECISION_AUTO, resolve_precision, with_precision_setup
from mfg_lightning.run.slurm import slurm_environment
from mfg_lightning.run.together import BuffersWhereNeeded, StopTogether

log = logging.getLogger(__name__)


def instantiate_list(cfg: DictConfig | None) -> list[Any]:
    """Instantiate every entry with a ``_target_`` of a config mapping (callbacks, loggers)."""
    if not cfg:
        return []
    return [instantiate(v) for v in cfg.values() if isinstance(v, DictConfig) and "_target_" in v]


def build_model(cfg: DictConfig) -> L.LightningModule:
    """Instantiate the LightningModule with its resolved config as its ``model_config`` (saved
    with its hyperparameters, so that its checkpoints record it), and remember the dataset's."""
    net = cfg.model.get("net")
    if net is not None and "top_k" in net:
        # one knob: top-k is an evaluation setting of the module, not of the network
        raise ValueError(
            f"model.net.top_k={net.top_k} is not a setting of the network: set model.top_k "
            "instead (the fraction kept at validation and test)"
        )
    model = module_of(OmegaConf.to_container(cfg.model, resolve=True))
    model.dataset_config = OmegaConf.to_container(cfg.dataset, resolve=True)
    return model


def module_of(config: dict[str, Any]) -> L.LightningModule:
    """The LightningModule of a resolved ``model`` config, given that config as its
    ``model_config`` (plain data: Hydra instantiates everything else in it)."""
    return instantiate(config, _partial_=True)(model_config=config)


def set_baseline(model: L.LightningModule, datamodule: L.LightningDataModule) -> None:
    """Give the model its evaluation baseline: the mean motion of the datamodule's training
    split (:meth:`mfg_lightning.data.base.MFGDataModule.mean_motion`), scored as
    ``<stage>/baseline_*``."""
    model.set_mean_motion(*datamodule.mean_motion("train"))


def resolve_configured_precision(cfg: DictConfig) -> Any:
    """Make a ``cfg.trainer.precision=auto`` that no training run resolved concrete in ``cfg``
    (logged); return the precision.

    A training run resolves ``auto`` by this machine's measurement before it builds the trainer
    (:mod:`mfg_lightning.run.run_choices`); anywhere else (evaluation, prediction, the flow
    network's training) nothing is measured and ``auto`` is :func:`resolve_precision`'s
    ``32-true``.
    """
    from omegaconf import open_dict

    trainer = cfg.get("trainer")
    if trainer is None or str(trainer.get("precision")) != PRECISION_AUTO:
        return None if trainer is None else trainer.get("precision")
    chosen = resolve_precision(PRECISION_AUTO, trainer.get("accelerator", "auto"))
    log.info("trainer.precision=auto: %s (not measured outside a training run)", chosen)
    with open_dict(cfg):
        cfg.trainer.precision = chosen
    return chosen


def build_trainer(cfg: DictConfig, callbacks: list[Any], loggers: list[Any]) -> L.Trainer:
    """The configured ``lightning.Trainer``, writing checkpoints atomically unless the config
    brings its own checkpoint IO plugin (``trainer.plugins``: one or a list, configs with a
    ``_target_`` or Lightning's plugin names), inside a SLURM allocation with Lightning's SLURM
    environment without its auto-requeue (:func:`mfg_lightning.run.slurm.slurm_environment`),
    and with the precision rules
    (:class:`mfg_lightning.run.precision.PrecisionSetup`), the SIGTERM handling that stops
    every DDP process after the same step (:class:`mfg_lightning.run.together.StopTogether`) and
    DDP's buffer broadcast only where a buffer needs it
    (:class:`mfg_lightning.run.together.BuffersWhereNeeded`) among its callbacks."""
    resolve_configured_precision(cfg)
    given = cfg.trainer.get("plugins") or []
    given = list(given) if isinstance(given, (list, ListConfig)) else [given]
    plugins = [instantiate(p) if isinstance(p, DictConfig) else p for p in given]
    if not any(isinstance(p, CheckpointIO) for p in plugins):
        plugins.append(AtomicCheckpointIO())
    if not any(isinstance(p, ClusterEnvironment) for p in plugins):
        # inside a SLURM allocation: Lightning's environment without its auto-requeue (a
        # requeue goes through last.ckpt and resume=true: mfg_lightning.run.slurm)
        slurm = slurm_environment()
        if slurm is not None:
            plugins.append(slurm)
    callbacks = with_precision_setup(callbacks)
    for needed in (StopTogether, BuffersWhereNeeded):
        if not any(isinstance(cb, needed) for cb in callbacks):
            callbacks.append(needed())
    return instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, plugins=plugins)


def tensorboard_writer(trainer: L.Trainer) -> Any | None:
    """The ``SummaryWriter`` of the trainer's TensorBoard logger, or None without one (images
    go only to TensorBoard; other loggers get the files in the run directory)."""
    from lightning.pytorch.loggers import TensorBoardLogger

    tb = [lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)]
    return tb[0].experiment if tb else None


def checkpoint_datamodule(
    dataset_cfg: DictConfig | None,
    stored: dict[str, Any] | None,
    ckpt_path: str | Path,
    size: Any | None = None,
    **overrides: Any,
) -> L.LightningDataModule:
    """The datamodule of a run that reads a checkpoint: ``dataset=`` when given, else the dataset
    the checkpoint was trained on (``stored``: :func:`mfg_lightning.run.checkpoints.dataset_config`,
    which falls back to the run directory's ``config.yaml``).

    Args:
        dataset_cfg: the composed ``dataset`` group, or None.
        stored: the checkpoint's dataset config, or None.
        ckpt_path: the checkpoint, for the error messages.
        size: the checkpoint's :class:`mfg_lightning.run.checkpoints.ModelSize`, checked against a
            given dataset's ``height`` × ``width``; None: not checked.
        overrides: keys set on the dataset config (e.g. ``eval_batch_size``). A ``dataset_cfg``
            without ``_target_`` (loader settings only, as ``trainer=gpu`` sets) is read as more
            of them, on the stored dataset.

    Raises:
        CheckpointSizeError: the given dataset delivers another resolution than the model takes.
        ValueError: neither is there.
    """
    from mfg_lightning.run.checkpoints import CheckpointSizeError

    if dataset_cfg is not None and "_target_" not in dataset_cfg:
        # Settings without a dataset (trainer=gpu's loader workers and pinned memory): they
        # apply to the checkpoint's own dataset rather than replace it.
        partial = OmegaConf.to_container(dataset_cfg, resolve=True)
        dataset_cfg, overrides = None, {**partial, **overrides}
    if dataset_cfg is not None and size is not None:
        given = (int(dataset_cfg.height), int(dataset_cfg.width))
        if given != (size.height, size.width):
            raise CheckpointSizeError(
                f"checkpoint {ckpt_path} holds an MFG with {size}, but the dataset delivers "
                f"{given[0]}×{given[1]} inputs: pass dataset.height={size.height} "
                f"dataset.width={size.width}, or omit dataset= to use the checkpoint's own"
            )
    if dataset_cfg is None and stored is None:
        raise ValueError(
            f"{ckpt_path} stores no dataset config and has no run directory config.yaml "
            "beside it: pass dataset=<name> (e.g. dataset=synthetic)"
        )
    chosen = dataset_cfg if dataset_cfg is not None else OmegaConf.create(stored)
    return instantiate(OmegaConf.merge(chosen, overrides) if overrides else chosen)


def log_hyperparameters(loggers: list[Any], hparams: dict[str, Any]) -> None:
    """The run's settings (``train.flat_hparams``) to every logger when the run starts, so that
    a run that crashes still shows what it was. TensorBoard is left for
    :func:`log_final_metrics`: its HParams view pairs the settings with the final metrics in
    one record."""
    from lightning.pytorch.loggers import TensorBoardLogger

    for lg in loggers:
        if not isinstance(lg, TensorBoardLogger):
            lg.log_hyperparams(hparams)


def log_final_metrics(
    loggers: list[Any], hparams: dict[str, Any], metrics: dict[str, Any], step: int
) -> None:
    """The run's final metrics (the last validation's ``val/*`` and the test's ``test/*``) to
    every logger, in the place each one shows a run's result, then close the W&B run.

    * TensorBoard: ``log_hyperparams(hparams, metrics)``, the HParams view's settings and
      results of the run;
    * CSV, MLflow, W&B and any other Lightning logger: ``log_metrics`` at the last step (the last
      row of CSV's ``metrics.csv``; MLflow's latest value of each metric; W&B's run summary).
    """
    from lightning.pytorch.loggers import TensorBoardLogger, WandbLogger

    values = {k: float(v) for k, v in metrics.items()}
    for lg in loggers:
        if isinstance(lg, TensorBoardLogger):
            lg.log_hyperparams(hparams, metrics=values)
        else:
            lg.log_metrics(values, step=step)
        lg.save()
        if isinstance(lg, WandbLogger):
            # Lightning never finishes a W&B run; the next job of a multirun would log into it.
            lg.experiment.finish()


def keep_csv_metrics(loggers: list[Any]) -> list[Path]:
    """Before a resumed run logs: move each CSVLogger's ``metrics.csv`` aside to
    ``metrics.part<NNN>.csv`` (the next free number), which Lightning's CSV writer would
    otherwise delete when it starts, so that the learning curve survives every resume
    (:func:`read_csv_metrics` reads the parts and the current file in order). Returns the
    files written."""
    from lightning.pytorch.loggers import CSVLogger

    kept = []
    for lg in loggers:
        if not isinstance(lg, CSVLogger):
            continue
        current = Path(lg.log_dir) / "metrics.csv"
        if not current.is_file():
            continue
        n = len(list(current.parent.glob("metrics.part*.csv"))) + 1
        target = current.with_name(f"metrics.part{n:03d}.csv")
        current.replace(target)
        kept.append(target)
        log.info("resumed: the earlier CSV log is kept as %s", target)
    return kept


def read_csv_metrics(log_dir: Path) -> list[dict[str, str]]:
    """Every row a CSVLogger wrote under ``log_dir`` (searched recursively), across resumes: the
    parts :func:`keep_csv_metrics` moved aside, oldest first, then each ``metrics.csv``. Values
    stay strings as the CSV holds them ("" where a row lacks a column)."""
    import csv

    files = sorted(
        [*log_dir.glob("**/metrics.part*.csv"), *log_dir.glob("**/metrics.csv")],
        key=lambda p: (str(p.parent), p.name == "metrics.csv", p.name),
    )
    rows: list[dict[str, str]] = []
    for path in files:
        with path.open(newline="") as fh:
            rows += list(csv.DictReader(fh))
    return rows


def finish_stale_logger_runs() -> None:
    """End a W&B run that an earlier job of this process left open by failing, so that this
    job's logger starts its own run (Lightning reuses any open one)."""
    import sys

    wandb = sys.modules.get("wandb")  # imported only by a W&B logger: no import otherwise
    if wandb is not None and getattr(wandb, "run", None) is not None:
        log.warning("finishing the W&B run %s left open by a failed job", wandb.run.id)
        wandb.finish(exit_code=1)


def test_metrics(trainer: L.Trainer) -> dict[str, float | None]:
    """The ``test/*`` metrics of the trainer's last ``test`` as JSON-safe floats."""
    return {
        k: finite_or_none(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")
    }


def write_metrics(path: Path, metrics: dict[str, Any], extra: dict[str, Any] | None = None) -> dict:
    """Write ``metrics.json``: ``{"metrics": {...}, **extra}`` with plain floats."""
    payload = {"metrics": {k: finite_or_none(v) for k, v in sorted(metrics.items())}}
    payload.update(extra or {})
    atomic_write_text(path, json.dumps(payload, indent=2) + "\n")
    return payload


def _git(*args: str) -> str | None:
    """``git <args>``'s output in the source tree the package was imported from (None where
    that is no git checkout or git fails)."""
    try:
        out = subprocess.run(
            ["git", *args],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout if out.returncode == 0 else None


def git_commit() -> str | None:
    """The commit of the source tree the package was imported from, if it is a git checkout."""
    return (_git("rev-parse", "HEAD") or "").strip() or None


def git_dirty() -> bool:
    """Whether that checkout has uncommitted changes to tracked files (a result measured on it
    names its commit with ``+dirty``: that commit alone does not rebuild the code measured)."""
    return bool((_git("status", "--porcelain", "--untracked-files=no") or "").strip())


def run_info() -> dict[str, Any]:
    """Version information stored with every run, and the CPU kind it ran on."""
    import torch

    from mfg_lightning import __version__

    return {
        "mfg_lightning": __version__,
        "git_commit": git_commit(),
        "torch": torch.__version__,
        "lightning": L.__version__,
        "cpu_kind": cpu_kind(),
    }
