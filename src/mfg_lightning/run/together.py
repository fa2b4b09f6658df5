"""Every process of a data-parallel (DDP) run ends together: on SIGTERM, Ctrl-C and an error.

* **SIGTERM.** Lightning's handler makes a collective call inside the signal handler (a broadcast
  that interleaves with whatever collective the process is in: the processes crash, or hang), and
  each process then stops on its own flag, its own step. :class:`StopTogether` replaces the
  handler: it only records the signal (and hands it on once to the processes Lightning started,
  as Lightning's does). The run's per-step agreement
  (:class:`~mfg_lightning.run.agreed_steps.AgreedSteps`, a callback of every run's config)
  turns it into a stop after the same step on every process, where this callback sets
  Lightning's flag: ``LastCheckpoint`` saves there, and Lightning stops there, on
  every process alike. Without a process group the flag is set at once, as Lightning's handler
  does. Lightning's per-step broadcast of rank 0's flag (a collective and a
  host read before every DDP step) is then redundant and is turned off.
* **Ctrl-C.** From the first training step, the first SIGINT is taken as a SIGTERM (the same
  stop after the same step, ``last.ckpt`` saved; exit status 130), without handing it on: a
  terminal's Ctrl-C reaches every process of the run, and the agreement carries a SIGINT sent to
  one. The handler then gives SIGINT back to the operating system, so that a second Ctrl-C ends
  the process at once, even inside a collective or a save (``last.ckpt`` is written atomically:
  the previous one stays). Before the first step Lightning's own handling stays (nothing to save).
* **An error.** The errors the processes agree on (a refused batch, too many non-finite losses)
  are raised by all at the same step. Any other error ends its own process, and
  :func:`ending_together` makes sure that the others end within seconds, not at the process
  group's 30-minute timeout: the failing process leaves a gloo process group (the peers waiting on
  it fail at once), and the process that started the others (``trainer=ddp``: Lightning starts
  them from the first) waits up to :data:`CHILDREN_GRACE` seconds for them, then kills those left.
  Elsewhere the launcher does it (torchrun ends every process when one fails; under SLURM,
  ``srun --kill-on-bad-exit=1``).

DDP's broadcast of the module's buffers before every forward is kept only where a buffer needs it
(:class:`BuffersWhereNeeded`): the buffers this project's modules have are set before training
and equal on every process after DDP's first synchronisation.

Lightning watches the processes it started and kills the first one (SIGKILL) as soon as another
exits with an error status, which a process stopped by SIGTERM (143) or by an agreed error (2)
does on purpose. The first process therefore takes that watch over once an end is agreed or its
own error is raised: it waits for the others, and every process exits with its own status.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from types import FrameType
from typing import Any

import lightning as L
import torch
import torch.distributed as dist
from lightning.pytorch.utilities.exceptions import SIGTERMException
from lightning.pytorch.utilities.rank_zero import rank_prefixed_message

from mfg_lightning.run.agreed_steps import AgreedSteps, Agreement
from mfg_lightning.run.slurm import SlurmRequeue
from mfg_lightning.run.startup import launching

log = logging.getLogger(__name__)

__all__ = ["CHILDREN_GRACE", "BuffersWhereNeeded", "StopTogether", "ending_together"]

#: seconds the first process of ``trainer=ddp`` waits for the others to end after it stopped
#: (they stop at the same step, or their collectives fail once it has left the process group)
CHILDREN_GRACE = 30.0


class StopTogether(L.Callback):
    """SIGTERM and Ctrl-C under DDP: every process stops after the same step (see the module's
    docstring); a second Ctrl-C ends the process at once.

    :func:`mfg_lightning.run.runs.build_trainer` adds it to every Trainer a run builds. It acts
    through the ``agreement`` of the trainer's
    :class:`~mfg_lightning.run.agreed_steps.AgreedSteps`; without one it leaves Lightning's
    handler in place.
    """

    def __init__(self) -> None:
        self._held = False  # Lightning's flag held back during a validation (DDP)
        #: the signal that stopped this process when it was not SIGTERM (SIGINT): its exit status
        self.stopped_by: signal.Signals | None = None
        self._previous_sigint: Any = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        agreement = _agreement(trainer)
        connector = getattr(trainer, "_signal_connector", None)
        if not isinstance(agreement, Agreement) or connector is None:
            return
        if not hasattr(connector, "_sigterm_notifier_fn"):
            log.warning(
                "this Lightning version has no _sigterm_notifier_fn: its own SIGTERM handler is "
                "kept, and under DDP a SIGTERM may leave the processes waiting for each other"
            )
            return
        # Lightning composes the handler it registers before each stage from this attribute
        # (with SLURM's requeue handler and any handler already there).
        connector._sigterm_notifier_fn = functools.partial(_on_sigterm, trainer, agreement)
        epoch_loop = trainer.fit_loop.epoch_loop
        if hasattr(epoch_loop, "_broadcast_sigterm_tensor"):
            # Lightning broadcasts rank 0's flag and reads it before every DDP step (a collective
            # and a host wait per step); the agreement carries the signal instead.
            epoch_loop._broadcast_sigterm_tensor = _no_sigterm_broadcast

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        agreement = _agreement(trainer)
        if not isinstance(agreement, Agreement):
            if trainer.world_size > 1:
                return  # no agreement to stop together on: Lightning's KeyboardInterrupt
            agreement = None
        if threading.current_thread() is not threading.main_thread():
            return
        if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
            return  # started with SIGINT ignored (nohup, a background job): left so
        handler = functools.partial(self._on_sigint, trainer, agreement)
        self._previous_sigint = signal.signal(signal.SIGINT, handler)

    def _on_sigint(
        self, trainer: L.Trainer, agreement: Agreement | None, signum: int, frame: FrameType | None
    ) -> None:
        """The first Ctrl-C: a stop like SIGTERM's (see the module's docstring); the next one is
        the operating system's (the process ends at once)."""
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        log.warning(
            rank_prefixed_message(
                "Ctrl-C: stopping after this step and saving last.ckpt (Ctrl-C again: at once, "
                "without saving)",
                trainer.local_rank,
            )
        )
        self.stopped_by = signal.SIGINT
        if agreement is not None:
            agreement.sigterm = True
        if trainer.world_size == 1:
            trainer._signal_connector.received_sigterm = True

    def _restore_sigint(self) -> None:
        if (
            self._previous_sigint is not None
            and threading.current_thread() is threading.main_thread()
        ):
            signal.signal(signal.SIGINT, self._previous_sigint)
            self._previous_sigint = None

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self._restore_sigint()

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        agreement = _agreement(trainer)
        if trainer.world_size == 1 or not isinstance(agreement, Agreement) or not agreement.stop:
            return
        connector = trainer._signal_connector
        if not connector.received_sigterm:
            # Every process sets it after the same step: LastCheckpoint (after this callback)
            # saves here, and Lightning stops at the end of the step, on every process alike.
            connector.received_sigterm = True
            _take_over_the_watch(trainer)

    def on_validation_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        # Lightning's evaluation loop stops at its next batch on the flag, on each process alone,
        # and their shares of a split may differ by a batch: under DDP the flag waits for the
        # end of the validation (LastCheckpoint does the same, for its own reasons).
        connector = getattr(trainer, "_signal_connector", None)
        if trainer.world_size > 1 and connector is not None and connector.received_sigterm:
            connector.received_sigterm = False
            self._held = True

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._held:
            trainer._signal_connector.received_sigterm = True
            self._held = False

    def on_exception(
        self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException
    ) -> None:
        self._restore_sigint()  # a fit ended by an exception (the stop's included) has no teardown
        _take_over_the_watch(trainer)


def _agreement(trainer: L.Trainer) -> Agreement | None:
    steps = AgreedSteps.of(trainer)
    return None if steps is None else steps.agreement


def _no_sigterm_broadcast() -> None:
    """In place of Lightning's per-step SIGTERM broadcast (see :meth:`StopTogether.setup`)."""


class BuffersWhereNeeded(L.Callback):
    """DDP broadcasts the module's buffers from rank 0 before every forward: a collective per
    step. Only buffers that the forward changes need it, those of normalisation layers with
    running statistics; without such a layer this callback turns the per-forward broadcast off
    (``forward_sync_buffers=False``, torch ≥ 2.13: DDP's one synchronisation when it wraps the
    module still makes every buffer equal on every process; older torch:
    ``broadcast_buffers=False``, which skips that one too, harmless here since this project's
    modules compute theirs, the mean motion, alike on every process or load them from the
    checkpoint).

    A ``broadcast_buffers`` or ``forward_sync_buffers`` given to the strategy
    (``trainer.strategy.*``) is kept as given: set it for a module with other buffers that
    change in training. :func:`mfg_lightning.run.runs.build_trainer` adds this callback to every
    Trainer a run builds.
    """

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        # Callbacks' setup runs before the strategy wraps the module (strategy.setup)
        import inspect

        from lightning.pytorch.strategies import DDPStrategy
        from torch.nn.parallel import DistributedDataParallel

        strategy = trainer.strategy
        if not isinstance(strategy, DDPStrategy):
            return
        if {"broadcast_buffers", "forward_sync_buffers"} & set(strategy._ddp_kwargs):
            return  # given: kept
        needs = buffers_change_in_forward(pl_module)
        accepted = inspect.signature(DistributedDataParallel).parameters
        key = "forward_sync_buffers" if "forward_sync_buffers" in accepted else "broadcast_buffers"
        strategy._ddp_kwargs[key] = needs
        if not needs:
            log.debug("DDP: no buffer changes in a forward, %s=False", key)


def buffers_change_in_forward(module: torch.nn.Module) -> bool:
    """Whether ``module`` has buffers its forward updates: normalisation layers that track
    running statistics (batch norm and its kin)."""
    from torch.nn.modules.batchnorm import _NormBase

    return any(
        isinstance(m, _NormBase) and m.track_running_stats and m.running_mean is not None
        for m in module.modules()
    )


def _on_sigterm(
    trainer: L.Trainer, agreement: Agreement, signum: int, frame: FrameType | None
) -> None:
    """The SIGTERM handler: record the signal; hand it on once to the processes this one
    started; without a process group, set Lightning's flag at once (no collective call here)."""
    log.info(rank_prefixed_message(f"received SIGTERM ({signum})", trainer.local_rank))
    first = not agreement.sigterm
    agreement.sigterm = True
    launcher = trainer.strategy.launcher
    if first and launcher is not None:
        launcher.kill(signum)  # the processes this one started (trainer=ddp's first process)
    if trainer.world_size == 1:
        trainer._signal_connector.received_sigterm = True


def _children(trainer: L.Trainer) -> list[subprocess.Popen]:
    """The processes this one started (the first process of ``trainer=ddp``; else none)."""
    return list(getattr(trainer.strategy.launcher, "procs", None) or [])


def _starts_processes(trainer: L.Trainer) -> bool:
    """Whether this process starts the others (the first process of ``trainer=ddp``)."""
    environment = getattr(trainer.strategy, "cluster_environment", None)
    return trainer.world_size > 1 and not getattr(environment, "creates_processes_externally", True)


def _take_over_the_watch(trainer: L.Trainer) -> None:
    """Stop Lightning's watch on the processes this one started (it kills this process as soon
    as one of them exits with an error status): :func:`ending_together` waits for them."""
    if not _children(trainer):
        return
    for thread in threading.enumerate():
        if type(thread).__name__ == "_ChildProcessObserver" and hasattr(thread, "_child_processes"):
            # Its next look finds nothing to watch and ends (Lightning 2.x).
            thread._child_processes = []  # type: ignore[attr-defined]


def _end_children(trainer: L.Trainer, grace: float) -> None:
    """Wait up to ``grace`` seconds for the processes this one started; kill those left."""
    children = _children(trainer)
    if not children:
        return
    _take_over_the_watch(trainer)
    deadline = time.monotonic() + grace
    for rank, child in enumerate(children, start=1):
        try:
            child.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("local rank %d had not ended %.0f s after rank 0: killed", rank, grace)
            child.kill()
            child.wait()
        log.info("local rank %d ended with status %s", rank, child.returncode)


def _leave_process_group() -> None:
    """Leave a gloo process group, so that the peers waiting on this process in a collective
    fail at once rather than at the timeout. (An NCCL peer does not notice: the launcher ends
    it.) Never raises: the error that brought us here is the one to report."""
    with contextlib.suppress(Exception):
        if dist.is_available() and dist.is_initialized() and dist.get_backend() == "gloo":
            dist.destroy_process_group()


def _tear_down_data(trainer: L.Trainer) -> None:
    """The datamodule's ``teardown``, which Lightning skips when a stage ends by an exception: it
    stops the threads that fill the sample cache ahead of the loader. A daemon thread still in
    torch's C++ code when the interpreter exits is ended by ``pthread_exit``, whose unwinding
    through that code aborts the process (``terminate called without an active exception``,
    status -6), after ``last.ckpt`` was saved. Never raises: the error that brought us here is
    the one to report."""
    datamodule = getattr(trainer, "datamodule", None)
    if datamodule is None:
        return
    fn = trainer.state.fn
    with contextlib.suppress(Exception):
        datamodule.teardown(None if fn is None else fn.value)


@contextlib.contextmanager
def ending_together(trainer: L.Trainer) -> Iterator[None]:
    """Around an entry point's ``trainer.fit`` and ``trainer.test``.

    Lightning ends a fit or test stopped by SIGTERM with ``SIGTERMException`` (a ``SystemExit``
    of status 0): exit with 143 instead, the conventional status of a process ended by SIGTERM
    (130 when this process was stopped by Ctrl-C), so that schedulers and scripts see an
    interrupted job. During a fit, ``LastCheckpoint`` has
    saved ``last.ckpt`` by then; a stop on SLURM's requeue signal, seen by any process, requeues
    the job now (:class:`~mfg_lightning.run.slurm.SlurmRequeue`). Any end by an exception tears the
    datamodule down (its threads stopped before the interpreter exits). Under DDP it also ends
    the other processes (the module's docstring): this one leaves a gloo process group unless
    every process stopped together on SIGTERM, and the first process of ``trainer=ddp`` waits
    for the others. The processes Lightning starts here end with this one from their first second
    (:func:`mfg_lightning.run.startup.launching`).
    """
    try:
        with launching(_starts_processes(trainer)):
            yield
    except BaseException as err:
        stopped = isinstance(err, SIGTERMException)
        _tear_down_data(trainer)
        if stopped:
            # Before the first process waits for the others: every process takes part in the
            # requeue's agreement (SLURM's requeue signal may have reached any one of them).
            for callback in trainer.callbacks:
                if isinstance(callback, SlurmRequeue):
                    callback.requeue(trainer)
        if trainer.world_size > 1:
            if not stopped:
                _leave_process_group()
            _end_children(trainer, CHILDREN_GRACE)
        if stopped:
            by = next(
                (cb.stopped_by for cb in trainer.callbacks if isinstance(cb, StopTogether)), None
            )
            by = by or signal.SIGTERM  # SIGTERM, SLURM's requeue signal, a peer's stop
            log.warning("stopped by %s at step %d", by.name, trainer.global_step)
            raise SystemExit(128 + by) from None
        raise
