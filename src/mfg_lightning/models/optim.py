"""The optimiser and its learning-rate schedule, built from the config's partial constructors."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch


def checked_scheduler(scheduler: Callable[..., Any] | None) -> Callable[..., Any] | None:
    """``scheduler`` unchanged, after refusing a schedule length that is not positive: the
    default cosine schedule's ``T_max`` follows ``trainer.max_steps``, which is -1 in a run that
    counts epochs, and a non-positive length would silently drive the rate to nonsense."""
    keywords = getattr(scheduler, "keywords", None) or {}
    t_max = keywords.get("T_max")
    if t_max is not None and t_max <= 0:
        raise ValueError(
            f"model.scheduler.T_max must be a positive number of steps, got {t_max} (it follows "
            "trainer.max_steps); set model.scheduler.T_max=<steps>, or model.scheduler=null for "
            "a constant learning rate"
        )
    return scheduler


def optimizers(
    optimizer: Callable[..., torch.optim.Optimizer],
    scheduler: Callable[..., Any] | None,
    params: Iterable[torch.nn.Parameter],
) -> Any:
    """What ``configure_optimizers`` returns: the optimiser over ``params``, with its schedule
    stepped every training step when there is one."""
    opt = optimizer(params=params)
    if scheduler is None:
        return opt
    return {
        "optimizer": opt,
        "lr_scheduler": {"scheduler": scheduler(optimizer=opt), "interval": "step"},
    }
