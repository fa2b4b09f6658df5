"""SLURM: a job that reaches its time limit is requeued and resumes through the run's own resume.

Lightning's auto-requeue (``SLURMEnvironment(auto_requeue=True)``, what it picks by itself inside
an allocation) saves an ``hpc_ckpt_<n>.ckpt`` from inside the signal handler, in the middle of
whatever the process is doing (under DDP, of a collective), and the requeued job resumes from that
file on its own, bypassing ``last.ckpt`` and ``resume=true``. Here instead:

* :func:`slurm_environment` gives Lightning the SLURM environment with its auto-requeue off
  (:func:`mfg_lightning.run.runs.build_trainer` adds it to every Trainer inside an allocation);
* :class:`SlurmRequeue` takes the requeue signal (``#SBATCH --signal=SIGUSR1@120``: SLURM sends it
  that many seconds before the time limit) as a SIGTERM: every process stops after the same step
  and ``last.ckpt`` is saved (:class:`~mfg_lightning.run.together.StopTogether`,
  :class:`~mfg_lightning.run.callbacks.LastCheckpoint`). Once the run has ended so, the first
  process asks SLURM to requeue the job (``scontrol requeue <job id>``;
  :func:`~mfg_lightning.run.together.ending_together` calls :meth:`SlurmRequeue.requeue`), and
  every process exits with 143;
* the requeued job runs the same script: with the same ``hydra.run.dir`` and ``resume=true`` it
  continues from ``last.ckpt``, exactly where it stopped (docs/scaling.md has the script);
* the signal during the test phase does not stop it: it is recorded, the test runs to its end,
  ``metrics.json`` is written, and the first process requeues the job as it exits (the requeued
  job finds the training done and tests again). Before, the signal's default action ended every
  task, without ``metrics.json`` and without a requeue;
* the signal may reach one process only: the processes agree on it (one all-reduce when the run
  stops, or at the end of the test), so that the first process requeues the job, once.

Outside a SLURM job (no ``SLURM_JOB_ID``) none of this does anything.
"""

from __future__ import annotations

import atexit
import logging
import os
import re
import signal
import subprocess
import threading
from collections.abc import Sequence
from types import FrameType
from typing import Any

import lightning as L
import torch
import torch.distributed as dist
from lightning.fabric.plugins.environments import SLURMEnvironment

log = logging.getLogger(__name__)

__all__ = ["SlurmRequeue", "job_id", "slurm_environment"]


def job_id(environ: dict[str, str] | None = None) -> str | None:
    """The id ``scontrol requeue`` takes for this job: ``<array job>_<task>`` in a job array,
    else ``SLURM_JOB_ID``; None outside SLURM."""
    env = os.environ if environ is None else environ
    array = env.get("SLURM_ARRAY_JOB_ID")
    if array is not None and "SLURM_ARRAY_TASK_ID" in env:
        return f"{array}_{env['SLURM_ARRAY_TASK_ID']}"
    return env.get("SLURM_JOB_ID")


def slurm_environment() -> SLURMEnvironment | None:
    """Lightning's SLURM environment with its auto-requeue off, where Lightning would pick the
    SLURM environment by itself (tasks started by ``srun``, not by torchrun inside them); else
    None."""
    from lightning.fabric.plugins.environments import TorchElasticEnvironment

    if TorchElasticEnvironment.detect() or not SLURMEnvironment.detect():
        return None
    return SLURMEnvironment(auto_requeue=False)


class SlurmRequeue(L.Callback):
    """Requeue a SLURM job stopped by its requeue signal, through ``last.ckpt`` and
    ``resume=true`` (see the module's docstring).

    Args:
        signal: the requeue signal's name (``#SBATCH --signal=<name>@<seconds>``).
        command: the requeue command, the job id appended (``scontrol requeue``).
    """

    def __init__(
        self, signal: str = "SIGUSR1", command: Sequence[str] = ("scontrol", "requeue")
    ) -> None:
        try:
            self.signum = _signal_named(signal)
        except ValueError as err:
            raise ValueError(f"callbacks.slurm_requeue.signal: {err}") from None
        self.command = list(command)
        #: the requeue signal reached this process
        self.requested = False
        #: the job was requeued (by this process)
        self.requeued = False
        self._previous: Any = None
        self._installed = False
        self._stage: str | None = None
        self._at_exit = False

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage not in ("fit", "test") or job_id() is None:
            return
        if threading.current_thread() is not threading.main_thread():
            log.warning("not in the main thread: SLURM's requeue signal is not handled")
            return
        self._stage = stage
        if not self._installed:
            self._previous = signal.signal(self.signum, self._on_signal)
            self._installed = True

    def _restore(self) -> None:
        if self._installed and threading.current_thread() is threading.main_thread():
            # (None: a handler not installed from Python, which signal.signal cannot put back)
            signal.signal(self.signum, signal.SIG_DFL if self._previous is None else self._previous)
            self._previous, self._installed = None, False

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage in ("fit", "test"):
            self._restore()
            self._stage = None

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # Every process ends its test here: the one collective that makes a signal seen by any
        # of them the first process's. The requeue waits for metrics.json, written after the test.
        if self._stage != "test" or not self._agreed(trainer) or not trainer.is_global_zero:
            return
        if not self._at_exit:
            self._at_exit = True
            atexit.register(self._requeue_once)
            log.warning("SLURM's requeue signal during the test: requeuing the job as it exits")

    def on_exception(
        self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException
    ) -> None:
        # a fit ended by an exception (SIGTERM's included) gets no teardown hook
        self._restore()

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        """The requeue signal: remembered; during a fit, then handled as SIGTERM (whatever
        handles SIGTERM now: the stop that every process agrees on); during the test, only
        remembered (the test ends, then the job is requeued)."""
        name = signal.Signals(signum).name
        self.requested = True
        if self._stage != "fit":
            log.warning("SLURM's requeue signal (%s) during the test: requeuing after it", name)
            return
        log.warning("SLURM's requeue signal (%s): stopping to requeue", name)
        handler = signal.getsignal(signal.SIGTERM)
        if callable(handler):
            handler(signal.SIGTERM, frame)

    def _agreed(self, trainer: L.Trainer) -> bool:
        """Whether the requeue signal reached any process of the run: one all-reduce (max),
        called by every process at the same point; this process's own flag without a process
        group, or where the collective fails (a peer gone)."""
        if trainer.world_size == 1 or not (dist.is_available() and dist.is_initialized()):
            return self.requested
        flag = torch.tensor(float(self.requested), device=trainer.strategy.root_device)
        try:
            agreed = bool(trainer.strategy.reduce(flag, reduce_op="max").item())
        except Exception as err:  # (RuntimeError, DistBackendError): never hide the stop
            log.warning("the processes could not agree on SLURM's requeue signal: %s", err)
            return self.requested
        if agreed and not self.requested:
            log.info("SLURM's requeue signal reached another process")
        return agreed

    def requeue(self, trainer: L.Trainer) -> bool:
        """After the run stopped on SIGTERM or the requeue signal (``last.ckpt`` saved), called
        by every process at the same point: the first process asks SLURM to requeue the job when
        the signal reached any of them during the fit. Returns whether it was asked and
        accepted."""
        from lightning.pytorch.trainer.states import TrainerFn

        if self._stage is None and not self.requested:
            return False  # outside SLURM, or not a stage this callback handles
        # Only a fit stops together (every process here, after the same step): a collective
        # anywhere else could wait for a process that is not coming.
        fitting = trainer.state.fn == TrainerFn.FITTING
        requested = self._agreed(trainer) if fitting else self.requested
        if not requested or not trainer.is_global_zero:
            return False
        return self._requeue_once()

    def _requeue_once(self) -> bool:
        """``scontrol requeue <job id>``, once per callback. Returns whether it was accepted."""
        if self.requeued:
            return True
        job = job_id()
        if job is None or not re.fullmatch(r"[0-9_]+", job):
            log.warning("not requeued: SLURM job id %r", job)
            return False
        command = [*self.command, job]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired) as err:
            log.error("requeuing SLURM job %s failed: %s", job, err)
            return False
        if done.returncode != 0:
            log.error(
                "requeuing SLURM job %s failed (%s exited with %d): %s",
                job, " ".join(command), done.returncode, done.stderr.strip(),
            )  # fmt: skip
            return False
        log.warning("requeued SLURM job %s: it resumes from last.ckpt (resume=true)", job)
        self.requeued = True
        return True


def _signal_named(name: str) -> signal.Signals:
    """``signal.Signals`` of a name (``SIGUSR1`` or ``USR1``)."""
    key = name.upper()
    key = key if key.startswith("SIG") else f"SIG{key}"
    try:
        return signal.Signals[key]
    except KeyError:
        raise ValueError(f"no signal named {name!r} on this system") from None
