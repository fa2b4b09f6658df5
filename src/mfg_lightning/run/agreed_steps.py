"""What a run does about a training step that must not be taken, for any LightningModule.

A module's ``training_step`` prepares its targets, runs its network, computes its loss, logs it
and returns it. Everything else about a step is :class:`AgreedSteps`, one callback that a run's
trainer gets from its config (``callbacks.agreed_steps``, conf/callbacks/default.yaml and
flow.yaml):

* **Batch checks.** At the start of every training, validation and test step of an MFG module
  the batch is checked (:func:`mfg_lightning.data.sample.check_batch`: shapes at the network's
  input size, dtypes, finite poses, intrinsics and depth). A malformed one is refused with a
  :class:`~mfg_lightning.data.sample.SampleError` naming its samples. Non-finite flow pixels are
  not an error: the module masks them.
* **One skip route.** The loss of every batch is watched as it goes to backward
  (``on_before_backward``). Just before the optimiser step (``on_before_optimizer_step``) the
  step is skipped when one of those losses was not finite, or when this process had no usable
  sample: every gradient is dropped, and torch's optimisers leave a parameter without a gradient
  untouched, its state included. Lightning still counts the step, as it counts one that
  GradScaler skips. This works for every optimiser, precision and strategy. The verdict is read
  on the host once per optimiser step (on a GPU that waits for the step's kernels).
* **Too many in a row.** ``max_consecutive_nonfinite`` skipped steps in a row end the run with
  :class:`NonFiniteLossError`.
* **Together, under DDP.** Every process must make the same collective calls in the same order,
  so no process acts alone: each optimiser step makes one ``all_reduce`` (MAX) of this process's
  ``[skip, sigterm, fail]`` flags (:class:`Agreement`), and every process acts on the result
  at the same step: the step is skipped on every process; SIGTERM or Ctrl-C in any process stops
  all of them after that step (:class:`~mfg_lightning.run.together.StopTogether` records the
  signal and stops Lightning); a training batch refused in one process ends every process there,
  that one with its own error and the others with :class:`PeerFailedError` naming it.

A process without a usable sample still takes part in the step's forward, backward and gradient
all-reduce, whose skip the agreement then decides: it trains on a stand-in, its last accepted
training batch. A refused batch is replaced by it here; a batch whose every sample was unreadable
(None) is replaced by it in :meth:`mfg_lightning.run.startup.StartupDDPStrategy.batch_to_device`,
because Lightning would skip a None batch on that process alone.
"""

from __future__ import annotations

import logging
from typing import Any

import lightning as L
import torch
import torch.distributed as dist
from torch import Tensor

from mfg_lightning.core.errors import UserError
from mfg_lightning.data.sample import POSE, SAMPLE_ID, SampleError, check_batch

log = logging.getLogger(__name__)

__all__ = ["AgreedSteps", "Agreement", "NonFiniteLossError", "PeerFailedError"]


class NonFiniteLossError(RuntimeError):
    """Training produced non-finite losses too many times in a row."""


class PeerFailedError(UserError):
    """Another process of the run failed; its own error is printed by it (or is in its log)."""


class Agreement:
    """One process's side of the decisions taken together (see the module's docstring).

    Attributes:
        sigterm: SIGTERM or Ctrl-C reached this process (set by the signal handler).
        failure: the error this process holds, raised at the agreed step (None: none).
        stop: every process agreed to stop (the signal reached at least one of them).
    """

    def __init__(self) -> None:
        self.sigterm = False
        self.failure: BaseException | None = None
        self.stop = False

    def refuse(self, error: BaseException) -> None:
        """Keep ``error`` (the first one) to raise at the step every process agrees on."""
        if self.failure is None:
            self.failure = error

    def agree(self, skip: bool, step: int, device: torch.device) -> bool:
        """Reduce ``[skip, sigterm, fail]`` over every process (one ``all_reduce``), set
        :attr:`stop` and raise a failure; return whether the step is skipped on every process.

        Raises:
            BaseException: this process's :attr:`failure`, when a process failed.
            PeerFailedError: when another process failed and this one did not.
        """
        # fail carries the rank + 1, so that the others can say which process failed
        fail = 0.0 if self.failure is None else float(_rank() + 1)
        flags = torch.tensor([float(skip), float(self.sigterm), fail], device=device)
        if dist.is_available() and dist.is_initialized():
            dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        skip_all, stop, failed = flags.tolist()
        if stop and not self.stop:
            self.stop = True
            log.warning("SIGTERM reached the run: every process stops after step %d", step)
        if failed:
            if self.failure is not None:
                raise self.failure
            raise PeerFailedError(
                f"process {int(failed) - 1} of the run failed at step {step} (its error is "
                "printed above, or in its log): every process stopped there"
            )
        return bool(skip_all)


def _rank() -> int:
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def _ids(batch: Any, limit: int = 4) -> str:
    ids = list(batch.get(SAMPLE_ID, [])) if isinstance(batch, dict) else []
    more = f" (+{len(ids) - limit} more)" if len(ids) > limit else ""
    return ", ".join(map(str, ids[:limit])) + more


class AgreedSteps(L.Callback):
    """Batch checks, the skip of a non-finite step, and the agreement of every DDP process on
    skipping, stopping and failing (see the module's docstring).

    Args:
        max_consecutive_nonfinite: end the run after this many skipped steps in a row; None:
            the module's ``max_consecutive_nonfinite`` hyperparameter (``model.*``), else 20.

    Attributes:
        agreement: what this process decides with the others (:class:`Agreement`).
        skipped: training steps skipped so far (logged as ``train/skipped_steps``).
        consecutive: skipped steps in a row, up to the last one.
    """

    def __init__(self, max_consecutive_nonfinite: int | None = None) -> None:
        if max_consecutive_nonfinite is not None and max_consecutive_nonfinite < 1:
            raise ValueError(
                "max_consecutive_nonfinite must be >= 1, got " + str(max_consecutive_nonfinite)
            )
        self.max_consecutive = max_consecutive_nonfinite
        self.agreement = Agreement()
        self.skipped = 0
        self.consecutive = 0
        self._stand_in: dict[str, Any] | None = None
        self._no_samples = False  # this process trains on the stand-in in this step
        self._bad_loss: float | None = None  # the first non-finite loss of this step
        self._ids = ""

    @staticmethod
    def of(trainer: L.Trainer) -> AgreedSteps | None:
        """The trainer's :class:`AgreedSteps` callback, or None."""
        return next((cb for cb in trainer.callbacks if isinstance(cb, AgreedSteps)), None)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.max_consecutive is None:
            self.max_consecutive = int(pl_module.hparams.get("max_consecutive_nonfinite", 20))

    # -- the batches ---------------------------------------------------------------------------

    def stand_in(self) -> dict[str, Any]:
        """The batch this process trains on when it has no usable sample (DDP): its last
        accepted training batch. The step is then skipped by every process."""
        if self._stand_in is None:
            raise UserError(
                f"process {_rank()} has no usable sample in its first training batch (every "
                "sample unreadable or refused): nothing to take part in the step with"
            )
        self._no_samples = True
        return self._stand_in

    @staticmethod
    def check(pl_module: L.LightningModule, batch: Any) -> None:
        """Refuse a malformed batch of an MFG module (:func:`~mfg_lightning.data.sample.check_batch`
        at the network's input size, with the pose that training and evaluation compare with)."""
        from mfg_lightning.models.mfg import MotionFieldNetwork, input_size

        net = getattr(pl_module, "net", None)
        if not batch or not isinstance(net, MotionFieldNetwork):
            return
        height, width = input_size(net)
        param = next(pl_module.parameters(), None)
        dtype = None if param is None else param.dtype
        check_batch(batch, height, width, dtype=dtype, needs=(POSE,))

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        self._ids = "this process" if self._no_samples else _ids(batch)
        try:
            self.check(pl_module, batch)
        except SampleError as err:
            if trainer.world_size == 1:
                raise
            # Under DDP every process ends at the agreed step; until then this one trains on
            # the stand-in (in place: Lightning hands this dict to the training step).
            self.agreement.refuse(err)
            stand_in = self.stand_in()
            batch.clear()
            batch.update(stand_in)
            self._ids = "this process"
            return
        if not self._no_samples:
            self._stand_in = batch

    def on_validation_batch_start(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        self.check(pl_module, batch)

    on_test_batch_start = on_validation_batch_start

    # -- the skip ------------------------------------------------------------------------------

    def on_before_backward(
        self, trainer: L.Trainer, pl_module: L.LightningModule, loss: Tensor
    ) -> None:
        if self._bad_loss is None and trainer.training and not bool(torch.isfinite(loss)):
            self._bad_loss = float(loss.detach())

    def on_before_optimizer_step(
        self, trainer: L.Trainer, pl_module: L.LightningModule, optimizer: torch.optim.Optimizer
    ) -> None:
        bad_loss, no_samples = self._bad_loss, self._no_samples
        self._bad_loss, self._no_samples = None, False
        skip = no_samples or bad_loss is not None
        if trainer.world_size > 1:
            skip = self.agreement.agree(skip, trainer.global_step, pl_module.device)
        if not skip:
            self.consecutive = 0
            return
        for group in optimizer.param_groups:
            for param in group["params"]:
                param.grad = None
        self.skipped += 1
        self.consecutive += 1
        if no_samples:
            cause = "no usable sample"
        elif bad_loss is not None:
            cause = f"non-finite loss ({bad_loss})"
        else:  # under DDP the verdict came from another process
            cause = "a non-finite loss or no usable sample in another process"
        log.warning("%s on %s: step skipped", cause, self._ids)
        if self.consecutive >= (self.max_consecutive or 20):
            raise NonFiniteLossError(
                f"{self.consecutive} consecutive non-finite losses; last samples: {self._ids}"
            )

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        pl_module.log("train/skipped_steps", float(self.skipped))
