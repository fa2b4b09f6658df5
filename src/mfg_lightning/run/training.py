"""One training run from a composed ``train`` config: build everything with
``hydra.utils.instantiate``, fit, test the best checkpoint, write ``metrics.json``.

:mod:`mfg_lightning.train` is its command line; the reproduction study calls :func:`train` for
each of its models. A run stopped at any point continues exactly where its last checkpoint left
it with ``ckpt_path=last`` or ``resume=true`` and the same ``hydra.run.dir``
(:mod:`mfg_lightning.run.callbacks`: atomic checkpoints, a data order that resumes mid-epoch, a
checkpoint on SIGTERM)."""

from __future__ import annotations

import json
import logging
import os
import sys
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import lightning as L
from filelock import FileLock
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.core.denormals import denormals_flushed
from mfg_lightning.core.host_memory import freed_memory_kept
from mfg_lightning.data.resumable_loader import refuse_other_batches, restarting_epochs
from mfg_lightning.run.callbacks import LastCheckpoint
from mfg_lightning.run.checkpoints import (
    CheckpointError,
    peek_checkpoint,
    saved_loader_places,
    unreadable_checkpoint,
)
from mfg_lightning.run.precision import PRECISION_AUTO, check_precision
from mfg_lightning.run.run_choices import choice_overrides, resolve_run_choices
from mfg_lightning.run.runs import (
    build_model,
    build_trainer,
    finish_stale_logger_runs,
    instantiate_list,
    keep_csv_metrics,
    log_final_metrics,
    log_hyperparameters,
    run_info,
    set_baseline,
    write_metrics,
)
from mfg_lightning.run.shared_training import (
    VALIDATIONS_DIR,
    best_checkpoint,
    keep_validation_weights,
    read_training,
    shared_folder,
    training_config,
    training_id,
)
from mfg_lightning.run.together import ending_together

# The command line's logger: a run's log reads the same whoever started it.
log = logging.getLogger("mfg_lightning.train")


def resolve_ckpt_path(ckpt_path: str | None, output_dir: Path, resume: bool = False) -> str | None:
    """The checkpoint to resume from, or None for a fresh start.

    ``ckpt_path="last"`` means ``<run dir>/checkpoints/last.ckpt``; without ``ckpt_path``,
    ``resume=True`` picks that file up if it exists (a requeued job resumes, a first one starts).
    A missing file named by ``ckpt_path`` or an unreadable one is a clear error: corrupt or
    unsafe, as :func:`~mfg_lightning.run.checkpoints.unreadable_checkpoint` says.
    """
    last = output_dir / "checkpoints" / "last.ckpt"
    if ckpt_path is None:
        if not (resume and last.is_file()):
            return None
        path = last
    else:
        path = last if ckpt_path == "last" else Path(ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path: checkpoint not found: {path}")
    # torch.save writes a zip archive whose directory sits at the end of the file, so a file cut
    # short (a save killed by an older, non-atomic writer) fails this cheap check.
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"ckpt_path: {unreadable_checkpoint(path)}")
    log.info("resuming from %s", path)
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


def check_trainer_settings(cfg: DictConfig) -> None:
    """Refuse what the run cannot do before anything is built or written, and settle the
    trainer settings that contradict each other.

    * ``trainer.precision``: ``auto`` (made concrete by :func:`run_config`; the run's
      ``config.yaml`` records what it ran in), ``32-true``, ``bf16-mixed`` or ``16-mixed``
      (:func:`mfg_lightning.run.precision.check_precision`; a ``*-true`` low precision is one
      ``error:`` line naming the key).
    * ``trainer.deterministic=true`` with ``trainer.benchmark=true`` (``trainer=gpu``'s): cuDNN's
      benchmark picks its convolution algorithms by timing them, so ``deterministic`` wins and
      ``benchmark`` is turned off (in the config that ``config.yaml`` records).

    Raises:
        ValueError: naming the key.
    """
    trainer = cfg.get("trainer") or {}
    precision = trainer.get("precision", "32-true")
    if str(precision) != PRECISION_AUTO:
        check_precision(precision)
    if trainer.get("deterministic") and trainer.get("benchmark"):
        log.info("trainer.deterministic=%s: trainer.benchmark turned off", trainer.deterministic)
        with open_dict(cfg):
            cfg.trainer.benchmark = False


#: The environment variables Lightning's DDP launcher sets in the process that starts the others
_LAUNCH_VARIABLES = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE")


def run_config(cfg: DictConfig, ckpt_path: str | None = None) -> tuple[DictConfig, str | None]:
    """The run's own config, resolved once and then read-only: ``cfg`` with every interpolation
    resolved, the trainer settings checked (:func:`check_trainer_settings`) and ``auto``
    precision and kernels made concrete (:func:`~mfg_lightning.run.run_choices.
    resolve_run_choices`). Nothing changes it afterwards; ``config.yaml`` records it. Returns it
    and where the precision and kernels came from (None: neither was ``auto``)."""
    own = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    check_trainer_settings(own)
    source = resolve_run_choices(own, ckpt_path)
    OmegaConf.set_readonly(own, True)
    return own, source


@contextmanager
def children_run_this_job(trainer: L.Trainer, cfg: DictConfig) -> Iterator[None]:
    """Where the trainer starts its own DDP processes, they run this job with this process's
    resolved precision and kernels; afterwards this process is ready for a next job.

    Lightning starts each of them as ``python -m <module> <sys.argv[1:]>
    hydra.run.dir=<hydra.run.dir>``. For the block, ``sys.argv`` ends with the resolved values
    (:func:`~mfg_lightning.run.run_choices.choice_overrides`), so every process computes as the
    first one chose. In a multirun ``sys.argv`` holds ``-m`` and the whole sweep, and
    ``hydra.run.dir`` is not this job's directory: there ``sys.argv`` is this job's own overrides
    and ``hydra.run.dir`` this job's output directory. Afterwards both are put back, and, since
    the basic launcher runs the next job in this process, the job's process group is destroyed
    (its peers have exited) and the launch variables Lightning set here are removed (with
    ``LOCAL_RANK`` set, the next trainer would wait for processes started by someone else).
    Nothing changes where processes are started by others (SLURM, torchrun) or not at all."""
    import torch.distributed as dist
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    spawns = trainer.world_size > 1 and not getattr(
        trainer.strategy.cluster_environment, "creates_processes_externally", True
    )
    if not spawns:
        yield
        return
    multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    argv = list(sys.argv)
    env = {name: os.environ.get(name) for name in _LAUNCH_VARIABLES}
    hc = HydraConfig.get() if multirun else None
    run_dir = None if hc is None else hc.run.dir
    given = list(hc.overrides.task) if hc is not None else argv[1:]
    resolved = choice_overrides(cfg)
    keys = {o.split("=", 1)[0] for o in resolved}
    sys.argv = [argv[0], *(o for o in given if o.split("=", 1)[0] not in keys), *resolved]
    if hc is not None:
        with read_write(hc):
            hc.run.dir = hc.runtime.output_dir
    try:
        yield
    finally:
        sys.argv = argv
        if hc is not None:
            with read_write(hc):
                hc.run.dir = run_dir
        if multirun:
            if dist.is_available() and dist.is_initialized():
                dist.destroy_process_group()
            for name, value in env.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit and test as configured. Returns the final metrics (``val/*`` and ``test/*``)."""
    # Denormals flushed first, before torch's thread pool starts: its threads copy the flags when
    # they start (mfg_lightning.core.denormals); every step's freed tensors reused, not
    # page-faulted back (mfg_lightning.core.host_memory). Both set back when the training
    # returns, for the process that called it (a notebook, a test). resume_restart_epoch: a
    # resume inside an epoch with other batches restarts that epoch instead of being refused
    # (mfg_lightning.data.resumable_loader).
    with (
        denormals_flushed(bool(cfg.get("flush_denormals", True))),
        freed_memory_kept(bool(cfg.get("keep_freed_memory", True))),
        restarting_epochs(bool(cfg.get("resume_restart_epoch"))),
    ):
        return _train(cfg)


def _train(cfg: DictConfig) -> dict[str, Any]:
    output_dir = Path(cfg.paths.output_dir)
    ckpt_path = resolve_ckpt_path(cfg.get("ckpt_path"), output_dir, bool(cfg.get("resume")))
    # trainer.precision=auto and model.net.conv_impl=auto made concrete from the committed table
    # (or the run resumed from), bad trainer settings refused; from here on it is read-only
    cfg, choices = run_config(cfg, ckpt_path)
    folder = shared_folder(cfg)
    if folder is None:
        return _fit_and_test(cfg, ckpt_path, choices)[0]
    # A multirun: jobs with equal training configs share one training (run/shared_training.py)
    key = training_id(cfg)
    folder.mkdir(parents=True, exist_ok=True)
    with FileLock(str(folder / f"{key}.lock")):
        done = read_training(folder, key)
        if done is None:
            metrics, record = _fit_and_test(cfg, ckpt_path, choices, keep_validations=True)
            record["config"] = training_config(cfg)
            atomic_write_text(folder / f"{key}.json", json.dumps(record, indent=1) + "\n")
            return metrics
    log.info("the training of this job ran in %s: this job evaluates it", done["run_dir"])
    return evaluate_shared(cfg, done, choices)


def _fit_and_test(
    cfg: DictConfig, ckpt_path: str | None, choices: str | None, keep_validations: bool = False
) -> tuple[dict[str, float], dict[str, Any]]:
    """Fit, test the best checkpoint, write the run's files. Returns the final metrics and what
    a shared training records (:mod:`mfg_lightning.run.shared_training`)."""
    output_dir = Path(cfg.paths.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    L.seed_everything(cfg.seed, workers=True)

    # The dataset checks its data when built: a refused data root writes nothing of the run's.
    datamodule: L.LightningDataModule = instantiate(cfg.dataset)
    resumed = None if ckpt_path is None else peek_checkpoint(ckpt_path)
    if resumed is not None and not cfg.get("resume_restart_epoch"):
        # before the run's files are rewritten: a refused resume leaves them as they were
        for place in saved_loader_places(resumed):
            refuse_other_batches(place, int(cfg.dataset.batch_size))
    atomic_write_text(output_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    info = {
        **run_info(),
        "seed": cfg.seed,
        "resumed_from": ckpt_path,
        "precision_and_kernels_from": choices,
    }
    atomic_write_text(output_dir / "run_info.json", json.dumps(info, indent=2) + "\n")
    model = build_model(cfg)
    if hasattr(model, "set_mean_motion"):  # (MFG's baseline; the flow network has none)
        set_baseline(model, datamodule)
    callbacks = instantiate_list(cfg.get("callbacks"))
    # LastCheckpoint saves after ModelCheckpoint has recorded a validation's score (stable sort).
    callbacks.sort(key=lambda cb: isinstance(cb, LastCheckpoint))
    if keep_validations:  # the weights of every validation, for the jobs sharing this training
        callbacks.append(keep_validation_weights(output_dir))
    finish_stale_logger_runs()
    loggers = instantiate_list(cfg.get("logger"))
    if ckpt_path is not None:
        keep_csv_metrics(loggers)
    trainer = build_trainer(cfg, callbacks, loggers)
    hparams = flat_hparams(cfg)
    log_hyperparameters(loggers, hparams)

    if trainer.world_size > 1 and trainer.is_global_zero:
        # the first process resolved them; the others get them on their command line
        log.info("kernels of all %d processes: trainer.precision=%s, model.net.conv_impl=%s",
                 trainer.world_size, cfg.trainer.precision,
                 OmegaConf.select(cfg, "model.net.conv_impl"))  # fmt: skip
    with children_run_this_job(trainer, cfg):
        start = time.perf_counter()
        with ending_together(trainer):
            trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
        train_seconds = time.perf_counter() - start
        # The last validation's metrics; a run resumed after it has them from the checkpoint.
        last = [cb.validation_metrics for cb in callbacks if isinstance(cb, LastCheckpoint)]
        metrics = {**(last[0] if last else {})}
        metrics.update({k: v for k, v in trainer.callback_metrics.items() if k.startswith("val/")})

        if cfg.get("test"):
            best = getattr(trainer.checkpoint_callback, "best_model_path", "") or None
            if best is None:
                log.warning("no best checkpoint (no validation ran?): testing the current weights")
            with ending_together(trainer):
                trainer.test(model, datamodule=datamodule, ckpt_path=best, weights_only=True)
            metrics.update(
                {k: v for k, v in trainer.callback_metrics.items() if k.startswith("test/")}
            )
        log_final_metrics(loggers, hparams, metrics, trainer.global_step)
        if cfg.get("test") and trainer.is_global_zero:
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
    validations = sorted(str(p) for p in (output_dir / VALIDATIONS_DIR).glob("*.ckpt"))
    record = {"run_dir": str(output_dir), "validations": validations,
              "global_step": trainer.global_step, "train_seconds": train_seconds}  # fmt: skip
    return {k: float(v) for k, v in metrics.items()}, record


def evaluate_shared(cfg: DictConfig, done: dict[str, Any], choices: str | None) -> dict[str, float]:
    """Evaluate a training another job of the multirun ran (``done``: its record): validate
    every validation's weights with this job's settings, test the best by this job's
    ``callbacks.model_checkpoint`` rule, write this job's files. Returns the final metrics,
    those an independent run of this job would return."""
    from lightning.pytorch.callbacks import Checkpoint

    output_dir = Path(cfg.paths.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    L.seed_everything(cfg.seed, workers=True)
    datamodule: L.LightningDataModule = instantiate(cfg.dataset)
    atomic_write_text(output_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    info = {**run_info(), "seed": cfg.seed, "trained_in": done["run_dir"],
            "precision_and_kernels_from": choices}  # fmt: skip
    atomic_write_text(output_dir / "run_info.json", json.dumps(info, indent=2) + "\n")
    model = build_model(cfg)
    if hasattr(model, "set_mean_motion"):
        set_baseline(model, datamodule)
    # the callbacks that evaluate (figures, progress), not those that save or stop a training
    callbacks = [c for c in instantiate_list(cfg.get("callbacks")) if not isinstance(c, Checkpoint)]
    callbacks = [c for c in callbacks if not hasattr(c, "monitor")]
    finish_stale_logger_runs()
    loggers = instantiate_list(cfg.get("logger"))
    trainer = build_trainer(cfg, callbacks, loggers)
    hparams = flat_hparams(cfg)
    log_hyperparameters(loggers, hparams)
    scores = []
    for path in done["validations"]:
        trainer.validate(model, datamodule=datamodule, ckpt_path=path, weights_only=True,
                         verbose=False)  # fmt: skip
        scores.append({k: float(v) for k, v in trainer.callback_metrics.items()
                       if k.startswith("val/")})  # fmt: skip
    rule = cfg.callbacks.model_checkpoint
    best = best_checkpoint(done["validations"], scores, rule.monitor, rule.get("mode", "min"))
    metrics = dict(scores[-1]) if scores else {}
    if cfg.get("test"):
        if best is None:
            log.warning("no best checkpoint (no validation ran?): testing the final weights")
            best = str(Path(done["run_dir"]) / "checkpoints" / "last.ckpt")
        trainer.test(model, datamodule=datamodule, ckpt_path=best, weights_only=True)
        metrics.update(
            {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")}
        )
    log_final_metrics(loggers, hparams, metrics, int(done["global_step"]))
    if cfg.get("test"):
        extra = {"train_seconds": done["train_seconds"], "global_step": done["global_step"],
                 "best_checkpoint": best, "trained_in": done["run_dir"], **run_info()}  # fmt: skip
        write_metrics(output_dir / "metrics.json", metrics, extra)
    return metrics
