"""What makes a training run survive being stopped: exact resumption, safe checkpoints, SIGTERM.

* The training data order that resumes mid-epoch lives with the data:
  :class:`mfg_lightning.data.resumable_loader.ResumableDataLoader`.
* :class:`AtomicCheckpointIO`: writes checkpoints through :mod:`mfg_lightning.core.atomic`
  (temporary file, fsync, ``os.replace``): a kill or a full disk during a save leaves the
  previous file intact; a failed write is one :class:`StorageError` naming the file; an
  unreadable checkpoint is a :class:`~mfg_lightning.run.checkpoints.CheckpointError`, and so is
  one that holds anything but tensors and plain data (it is never unpickled).
* :class:`LastCheckpoint`: ``checkpoints/last.ckpt`` every N minutes and/or every N steps, at the
  end, and on SIGTERM or Ctrl-C (SIGTERM is what SLURM sends at the time limit: the current step
  finishes, the checkpoint is saved, the run stops); ``ckpt_path=last`` or ``resume=true``
  continues from it. It is saved where Lightning resumes it exactly: after a training step, or
  after the validation that follows it.
* :func:`storage_error`: a full disk is one :class:`StorageError` line naming the file.

Resumption is exact on one device (tests/test_resume.py compares weights and metrics with an
uninterrupted run) and under DDP, where every process resumes its share of the epoch's order
(tests/test_ddp_faults.py compares the test metrics of a 2-process run stopped by SIGTERM and
resumed with those of an uninterrupted one). Under DDP, SIGTERM stops every process after the
same step (:mod:`mfg_lightning.run.together`), so that the collective save lines up.
"""

from __future__ import annotations

import errno
import io
import logging
import os
import re
import shutil
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import Checkpoint
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities.exceptions import SIGTERMException

from mfg_lightning.core.atomic import atomic_write_bytes
from mfg_lightning.core.errors import UserError

log = logging.getLogger(__name__)

__all__ = [
    "AtomicCheckpointIO",
    "LastCheckpoint",
    "StorageError",
    "storage_error",
]

# The temporary file name of mfg_lightning.core.atomic: ".<target name>.<uuid4 hex>.tmp".
_ATOMIC_TEMPORARY = re.compile(r"\.(.+)\.[0-9a-f]{32}\.tmp")
# errno values that mean "the file system has no room for this write".
_NO_SPACE = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


# --------------------------------------------------------------------------------------------
# Checkpoint files
# --------------------------------------------------------------------------------------------


class StorageError(UserError):
    """Writing a run's output failed for a reason outside the program (full disk, permissions).

    The message names the file and, for a full disk, how much space is left.
    """


def _human_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def storage_error(
    path: str | os.PathLike[str] | None, err: OSError, what: str = "file", hint: str = ""
) -> StorageError:
    """A :class:`StorageError` for a failed write of ``path``, saying what is left of the disk
    when it is full. A temporary file of :mod:`mfg_lightning.core.atomic` (``.<name>.<hex>.tmp``)
    is reported as the file it was going to become. ``path`` is None when the operating system
    did not say (a failed ``write`` names no file): then ``hint`` says where the run writes."""
    full = err.errno in _NO_SPACE
    if path is None:
        reason = "no space left on device" if full else (err.strerror or str(err))
        return StorageError(f"cannot write a {what}: {reason}" + (f" ({hint})" if hint else ""))
    path = Path(path)
    temporary = _ATOMIC_TEMPORARY.fullmatch(path.name)
    if temporary:
        path = path.with_name(temporary.group(1))
    if full:
        try:
            free = f"{_human_bytes(shutil.disk_usage(path.parent).free)} free"
        except OSError:
            free = "free space unknown"
        reason = f"no space left on device ({free} in {path.parent})"
    else:
        reason = err.strerror or str(err)
    return StorageError(
        f"cannot write {what} {path}: {reason}; the previous {what} there, if any, is unchanged"
    )


def _is_local(path: str | os.PathLike[str]) -> bool:
    return "://" not in str(path) or str(path).startswith("file://")


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint IO that never leaves a half-written or unreadable checkpoint.

    The checkpoint is serialised in memory, written to a temporary file beside the target,
    fsynced and renamed over it (:func:`mfg_lightning.core.atomic.atomic_write_bytes`): a process
    killed during the save, or a disk that fills up, leaves the previous file as it was. A failed
    write raises :class:`StorageError` naming the checkpoint; a checkpoint that cannot be read
    raises :class:`~mfg_lightning.run.checkpoints.CheckpointError`. Reading is safe by default:
    unless
    the caller passes ``weights_only=False`` explicitly, only tensors and plain data are unpickled
    (:func:`mfg_lightning.run.checkpoints.safe_unpickling`), so resuming from a checkpoint someone
    else wrote cannot run their code. Remote (``fsspec`` URL) paths fall back to Lightning's own
    writer.
    """

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None
    ) -> None:
        if storage_options is not None or not _is_local(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        local = Path(str(path).removeprefix("file://"))
        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        try:
            atomic_write_bytes(local, buffer.getvalue())
        except OSError as err:
            raise storage_error(local, err, "checkpoint") from err

    def load_checkpoint(
        self, path: Any, map_location: Any = lambda storage, loc: storage, weights_only: Any = None
    ) -> dict[str, Any]:
        from mfg_lightning.run.checkpoints import safe_unpickling, unreadable_checkpoint

        weights_only = True if weights_only is None else weights_only
        try:
            with safe_unpickling():
                return super().load_checkpoint(
                    path, map_location=map_location, weights_only=weights_only
                )
        except FileNotFoundError:
            raise
        except Exception as err:  # torch/zip/pickle errors of a truncated, foreign or unsafe file
            raise unreadable_checkpoint(path, err) from err


# --------------------------------------------------------------------------------------------
# The resumable checkpoint: periodic, at the end, and on SIGTERM
# --------------------------------------------------------------------------------------------


def _validation_follows(trainer: L.Trainer) -> bool | None:
    """Whether the fit loop validates right after the training step that just ended.

    Asked of Lightning's own decision (a private method, hence None when it cannot be asked).
    """
    try:
        loop = trainer.fit_loop.epoch_loop
        return bool(loop._should_check_val_fx(trainer.fit_loop._data_fetcher))
    except Exception:  # another Lightning version: the caller falls back to saving twice
        return None


class LastCheckpoint(Checkpoint):
    """Keep ``<dirpath>/last.ckpt`` up to date: the checkpoint a stopped run resumes from.

    Saved every ``every_minutes`` of wall time and every ``every_n_train_steps`` optimiser steps
    (whichever comes first), when training ends, and when SIGTERM stops the fit (Lightning's
    SIGTERM handler lets the current step finish and then stops the loop; the file is saved just
    before). Lightning's ``ModelCheckpoint(save_last=True)`` refreshes its "last" file only when
    it saves a top-k one too; this file is always the latest state. Nothing is saved under
    ``fast_dev_run``.

    When to save so that the resumed run is the uninterrupted one: a checkpoint taken at the end
    of a training step is resumed correctly even at the end of an epoch, but Lightning treats the
    validation of that step as done; so a step followed by a validation is saved after the
    validation (and after ``ModelCheckpoint`` has recorded its score: this callback must come
    after it, which :func:`mfg_lightning.train` ensures). SIGTERM during a validation lets the
    validation finish first, so its metrics and the best-checkpoint choice see all of it.

    Why wall time as well as steps: the full state (weights and Adam's moments, ~150 MB for
    the default network) is written with an fsync. A step period that suits a CPU (the config's
    300 steps, about a minute there) would have a GPU, which takes 100 steps in under a second,
    spend a large share of its time saving (the GPU trainer configs turn it off); a period in
    minutes costs the same share of any device's time. The time is checked
    after each step, so a save still lands where a resumed run continues exactly. Under DDP
    every process must save together (``Trainer.save_checkpoint`` is collective) while their
    clocks disagree: rank 0's clock decides, broadcast at the logging steps
    (every ``trainer.log_every_n_steps``), where the host waits for the loggers anyway, so
    that the other steps have no collective.
    SIGTERM is acted on when every process has agreed on it
    (:class:`~mfg_lightning.run.together.StopTogether` sets Lightning's flag after the same step
    everywhere), so the save on SIGTERM is collective too.

    Args:
        dirpath: the run's checkpoint directory (``<run dir>/checkpoints``).
        every_n_train_steps: save period in optimiser steps (0: none by steps).
        filename: the file written; ``last.ckpt`` is what ``ckpt_path=last`` resumes from.
        every_minutes: save period in minutes of wall time since the last save or the start of
            the fit (None: none by time). With both periods 0/None the file is saved only at
            the end and on SIGTERM.
    """

    def __init__(
        self,
        dirpath: str | os.PathLike[str],
        every_n_train_steps: int = 100,
        filename: str = "last.ckpt",
        every_minutes: float | None = None,
    ) -> None:
        if every_n_train_steps < 0:
            raise ValueError(
                f"callbacks.last_checkpoint.every_n_train_steps must be >= 0, "
                f"got {every_n_train_steps}"
            )
        if every_minutes is not None and not every_minutes > 0:
            raise ValueError(
                "callbacks.last_checkpoint.every_minutes must be positive (null: no saves by "
                f"time), got {every_minutes}"
            )
        self.path = Path(dirpath) / filename
        self.every_n_train_steps = int(every_n_train_steps)
        self.every_seconds = None if every_minutes is None else 60.0 * float(every_minutes)
        # time.monotonic, or a test's clock: when the last save (or the fit's start) was
        self.clock = time.monotonic
        self._last_save_time: float | None = None
        self._saved_step: int | None = None
        # A step whose save waits for the validation that follows it.
        self._after_validation: int | None = None
        self._sigterm_deferred = False
        #: ``val/*`` metrics of the last validation of the fit, kept in the checkpoint so that a
        #: run resumed after its last validation still reports them
        self.validation_metrics: dict[str, float] = {}

    @property
    def state_key(self) -> str:
        return self._generate_state_key(path=str(self.path), every=self.every_n_train_steps)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        # A process killed during a save leaves its temporary file (never the checkpoint
        # itself, see AtomicCheckpointIO); the next run of the same directory removes them.
        if stage == "fit" and trainer.is_global_zero and self.path.parent.is_dir():
            for stale in self.path.parent.glob(".*.ckpt.*.tmp"):
                stale.unlink(missing_ok=True)

    def _save(self, trainer: L.Trainer) -> None:
        trainer.save_checkpoint(self.path, weights_only=False)  # full state: resumable
        self._saved_step = trainer.global_step
        self._last_save_time = self.clock()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # The time period counts from the start of this fit: a resumed run has just loaded
        # what it would save.
        self._last_save_time = self.clock()

    def _time_is_up(self, trainer: L.Trainer) -> bool:
        """Whether ``every_minutes`` have passed since the last save; the same answer on every
        process (see the class's notes on DDP)."""
        if self.every_seconds is None or self._last_save_time is None:
            return False
        if trainer.world_size == 1:
            return self.clock() - self._last_save_time >= self.every_seconds
        every = int(trainer.log_every_n_steps) or 20
        if trainer.global_step % every:  # rank 0's clock is broadcast at the logging steps
            return False
        up = self.clock() - self._last_save_time >= self.every_seconds
        return bool(trainer.strategy.broadcast(up, src=0))

    def _fitting(self, trainer: L.Trainer) -> bool:
        return (
            trainer.state.fn == TrainerFn.FITTING
            and not trainer.sanity_checking
            and not trainer.fast_dev_run
        )

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        if not self._fitting(trainer):
            return
        step, n = trainer.global_step, self.every_n_train_steps
        missed = self._after_validation is not None and self._after_validation != step
        # Asked at every step on every process alike (under DDP it may be a collective).
        timed = self._time_is_up(trainer) and step != self._saved_step
        due = (n and step % n == 0 and step != self._saved_step) or timed
        due = due or trainer.received_sigterm
        if not (due or missed):
            return
        follows = _validation_follows(trainer)
        if follows is not True or missed:
            self._save(trainer)
        # If a validation runs after this step, save (again) once it is done.
        self._after_validation = step if follows is not False else None

    def on_validation_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        # Lightning would stop at the next validation batch; hold the signal back until the
        # validation is complete (on_validation_end hands it back).
        connector = getattr(trainer, "_signal_connector", None)
        if self._fitting(trainer) and trainer.received_sigterm and connector is not None:
            connector.received_sigterm = False
            self._sigterm_deferred = True

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self._fitting(trainer):
            return
        step = trainer.global_step
        self.validation_metrics = {
            k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")
        }
        if self._sigterm_deferred:
            trainer._signal_connector.received_sigterm = True
            self._sigterm_deferred = False
            self._after_validation = step
        if self._after_validation == step:
            self._save(trainer)
        self._after_validation = None

    def state_dict(self) -> dict[str, Any]:
        return {"validation_metrics": dict(self.validation_metrics)}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.validation_metrics = dict(state_dict.get("validation_metrics", {}))

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.fast_dev_run and trainer.global_step != self._saved_step:
            self._save(trainer)

    def on_exception(
        self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException
    ) -> None:
        if not isinstance(exception, SIGTERMException) or not self._fitting(trainer):
            return
        # Normally saved already at the end of the step (or of its validation). SIGTERMException
        # is raised only inside the fit loops, i.e. after a resumed run has restored its
        # checkpoint: what is saved here is never older than what was loaded.
        if trainer.global_step != self._saved_step:
            self._save(trainer)
        log.warning(
            "SIGTERM or Ctrl-C: stopped at step %d and saved %s; resume with ckpt_path=last "
            "(or resume=true) and the same hydra.run.dir",
            trainer.global_step,
            self.path,
        )
