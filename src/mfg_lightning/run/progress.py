"""Training's progress bar, which says what limits the run: steps or epochs.

Lightning's :class:`~lightning.pytorch.callbacks.RichProgressBar` counts the batches of the current
epoch and titles the bar ``Epoch e/max_epochs − 1``. A run limited by ``trainer.max_steps`` has
``max_epochs = -1``, so it read ``Epoch 6/-2`` and restarted its bar every epoch, never saying how
far the run is. :class:`RunProgressBar` keeps Lightning's bar for runs that ``max_epochs`` limits
and, for runs that ``max_steps`` limits, shows the optimiser steps of the whole run instead: the
bar's total is ``max_steps``, its count the steps done (``trainer.global_step``), and the title
``Epoch e · s steps to go``. Validation, test and predict bars are Lightning's.

The training loss is shown without being a progress-bar value of Lightning's (``prog_bar=True``):
Lightning converts such a value to a Python number after every training step until the epoch
ends, a host wait per step on a GPU, although the module logs it only at the logging steps. The
bar reads the logged tensor itself, once per new value (:attr:`RunProgressBar.SHOWN`).
"""

from __future__ import annotations

from typing import Any

import lightning as L
from lightning.pytorch.callbacks import RichProgressBar

__all__ = ["RunProgressBar", "steps_limit"]


def steps_limit(trainer: L.Trainer) -> int | None:
    """The ``max_steps`` that ends the run first, or None when ``max_epochs`` does.

    Args:
        trainer: a trainer whose training loop is set up (its batches per epoch known).

    Returns:
        ``trainer.max_steps`` when it is set (> 0) and no ``max_epochs`` ends the run before it
        (``max_epochs`` unset or -1, or its epochs hold at least ``max_steps`` optimiser steps);
        None otherwise.
    """
    max_steps = trainer.max_steps
    if max_steps is None or max_steps <= 0:
        return None
    max_epochs = trainer.max_epochs
    if max_epochs is None or max_epochs < 0:
        return max_steps
    # Lightning's estimate is min(max_steps, the epochs' optimiser steps) (inf for a loader of
    # unknown length): reaching max_steps means the steps limit the run.
    return max_steps if trainer.estimated_stepping_batches >= max_steps else None


class RunProgressBar(RichProgressBar):
    """:class:`~lightning.pytorch.callbacks.RichProgressBar` that counts the run's steps when
    ``trainer.max_steps`` limits it, and shows the training loss read once per logged value
    (module docstring); takes the same arguments."""

    #: logged training values the bar shows beside Lightning's progress-bar values
    SHOWN = ("train/loss",)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # name -> (the logged tensor last read, kept alive; its value)
        self._read: dict[str, tuple[Any, float]] = {}

    def get_metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, Any]:
        """Lightning's items, and :attr:`SHOWN`'s latest logged values: a value is read from
        its tensor (a host wait on a GPU) only when the module has logged a new one."""
        items = super().get_metrics(trainer, pl_module)
        for name in self.SHOWN:
            value = trainer.callback_metrics.get(name)
            if value is None:
                continue
            last = self._read.get(name)
            # Lightning hands out a new view of the same logged tensor at every step: the
            # storage tells a new value (the one held here stays alive, so no new value can
            # take its address)
            if last is None or last[0].data_ptr() != value.data_ptr():
                last = self._read[name] = (value, float(value))
            items[name] = last[1]
        return items

    def _steps(self) -> int | None:
        return steps_limit(self.trainer) if self._trainer is not None else None

    def _show_steps(self, max_steps: int) -> None:
        """The train bar as the run's steps: total ``max_steps``, count ``global_step``."""
        if self.progress is None or self.train_progress_bar_id is None or not self.is_enabled:
            return
        text = self._get_train_description(self.trainer.current_epoch)
        # Styled as Lightning styles the descriptions of the tasks it adds.
        style = self.theme.description
        self.progress.update(
            self.train_progress_bar_id,
            total=max_steps,
            completed=self.trainer.global_step,
            description=f"[{style}]{text}" if style else text,
        )

    def _get_train_description(self, current_epoch: int) -> str:
        max_steps = self._steps()
        if max_steps is None:
            return super()._get_train_description(current_epoch)
        to_go = max(max_steps - self.trainer.global_step, 0)
        return f"Epoch {current_epoch} · {to_go} steps to go"

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_epoch_start(trainer, pl_module)
        if (max_steps := self._steps()) is not None:
            self._show_steps(max_steps)
            self.refresh()

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any
    ) -> None:
        # The step's outputs, batch and index are Lightning's bar's business, passed on as given.
        max_steps = self._steps()
        if max_steps is None:
            super().on_train_batch_end(trainer, pl_module, *args)
            return
        if not self.is_disabled and self.train_progress_bar_id is None:
            # A run resumed in the middle of an epoch starts here (as Lightning's bar does).
            self._initialize_train_progress_bar_id()
        self._show_steps(max_steps)
        self._update_metrics(trainer, pl_module)
        self.refresh()
