"""What every process of a data-parallel (DDP) run decides together.

Under DDP every process must make the same collective calls in the same order. A process that
skips a step, stops or raises on its own leaves the others waiting in their next collective until
the process group's timeout (30 minutes). So no process acts alone on what it sees: each training
step reduces every process's flags in one small ``all_reduce`` (MAX), and every process acts on the
reduced flags at the same step (:class:`Agreement`):

* **skip** the step: the loss is non-finite, or the process has no usable sample (every sample of
  its batch unreadable under ``dataset.skip_bad_samples``, or the batch refused by
  :class:`~mfg_lightning.run.callbacks.BatchChecks`). Such a process still takes part in the step
  (a zero loss over every parameter, so that the gradient all-reduce sees all of them) and the
  step is skipped on every process.
* **stop**: SIGTERM reached the process (:class:`~mfg_lightning.run.together.StopTogether` records
  it): every process stops after the same step, and ``last.ckpt`` is saved by all together.
* **fail**: the process holds an error that ends the run (a refused batch): every process raises
  at the same step, that one its own error, the others :class:`PeerFailedError` naming it.

On an accelerator the skip flag stays on the device (a fused optimiser's ``found_inf``; the host
route reads it, as it reads the loss); on a CPU every step's verdict is read, which waits for
nothing there (:meth:`NonFiniteLosses.reads_wait_for_nothing`). The stop and fail flags are read on
the host at every step on a CPU, where a read costs nothing, and on an accelerator, where a read
waits for the device, only at the logging steps (:func:`logging_step`: every
``trainer.log_every_n_steps``, when the loggers make the host wait anyway); meanwhile their maximum
is kept on the device. A stop or a failure is then acted on up to that many steps late, at the same
step on every process.

One process (no process group): nothing is reduced; SIGTERM and a refused batch are acted on at
once, as Lightning and the callbacks do by themselves.

A LightningModule of the project gets all of this by deriving from :class:`AgreedSteps` (its
training step asks it whether to take the step; it also skips non-finite losses,
:class:`~mfg_lightning.models.nonfinite.NonFiniteLosses`), with ``max_consecutive_nonfinite`` in
its config. The other half lives with the run: :class:`~mfg_lightning.run.together.StopTogether`,
which every Trainer of a run has, records SIGTERM and Ctrl-C in the module's :attr:`agreement`
and stops Lightning after the agreed step; ``BatchChecks`` hands it a refused batch.
"""

from __future__ import annotations

import logging
import re
import warnings
from typing import Any

import torch
import torch.distributed as dist
from lightning.fabric.utilities.warnings import PossibleUserWarning
from torch import Tensor

from mfg_lightning.core.errors import UserError
from mfg_lightning.models.nonfinite import NonFiniteLosses

log = logging.getLogger(__name__)

__all__ = ["AgreedSteps", "Agreement", "PeerFailedError", "logging_step", "reduced_epoch_logs"]


def logging_step(trainer: Any, done: bool = False) -> bool:
    """Whether the training step in progress is a logging step: the loggers write its values,
    every ``trainer.log_every_n_steps`` optimiser steps (every :attr:`Agreement.READ_EVERY` where
    that is 0). The host waits for the device at these steps anyway, so the run's other host
    reads are made then too. The same answer on every process (the global step decides).

    Args:
        trainer: the Lightning trainer.
        done: asked after the optimiser step (``trainer.global_step`` already counts it, as in
            ``on_train_batch_end``), not during it (``training_step``).
    """
    every = int(trainer.log_every_n_steps) or Agreement.READ_EVERY
    return (trainer.global_step + (0 if done else 1)) % every == 0


def reduced_epoch_logs(*prefixes: str) -> None:
    """Declare the epoch-level values a module logs under ``prefixes`` (``"val/"``) already
    reduced over every process (the evaluator's gather, a torchmetrics ``compute``). Lightning
    advises ``sync_dist=True`` for each of them under DDP (about a hundred lines a run); for these
    values it would only average identical numbers again, so its advice is silenced for these
    names only (a process-wide warning filter; installing it twice keeps one)."""
    if not prefixes:  # an empty alternation would silence the advice for every name
        raise ValueError("reduced_epoch_logs needs at least one name prefix")
    names = "|".join(re.escape(p) for p in prefixes)
    warnings.filterwarnings(
        "ignore",
        message=rf"It is recommended to use `self\.log\('({names})",
        category=PossibleUserWarning,
    )


class PeerFailedError(UserError):
    """Another process of the run failed; its own error is printed by it (or is in its log)."""


class Agreement:
    """One process's side of the decisions taken together (see the module's docstring).

    The LightningModule calls :meth:`reduce` once per training step under DDP (the step's only
    collective besides DDP's own) and :meth:`decide` right after; the callbacks set
    :attr:`sigterm` (the signal handler) and call :meth:`refuse` (a refused batch), and read
    :attr:`stop`. :meth:`settle` agrees outside a step (the end of an epoch or of training).

    Attributes:
        sigterm: SIGTERM reached this process (set by the signal handler: a plain assignment).
        failure: the error this process holds, raised at the agreed step (None: none).
        stop: every process agreed to stop (SIGTERM reached at least one of them).
    """

    #: on an accelerator, the training steps between two host reads of the stop and fail flags
    #: where the loggers never write (``trainer.log_every_n_steps=0``; else the logging steps)
    READ_EVERY = 20

    def __init__(self) -> None:
        self.sigterm = False
        self.failure: BaseException | None = None
        self.stop = False
        # (2,) float32 on the device: this process's [sigterm, fail] flags, rewritten (two fill
        # kernels, no host-to-device copy) only when one of them changes
        self._local: Tensor | None = None
        self._local_values = (0.0, 0.0)
        # (2,) float32 on the device: the agreed [stop, fail] since the last host read
        self._unread: Tensor | None = None

    def refuse(self, error: BaseException) -> None:
        """Keep ``error`` (the first one) to raise at the step every process agrees on; until
        then this process has no usable sample."""
        if self.failure is None:
            self.failure = error

    def reduce(self, skip: Tensor, strategy: Any | None = None) -> Tensor:
        """The step's one collective: ``[skip, sigterm, fail]`` of every process, MAX-reduced.

        Args:
            skip: 0-dim bool, this process cannot take the step (non-finite loss, no usable
                sample); on the module's device.
            strategy: the Lightning strategy, used only where torch.distributed is not what it
                runs on.

        Returns:
            0-dim bool on the same device: the step is skipped on every process. Never read on
            the host here; the agreed stop and fail flags are kept for :meth:`decide`.
        """
        # fail carries the rank + 1, so that the others can say which process failed
        values = (float(self.sigterm), 0.0 if self.failure is None else float(_rank() + 1))
        if self._local is None or self._local.device != skip.device:
            self._local = torch.zeros(2, device=skip.device)
            self._local_values = (0.0, 0.0)
        if values != self._local_values:
            for i, value in enumerate(values):
                self._local[i].fill_(value)
            self._local_values = values
        flags = torch.cat([skip.reshape(1).to(self._local.dtype), self._local])
        flags = _max_over_processes(flags, strategy)
        agreed = flags[1:]
        self._unread = agreed if self._unread is None else torch.maximum(self._unread, agreed)
        return flags[0] > 0

    def decide(self, step: int, due: bool = False, force: bool = False) -> None:
        """Read the agreed stop and fail flags when due (every step on a CPU, at the logging
        steps elsewhere; ``force``: now): set :attr:`stop`, or raise.

        Args:
            step: the global step, the same on every process (for the messages).
            due: a logging step (:func:`logging_step`), the same answer on every process.
            force: read now (outside a step, where every process calls this alike).

        Raises:
            BaseException: this process's :attr:`failure`, when a process failed.
            PeerFailedError: when another process failed and this one did not.
        """
        unread = self._unread
        if unread is None:
            return
        # read at every step where a read waits for nothing (a CPU), else at the logging steps
        if not (force or due or NonFiniteLosses.reads_wait_for_nothing(unread.device)):
            return
        self._unread = None
        stop, fail = unread.tolist()
        if stop and not self.stop:
            self.stop = True
            log.warning("SIGTERM reached the run: every process stops after step %d", step)
        if not fail:
            return
        if self.failure is not None:
            raise self.failure
        raise PeerFailedError(
            f"process {int(fail) - 1} of the run failed at step {step} (its error is printed "
            "above, or in its log): every process stopped there"
        )

    def settle(self, device: torch.device, step: int, strategy: Any | None = None) -> None:
        """Agree outside a training step (every process calls it at the same point): one
        ``all_reduce`` now, then :meth:`decide` at once."""
        self.reduce(torch.zeros((), dtype=torch.bool, device=device), strategy)
        self.decide(step, force=True)


def _rank() -> int:
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def _max_over_processes(flags: Tensor, strategy: Any | None) -> Tensor:
    """``flags`` MAX-reduced over the processes: one ``all_reduce``, queued on the device like
    the gradients' and not read here. Lightning's ``strategy.reduce`` would add a ``barrier()``
    before it (``_sync_ddp``): it is used only where torch.distributed is not what the strategy
    runs on."""
    if dist.is_available() and dist.is_initialized():
        dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        return flags
    return flags if strategy is None else strategy.reduce(flags, reduce_op="max")


class AgreedSteps:
    """The fault handling of a LightningModule's training step: skip, stop and fail together.

    A mixin placed before ``L.LightningModule`` (``class M(AgreedSteps, L.LightningModule)``);
    ``__init__`` calls :meth:`init_agreed_steps` after ``super().__init__()``, and the training
    step asks it what to do::

        fused = self.skips_in_the_optimiser()
        if self.without_samples(batch):  # {} under DDP, or a refused batch
            return self.step_without_samples(fused)
        loss = ...  # the step's total loss, 0-dim
        if not self.agree_on_loss(loss, ids, fused):
            return self.skipped()
        return loss

    Under DDP that is the step's one collective (:meth:`Agreement.reduce`), which also carries
    SIGTERM, Ctrl-C and a refused batch to every process: the same step is skipped, and the run
    stops or fails after the same step, on every process. On one process nothing is reduced. A
    module that overrides a hook this mixin defines (``transfer_batch_to_device``,
    ``on_before_optimizer_step``, ``on_train_batch_end``, ``on_train_end``) calls ``super()``.

    Attributes:
        agreement: what this process decides with the others (:class:`Agreement`); read by
            :class:`~mfg_lightning.run.together.StopTogether` and ``BatchChecks``.
        nonfinite: the non-finite losses skipped and counted (:class:`NonFiniteLosses`).
    """

    agreement: Agreement
    nonfinite: NonFiniteLosses

    def __setattr__(self, name: str, value: Any) -> None:
        # Lightning sets ``_current_fx_name`` (a string) before and after every hook it calls,
        # ~44 times a training step. nn.Module's __setattr__ first looks the name up among
        # parameters, buffers and submodules: 1.7 µs a call against object's 0.2 µs (timeit, AMD
        # EPYC), ~65 µs of a ~31 ms batch-1 step. A string is none of those, so nn.Module
        # would store it exactly as object.__setattr__ does.
        if name == "_current_fx_name":
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)

    def init_agreed_steps(self, max_consecutive_nonfinite: int = 20) -> None:
        """Set the attributes up (after ``nn.Module.__init__``: ``nonfinite`` is a submodule
        without parameters, buffers or persistent state, so checkpoints do not change)."""
        self.nonfinite = NonFiniteLosses(max_consecutive_nonfinite)
        self.agreement = Agreement()

    def _world_size(self) -> int:
        trainer = getattr(self, "_trainer", None)
        return 1 if trainer is None else int(trainer.world_size)

    def skips_in_the_optimiser(self) -> bool:
        """Whether a skipped step is skipped inside a fused optimiser (on an accelerator nothing
        is read on the host; :meth:`NonFiniteLosses.skips_in_the_optimiser`); asked once per
        step."""
        module: Any = self
        return self.nonfinite.skips_in_the_optimiser(
            getattr(self, "_trainer", None), module.automatic_optimization
        )

    def without_samples(self, batch: Any) -> bool:
        """Whether this process takes the step without samples: its batch is empty (every sample
        unreadable, under DDP: :meth:`transfer_batch_to_device`) or it holds a refused one."""
        return not batch or self.agreement.failure is not None

    def agreed(self, finite: Tensor) -> Tensor:
        """The step's verdict, 0-dim bool: ``finite`` here, or under DDP on every process (the
        step's one collective, which also agrees on stopping and failing, acted on when due)."""
        trainer: Any = getattr(self, "_trainer", None)
        if trainer is None or trainer.world_size == 1:
            return finite
        skip = self.agreement.reduce(~finite, trainer.strategy)
        self.agreement.decide(trainer.global_step, due=logging_step(trainer))
        return ~skip

    def agree_on_loss(self, loss: Tensor, ids: str | None, fused: bool) -> bool:
        """Account for a step with samples; False: return :meth:`skipped` from the step.

        Args:
            loss: the step's total loss (0-dim).
            ids: the batch's samples, for the messages.
            fused: :meth:`skips_in_the_optimiser`.

        Raises:
            NonFiniteLossError: too many non-finite losses in a row (the host route).
            BaseException: a failure agreed on (:meth:`Agreement.decide`).
        """
        finite = self.agreed(torch.isfinite(loss.detach()))
        return self.nonfinite.check(loss, finite, ids, fused)

    def step_without_samples(self, fused: bool) -> Tensor | None:
        """DDP only: this process has no usable sample (every one unreadable, or its batch
        refused). It takes part in the step all the same, with a zero loss, and the agreed
        verdict skips the step on every process."""
        loss = self.zero_loss()
        finite = self.agreed(torch.zeros((), dtype=torch.bool, device=loss.device))
        if not self.nonfinite.check(loss, finite, "this process", fused, "no usable sample"):
            return self.skipped()
        trainer: Any = getattr(self, "_trainer", None)
        if trainer is None or logging_step(trainer) or trainer.should_stop:
            self.nonfinite.report("<no usable sample on this process>")
        return loss

    def skipped(self) -> Tensor | None:
        """What a step skipped on the host route returns. One process: None (no backward, no
        optimiser step). DDP: Lightning refuses None, and every process must run backward for
        the gradient all-reduce: a zero loss, whose gradients are dropped before the optimiser
        step (:meth:`NonFiniteLosses.drop_gradients`)."""
        if self._world_size() == 1:
            return None
        self.nonfinite.drop_gradients()
        return self.zero_loss()

    def zero_loss(self) -> Tensor:
        """0 × every trainable parameter (0-dim): a loss with a zero gradient for each of them,
        so that DDP's gradient all-reduce hears from every parameter."""
        module: Any = self
        params = [p for p in module.parameters() if p.requires_grad]
        return torch.stack([p.sum() for p in params]).sum() * 0.0

    # -- Lightning's hooks -------------------------------------------------------------------

    def transfer_batch_to_device(
        self, batch: Any, device: torch.device, dataloader_idx: int
    ) -> Any:
        """Under DDP a training batch whose every sample was skipped as unreadable (None) goes
        on as an empty one (``{}``, a step without samples): Lightning would skip the step of a
        None batch on this process alone, and the others would wait for it in the step's
        collectives. (This hook, not ``on_before_batch_transfer``: Lightning calls a
        datamodule's ``on_before_batch_transfer`` instead of the module's where it has one.)"""
        trainer: Any = getattr(self, "_trainer", None)
        if batch is None and trainer is not None and trainer.training and trainer.world_size > 1:
            return {}
        return super().transfer_batch_to_device(batch, device, dataloader_idx)  # type: ignore[misc]

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        self.nonfinite.before_optimizer_step(optimizer)
        super().on_before_optimizer_step(optimizer)  # type: ignore[misc]

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        module: Any = self
        self.nonfinite.after_batch(module.trainer.optimizers)
        super().on_train_batch_end(outputs, batch, batch_idx)  # type: ignore[misc]

    def on_train_end(self) -> None:
        self.nonfinite.report("<end of training>")
        super().on_train_end()  # type: ignore[misc]
