"""Faults injected into one process of a real ``trainer=ddp`` training (tests/test_ddp_faults.py).

:class:`Fault` is a Lightning callback that the training builds from the command line
(``+callbacks.fault._target_=ddp_faults.Fault``, with this folder on ``PYTHONPATH``); Lightning
starts the second process with the same command, so both have it, and it acts in the process of
rank ``rank`` only, at the training steps ``steps`` (global steps, before the step runs):

* ``sigterm``: the process sends SIGTERM to itself, as a scheduler would;
* ``bad_batch``: the first sample's pose is made non-finite, which ``BatchChecks`` refuses;
* ``non_finite``: the step's loss is NaN (a forward hook on the loss);
* ``no_samples``: the batch arrives as None (before its transfer to the device), as when every
  sample was skipped as unreadable;
* ``error``: a ``RuntimeError`` that nothing agrees on (a bug in one process).

It writes ``<marker>`` (the time and the step) each time it acts, so that the test can time the
end of the run from the last fault.

Not a test module (no ``test_`` prefix): pytest does not collect it.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch

KINDS = ("sigterm", "bad_batch", "non_finite", "no_samples", "error")


class Fault(L.Callback):
    """One kind of fault in the process of rank ``rank`` at the training steps ``steps``.

    Args:
        kind: one of :data:`KINDS`.
        steps: the global steps at whose start it acts.
        marker: the file written each time it acts.
        rank: the process it acts in.
    """

    def __init__(self, kind: str, steps: list[int], marker: str, rank: int = 1) -> None:
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        self.kind, self.steps, self.marker, self.rank = kind, set(steps), Path(marker), rank

    def _due(self, trainer: L.Trainer) -> bool:
        return (
            trainer.global_rank == self.rank
            and trainer.training
            and not trainer.sanity_checking
            and trainer.global_step in self.steps
        )

    def _mark(self, trainer: L.Trainer) -> None:
        self.marker.write_text(f"{time.time()} {trainer.global_step}\n")

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        # First among the callbacks, so that a corrupted batch reaches BatchChecks.
        trainer.callbacks.remove(self)
        trainer.callbacks.insert(0, self)
        self._trainer = trainer
        if self.kind == "non_finite":
            pl_module.loss_fn.register_forward_hook(self._nan_loss)
        if self.kind == "no_samples":
            step = pl_module.on_before_batch_transfer

            def none_batch(batch: Any, dataloader_idx: int) -> Any:
                if self._due(trainer):
                    self._mark(trainer)
                    batch = None
                return step(batch, dataloader_idx)

            pl_module.on_before_batch_transfer = none_batch  # type: ignore[method-assign]

    def _nan_loss(self, module: torch.nn.Module, args: Any, terms: Any) -> Any:
        trainer = self._trainer
        if not module.training or not self._due(trainer):
            return terms
        self._mark(trainer)
        return terms._replace(total=terms.total * float("nan"))

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        if not self._due(trainer) or self.kind not in ("sigterm", "bad_batch", "error"):
            return
        self._mark(trainer)
        if self.kind == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)
        elif self.kind == "bad_batch":
            batch["pose"][0, 0, 3] = float("nan")
        else:
            raise RuntimeError(f"injected error in process {trainer.global_rank}")
