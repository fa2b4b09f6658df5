"""The statistics every metric reports, computed in one place.

* :func:`summary`: mean, population standard deviation (``np.std``, as Zhou et al. and ``evo``)
  and root mean square of a set of per-element errors; NaN for each when the set is empty (an
  undefined metric, e.g. a path shorter than a drift segment), never an exception.
* :func:`cat_state`: a torchmetrics list state as one tensor (a tensor already after a DDP sync).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics.utilities import dim_zero_cat

__all__ = ["cat_state", "summary"]


def summary(values: Tensor) -> dict[str, Tensor]:
    """Mean, population std and RMSE of per-element errors.

    Args:
        values: ``(S,)`` errors in any unit (any float dtype; computed in float64).

    Returns:
        ``{"mean", "std", "rmse"}``: float64 scalars in the unit of ``values``; NaN when ``S == 0``.
    """
    v = values.reshape(-1).double()
    if v.numel() == 0:
        nan = torch.tensor(float("nan"), dtype=torch.float64, device=v.device)
        return {"mean": nan, "std": nan.clone(), "rmse": nan.clone()}
    return {"mean": v.mean(), "std": v.std(correction=0), "rmse": v.square().mean().sqrt()}


def cat_state(state: list[Tensor] | Tensor) -> Tensor:
    """A concatenated list state (a tensor already after a DDP sync); empty float64 if none."""
    if isinstance(state, list) and not state:
        return torch.zeros(0, dtype=torch.float64)
    return dim_zero_cat(state)
