"""Train until a stated convergence rule is met, then decay the rate and stop.

:class:`ConvergenceStop` is a Lightning callback (``callbacks=convergence``) that makes "trained
to convergence" a rule fixed before training rather than a schedule's length:

* **Plateau.** At every validation (step ``s``), the best ``monitor`` value so far is compared with
  the best up to step ``(1 − window) · s``. When it improved by less than ``min_improvement``
  (relative) over that last ``window`` of the steps so far, and ``s ≥ min_steps``, the model has
  **converged at s**. A constant rate cannot fake this (a schedule that takes the rate to 0 would
  flatten any curve): the rule is tested while the rate is still constant.
* **Decay.** Then the rate falls linearly to 0 over ``decay_fraction · s`` further steps (rounded
  up to the next validation) and training stops after that validation; the checkpoint callback
  keeps the best by ``monitor`` as always.
* **Budget.** With ``budget_steps`` the plateau test is off: the rate is constant until
  ``budget_steps − ⌈decay_fraction · budget_steps⌉`` and falls linearly to 0 at
  ``budget_steps`` (``reason``: ``budget``). Models compared with each other (seeds, flows,
  training sets) then train for the same steps whatever their curves do: an equal budget stated
  before training, for measurements that validation's ``monitor`` does not cover.
* **Caps.** When the decay would overrun ``trainer.max_steps`` or ``trainer.max_time`` (projected
  from the seconds per step so far), it starts early instead, and the run is reported as
  **not converged at N steps** (``reason``: ``step cap`` / ``time cap``): a budget shortens the
  schedule rather than cutting it mid-rate, and never reads as convergence. A capped run resumed
  with more room (a larger ``max_steps``, or any resume after a time cap) returns to the
  constant rate and carries on testing the rule.

Everything is resumable (the callback's state rides in the checkpoint) and written after every
validation to ``path`` (JSON: the rule, the curve, the status), which the reproduction study reads.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import lightning as L

from mfg_lightning.core.atomic import atomic_write_text

__all__ = ["ConvergenceStop", "plateau_improvement"]

log = logging.getLogger(__name__)


def plateau_improvement(curve: list[tuple[int, float]], step: int, window: float) -> float | None:
    """Relative improvement of the best value over the last ``window`` of the steps so far.

    Args:
        curve: ``(step, value)`` of every validation so far (lower is better; non-finite values
            are ignored).
        step: the current step ``s``.
        window: fraction of ``s``: the best up to ``(1 − window) · s`` is the reference.

    Returns:
        ``(best_before − best_now) / best_before`` (≥ 0), or None when no finite value lies at
        or before ``(1 − window) · s``.
    """
    cut = (1.0 - window) * step
    before = [v for s, v in curve if s <= cut and math.isfinite(v)]
    now = [v for s, v in curve if s <= step and math.isfinite(v)]
    if not before or not now:
        return None
    ref = min(before)
    if ref <= 0:
        return 0.0
    return (ref - min(now)) / ref


class ConvergenceStop(L.Callback):
    """Constant rate until ``monitor`` plateaus, then a linear decay to 0 and a stop.

    Args:
        monitor: the validation metric (lower is better), e.g. ``val/ate``.
        window: the fraction of the steps so far over which improvement is measured (0.25).
        min_improvement: relative improvement below which the model has converged (0.02).
        decay_fraction: the decay's length as a fraction of the steps at convergence (0.1).
        min_steps: no convergence is declared before this step.
        budget_steps: an equal budget instead of the rule (None: the rule): constant rate, then
            the decay over the last ``decay_fraction`` of these steps (``trainer.max_steps``
            should equal it; the study sets both).
        path: where the status JSON is written (None: nowhere).

    Needs a constant rate: a run with a learning-rate scheduler is refused at the start.
    """

    def __init__(
        self,
        monitor: str = "val/ate",
        window: float = 0.25,
        min_improvement: float = 0.02,
        decay_fraction: float = 0.1,
        min_steps: int = 1000,
        path: str | None = None,
        budget_steps: int | None = None,
    ) -> None:
        if not 0 < window < 1:
            raise ValueError(f"callbacks.convergence.window must be in (0, 1), got {window}")
        if min_improvement < 0:
            raise ValueError(
                f"callbacks.convergence.min_improvement must be ≥ 0, got {min_improvement}"
            )
        if not 0 < decay_fraction <= 1:
            raise ValueError(
                f"callbacks.convergence.decay_fraction must be in (0, 1], got {decay_fraction}"
            )
        self.monitor, self.window = monitor, float(window)
        self.min_improvement, self.decay_fraction = float(min_improvement), float(decay_fraction)
        self.min_steps = int(min_steps)
        if budget_steps is not None and int(budget_steps) < 2:
            raise ValueError(
                f"callbacks.convergence.budget_steps must be at least 2, got {budget_steps}"
            )
        self.budget_steps = None if budget_steps is None else int(budget_steps)
        self.path = Path(path) if path else None
        self.curve: list[tuple[int, float]] = []
        self.decay_start: int | None = None
        self.decay_end: int | None = None
        self.reason: str | None = None
        self.base_lrs: list[float] = []
        self.seconds = 0.0
        self._t0: float | None = None
        self._fit_start = 0.0
        self._step0 = 0
        self._reopen = False

    # -- the rule --------------------------------------------------------------------------

    def rule(self) -> dict[str, Any]:
        """The rule as stated (the report prints it)."""
        return {
            "monitor": self.monitor,
            "window": self.window,
            "min_improvement": self.min_improvement,
            "decay_fraction": self.decay_fraction,
            "min_steps": self.min_steps,
            "budget_steps": self.budget_steps,
        }

    def status(self, trainer: L.Trainer | None = None) -> dict[str, Any]:
        """``converged`` (bool), ``reason``, the decay's steps, the curve and the rule."""
        step = int(trainer.global_step) if trainer is not None else None
        return {
            "rule": self.rule(),
            "converged": self.reason == "plateau",
            "reason": self.reason,
            "decay_start": self.decay_start,
            "decay_end": self.decay_end,
            "step": step,
            "seconds": self.seconds,
            "curve": [{"step": s, self.monitor: v} for s, v in self.curve],
        }

    # -- Lightning hooks -------------------------------------------------------------------

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.lr_scheduler_configs:
            raise ValueError(
                "callbacks.convergence decays the rate itself: set model.scheduler=null "
                "(a constant rate until the plateau rule is met)"
            )
        self._t0, self._step0 = time.perf_counter(), int(trainer.global_step)
        self._fit_start = self._t0
        # A run the caps decayed, resumed with more room (a larger max_steps, or a new session's
        # time): back to the constant rate, so that a longer budget can still meet the rule.
        capped = self.reason in ("step cap", "time cap")
        more_steps = (
            not trainer.max_steps
            or trainer.max_steps < 0
            or (self.decay_end is not None and trainer.max_steps > self.decay_end)
        )
        if capped and (more_steps or self.reason == "time cap"):
            self._reopen = True
            self.decay_start = self.decay_end = self.reason = None

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # A run that has already decayed to its end (a finished model resumed by a study that
        # lost its stage results) must not train on: without this it would run one more
        # validation interval at the rate's end and overwrite its checkpoints.
        if self.decay_end is not None and int(trainer.global_step) >= self.decay_end:
            log.info(
                "callbacks.convergence: the run ended at step %d (%s); nothing to train",
                self.decay_end, self.reason,
            )  # fmt: skip
            trainer.should_stop = True

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        groups = [g for opt in trainer.optimizers for g in opt.param_groups]
        if self.budget_steps is not None and self.decay_start is None:
            # the schedule is known from the start: no test, no cap (max_steps is the budget)
            span = max(1, math.ceil(self.decay_fraction * self.budget_steps))
            self.decay_start = max(0, self.budget_steps - span)
            self.decay_end, self.reason = self.budget_steps, "budget"
        if self._reopen:
            for g, base in zip(groups, self.base_lrs, strict=True):
                g["lr"] = base
            self._reopen, self.base_lrs = False, []
        if self.decay_start is None or self.decay_end is None:
            return
        if not self.base_lrs:
            self.base_lrs = [float(g["lr"]) for g in groups]
        span = max(1, self.decay_end - self.decay_start)
        # clamped at 1: under a budget the decay's start is set before the run reaches it
        factor = min(1.0, max(0.0, 1.0 - (int(trainer.global_step) - self.decay_start) / span))
        for g, base in zip(groups, self.base_lrs, strict=True):
            g["lr"] = base * factor

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        step = int(trainer.global_step)
        if self._t0 is not None:
            now = time.perf_counter()
            self.seconds += now - self._t0
            self._t0 = now
        value = trainer.callback_metrics.get(self.monitor)
        v = float(value) if value is not None else math.nan
        if not self.curve or self.curve[-1][0] != step:
            self.curve.append((step, v))
        if self.decay_start is None:
            self._maybe_start_decay(trainer, step)
        if self.decay_end is not None and step >= self.decay_end:
            trainer.should_stop = True
        self._write(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.reason is None:
            self.reason = "stopped before the rule was met"
        self._write(trainer)

    def _maybe_start_decay(self, trainer: L.Trainer, step: int) -> None:
        gain = plateau_improvement(self.curve, step, self.window)
        decay = max(1, math.ceil(self.decay_fraction * step))
        interval = _val_interval(trainer)
        end = step + interval * math.ceil(decay / interval)
        if step >= self.min_steps and gain is not None and gain < self.min_improvement:
            self.reason = "plateau"
        elif trainer.max_steps and trainer.max_steps > 0 and end >= trainer.max_steps:
            self.reason = "step cap"
            end = int(trainer.max_steps)
        elif self._time_cap(trainer, step, end):
            self.reason = "time cap"
        else:
            return
        self.decay_start, self.decay_end = step, max(end, step + 1)

    def _time_cap(self, trainer: L.Trainer, step: int, end: int) -> bool:
        """Would the decay from here overrun ``trainer.max_time`` at the pace so far?"""
        from lightning.pytorch.callbacks import Timer

        timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
        remaining = None if timer is None else timer.time_remaining("train")
        done = step - self._step0
        if remaining is None or done <= 0 or self.seconds <= 0:
            return False
        # seconds per step this session (validations included: the decay has them too)
        per_step = (time.perf_counter() - self._fit_start) / done
        return per_step * (end - step) >= float(remaining)

    def _write(self, trainer: L.Trainer) -> None:
        if self.path is not None and trainer.is_global_zero:
            atomic_write_text(self.path, json.dumps(self.status(trainer), indent=1) + "\n")

    # -- resume ----------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "curve": [list(p) for p in self.curve],
            "decay_start": self.decay_start,
            "decay_end": self.decay_end,
            "reason": self.reason,
            "base_lrs": self.base_lrs,
            "seconds": self.seconds,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.curve = [(int(s), float(v)) for s, v in state.get("curve", [])]
        self.decay_start = state.get("decay_start")
        self.decay_end = state.get("decay_end")
        self.reason = state.get("reason")
        self.base_lrs = [float(x) for x in state.get("base_lrs", [])]
        self.seconds = float(state.get("seconds", 0.0))


def _val_interval(trainer: L.Trainer) -> int:
    """Steps between validations (an integer ``val_check_interval``; else one epoch)."""
    v = trainer.val_check_interval
    if isinstance(v, int) and v > 0:
        return v
    n = trainer.num_training_batches
    return max(1, int(n * float(v))) if math.isfinite(n) else 1
