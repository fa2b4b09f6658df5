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
  continues from ``last.ckpt``, exactly where it stopped (docs/scaling.md has the script).

Outside a SLURM job (no ``SLURM_JOB_ID``) none of this does anything.
"""

from __future__ import annotations

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
        self._previous: Any = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit" or job_id() is None:
            return
        if threading.current_thread() is not threading.main_thread():
            log.warning("not in the main thread: SLURM's requeue signal is not handled")
            return
        self._previous = signal.signal(self.signum, self._on_signal)

    def _restore(self) -> None:
        if self._previous is not None and threading.current_thread() is threading.main_thread():
            signal.signal(self.signum, self._previous)
            self._previous = None

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage == "fit":
            self._restore()

    def on_exception(
        self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException
    ) -> None:
        # a fit ended by an exception (SIGTERM's included) gets no teardown hook
        self._restore()

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        """The requeue signal: remembered, then handled as SIGTERM (whatever handles SIGTERM
        now: the stop that every process agrees on)."""
        log.warning("SLURM's requeue signal (%s): stopping to requeue", signal.Signals(signum).name)
        self.requested = True
        handler = signal.getsignal(signal.SIGTERM)
        if callable(handler):
            handler(signal.SIGTERM, frame)

    def requeue(self, trainer: L.Trainer) -> bool:
        """After the run stopped on the requeue signal (``last.ckpt`` saved): the first process
        asks SLURM to requeue the job. Returns whether it was asked and accepted."""
        if not self.requested or not trainer.is_global_zero:
            return False
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
        return True


def _signal_named(name: str) -> signal.Signals:
    """``signal.Signals`` of a name (``SIGUSR1`` or ``USR1``)."""
    key = name.upper()
    key = key if key.startswith("SIG") else f"SIG{key}"
    try:
        return signal.Signals[key]
    except KeyError:
        raise ValueError(f"no signal named {name!r} on this system") from None
