"""What a training step does with a non-finite loss: the step is skipped, counted, and a run
that keeps producing them is stopped (:class:`NonFiniteLosses`).

Two ways to skip, chosen once per step by what the optimiser can do:

- **in the optimiser** (one fused optimiser, e.g. Adam with ``fused=True``, the default config's):
  the step's finiteness goes to the optimiser's kernel as ``found_inf`` (as GradScaler does),
  which leaves weights and state untouched on the device. On an accelerator nothing is read on
  the host; the counts are read at the logging steps (:meth:`NonFiniteLosses.report`). On a CPU,
  where the verdict already is in host memory, every step's verdict is read, and a finite step
  then skips this plumbing (same weights, fewer operations).
- **on the host** (any other optimiser): the verdict is read on the host (one synchronisation per
  step) and the step returns None, which skips backward and the optimiser step. Under DDP, where
  Lightning refuses a None step and every process must run backward, the step returns a zero
  loss instead and its gradients are dropped before the optimiser step
  (:meth:`NonFiniteLosses.drop_gradients`).

Under DDP either way takes one verdict for every process: the gradients are averaged, so one
process's NaN reaches all of them, and a process that skipped backward alone would leave the
others waiting in the gradient all-reduce. The module passes the verdict agreed by
:class:`~mfg_lightning.models.agreement.Agreement` (one ``all_reduce`` per step), so the counts,
and the :class:`NonFiniteLossError` that ends a run, are the same on every process.

Logged names, one meaning each: ``train/skipped_steps`` is the number of training steps skipped
so far (either way). The counts are :class:`StepCount` tensors on the device; the skipped and
consecutive counts follow the agreed verdict, so they are the same on every process.
"""

from __future__ import annotations

import logging
from typing import Any

import torch
from torch import Tensor, nn

from mfg_lightning.data.sample import SAMPLE_ID

log = logging.getLogger(__name__)


class NonFiniteLossError(RuntimeError):
    """Training produced non-finite losses too many times in a row."""


class StepCount(nn.Module):
    """A count kept on the device (``count``, a 0-dim long tensor), added to in place:
    ``update(n)``, and with ``restart`` set to 0 where ``restart`` is True. ``update`` reads
    nothing back from the device and costs two tensor operations.

    Not a torchmetrics ``Metric``: its ``update`` wrapper's bookkeeping cost the batch-1 step
    ~0.4 ms for three counts (Lightning / bare, step-paired, bf16-mixed on an AMD EPYC: 0.943 with
    them, 0.957 without; no ``compute()`` reduced them across processes). Not a buffer either:
    DDP broadcasts buffers from rank 0 at every forward, and ``masked_flow_pixels`` is each
    process's own count. It moves with the module all the same (``_apply``), and like a
    ``Metric``'s state it is not saved in checkpoints."""

    def __init__(self) -> None:
        super().__init__()
        self.count = torch.zeros((), dtype=torch.long)

    def _apply(self, fn: Any, recurse: bool = True) -> StepCount:
        self.count = fn(self.count)
        return super()._apply(fn, recurse)

    def update(self, n: Tensor, restart: Tensor | None = None) -> None:
        self.count.add_(n.to(self.count))
        if restart is not None:
            self.count.masked_fill_(restart, 0)


class NonFiniteLosses(nn.Module):
    """Skips, counts and stops on non-finite losses (see the module's docstring).

    The LightningModule calls :meth:`check` in its training step, :meth:`before_optimizer_step`
    and :meth:`after_batch` from the hooks of the same names, and :meth:`report` at its logging
    steps and at the end of training.

    Args:
        max_consecutive: stop after this many non-finite losses in a row.
    """

    def __init__(self, max_consecutive: int = 20) -> None:
        super().__init__()
        self.max_consecutive = max_consecutive
        #: training steps skipped so far
        self.skipped = StepCount()
        #: non-finite losses in a row, up to the last step
        self.consecutive = StepCount()
        self._reported = 0
        self._window_finite: Tensor | None = None
        self._found_inf: Tensor | None = None
        self._drop_gradients = False

    @staticmethod
    def skips_in_the_optimiser(trainer: Any, automatic_optimization: bool = True) -> bool:
        """Whether a non-finite loss can be skipped inside the optimiser's step: one fused
        optimiser, whose kernel leaves weights and state untouched when told ``found_inf``."""
        if trainer is None or not automatic_optimization or len(trainer.optimizers) != 1:
            return False
        return bool(trainer.optimizers[0].defaults.get("fused"))

    @staticmethod
    def reads_wait_for_nothing(device: torch.device) -> bool:
        """Whether reading a tensor on ``device`` from the host waits for nothing: on a CPU it is
        in host memory already; on an accelerator the read waits for the step's kernels. The
        one answer for every per-step read of a verdict or a flag (:meth:`check`,
        :meth:`~mfg_lightning.models.agreement.Agreement.decide`, the batch checks' default
        deferral)."""
        return device.type == "cpu"

    def check(
        self,
        loss: Tensor,
        finite: Tensor,
        ids: str | None = None,
        fused: bool = True,
        cause: str | None = None,
    ) -> bool:
        """Account for the step; False: skip it (return None from the step).

        Args:
            loss: this process's total loss (0-dim), for the host route's message.
            finite: 0-dim bool, the step may be taken: the loss is finite (under DDP: on every
                process, and every process had a usable sample; the agreed verdict).
            ids: the batch's sample ids, for the messages of the host route.
            fused: :meth:`skips_in_the_optimiser`.
            cause: why this process cannot take the step, when it is not its loss (the host
                route's message).

        Raises:
            NonFiniteLossError: on the host route, after ``max_consecutive`` in a row.
        """
        if fused:
            if self.reads_wait_for_nothing(finite.device) and bool(finite):
                # A finite step needs no ``found_inf`` (the optimiser's step as without the
                # guard, to the bit) and leaves the skip count as it is: one operation where
                # the device's route takes eight, fused Adam's ``found_inf`` correction
                # included (bench/results/throughput_epyc/batch1_ab.md).
                self.consecutive.count.zero_()
                return True
            window = self._window_finite
            self._window_finite = finite if window is None else window & finite
            self.consecutive.update(torch.ones_like(self.consecutive.count), restart=finite)
            self.skipped.update((~finite).long())
            return True
        if bool(finite):
            self.consecutive.count.zero_()
            return True
        self.skipped.update(torch.ones_like(self.skipped.count))
        self.consecutive.update(torch.ones_like(self.consecutive.count))
        run = int(self.consecutive.count)
        self._reported = int(self.skipped.count)
        value = loss.detach()
        if cause is None and bool(torch.isfinite(value)):
            # under DDP the verdict may come from another process, whose loss is not here
            cause = "a non-finite loss or no usable sample in another process"
        elif cause is None:
            cause = f"non-finite loss ({value.item()})"
        log.warning("%s on %s: step skipped", cause, ids)
        if run >= self.max_consecutive:
            raise NonFiniteLossError(f"{run} consecutive non-finite losses; last samples: {ids}")
        return False

    def report(self, ids: str) -> None:
        """Read the counts (a host synchronisation: logging steps and the end of training only),
        warn about new skips and stop a run that keeps producing them.

        Raises:
            NonFiniteLossError: after ``max_consecutive`` in a row.
        """
        run, skipped = torch.stack([self.consecutive.count, self.skipped.count]).tolist()
        if skipped > self._reported:
            log.warning(
                "non-finite loss in %d step(s) since the last report: skipped in the optimiser "
                "(latest samples: %s)",
                skipped - self._reported,
                ids,
            )
        self._reported = skipped
        if run >= self.max_consecutive:
            raise NonFiniteLossError(f"{run} consecutive non-finite losses; last samples: {ids}")

    def drop_gradients(self) -> None:
        """Skip the coming optimiser step by dropping every gradient just before it (an optimiser
        leaves a parameter without a gradient untouched, state included): the host route's skip
        under DDP, where Lightning refuses a None step and every process must run backward for
        the gradient all-reduce."""
        self._drop_gradients = True

    def before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Hand the step's finiteness to a fused optimiser (``found_inf``: 1 skips the update of
        weights and state on the device). Under ``16-mixed`` the GradScaler sets its own
        ``found_inf``, which a non-finite loss trips as well (its gradients are non-finite).
        After :meth:`drop_gradients`, drop them."""
        if self._drop_gradients:
            self._drop_gradients = False
            for group in optimizer.param_groups:
                for param in group["params"]:
                    param.grad = None
        if self._window_finite is None:
            return
        if optimizer.defaults.get("fused"):
            self._found_inf = (~self._window_finite).to(torch.float32)
            optimizer.found_inf = self._found_inf
        self._window_finite = None

    def after_batch(self, optimizers: list[torch.optim.Optimizer]) -> None:
        """Take ``found_inf`` back: it is this step's only; a stale one would skip later steps."""
        self._drop_gradients = False
        if self._found_inf is None:
            return
        for optimizer in optimizers:
            if getattr(optimizer, "found_inf", None) is self._found_inf:
                del optimizer.found_inf
        self._found_inf = None


class DeferredCounts:
    """Per-batch counts (of masked non-finite flow pixels) kept as device tensors beside their
    batch's sample ids, read back in one transfer when they are reported (a logging step, the
    end of an epoch)."""

    #: report anyway after this many batches, so that the list stays short
    LIMIT = 512

    def __init__(self) -> None:
        self._pending: list[tuple[Tensor, list]] = []

    def add(self, count: Tensor, batch: dict[str, Any]) -> bool:
        """Keep ``count`` (a 0-dim tensor); True when the list is full and should be read."""
        self._pending.append((count.detach(), list(batch.get(SAMPLE_ID, []))))
        return len(self._pending) >= self.LIMIT

    def read(self) -> list[tuple[int, list]]:
        """``(count, sample ids)`` of every kept batch with a non-zero count; empties the list
        (one host synchronisation)."""
        if not self._pending:
            return []
        counts = torch.stack([c for c, _ in self._pending]).tolist()
        out = [(int(n), ids) for n, (_, ids) in zip(counts, self._pending, strict=True) if n]
        self._pending.clear()
        return out
