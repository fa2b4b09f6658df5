"""The statistics every metric reports, computed in one place, and the names they are read by.

* :func:`statistics`: evo's seven statistics of a set of per-element errors (``max``, ``mean``,
  ``median``, ``min``, ``rmse``, ``sse``, ``std``; ``evo_ape`` and ``evo_rpe`` print these);
  :func:`summary`: the three of them every metric logs (mean, standard deviation and RMSE).
  The standard deviation is the population one (``np.std``, as Zhou et al. and ``evo``) unless
  ``correction`` says otherwise. Each is NaN when the set is empty (an undefined metric, e.g. a
  path shorter than a drift segment), never an exception.
* :func:`cat_state`: a torchmetrics list state as one tensor (a tensor already after a DDP sync).
* :class:`MetricValues`: a metric's results under their published names (``docs/protocols.md``),
  which also answers to the names used before them.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics.utilities import dim_zero_cat

__all__ = ["RENAMED", "STATISTICS", "MetricValues", "cat_state", "statistics", "summary"]

#: evo's statistics of a set of errors, in the order it prints them.
STATISTICS: tuple[str, ...] = ("max", "mean", "median", "min", "rmse", "sse", "std")


def statistics(
    values: Tensor, correction: int = 0, names: tuple[str, ...] = STATISTICS
) -> dict[str, Tensor]:
    """evo's statistics of per-element errors (the one place they are computed).

    Args:
        values: ``(S,)`` errors in any unit (any float dtype; computed in float64).
        correction: ``0`` (default) the population standard deviation (evo, every protocol);
            ``1`` the sample standard deviation (a spread over runs or seeds). NaN when
            ``S <= correction``.
        names: which of :data:`STATISTICS` to compute.

    Returns:
        ``{name: value}`` for ``names``: float64 scalars in the unit of ``values`` (``sse``, the
        sum of squares, in its square); NaN each when ``S == 0``. The ``median`` of an even count
        is the mean of the two middle values (``np.median``, as evo).
    """
    v = values.reshape(-1).double()
    nan = torch.tensor(float("nan"), dtype=torch.float64, device=v.device)
    if v.numel() == 0:
        return {name: nan.clone() for name in names}
    compute = {
        "max": lambda: v.max(),
        "mean": lambda: v.mean(),
        "median": lambda: v.quantile(0.5),
        "min": lambda: v.min(),
        "rmse": lambda: v.square().mean().sqrt(),
        "sse": lambda: v.square().sum(),
        "std": lambda: nan.clone() if v.numel() <= correction else v.std(correction=correction),
    }
    return {name: compute[name]() for name in names}


def summary(values: Tensor, correction: int = 0) -> dict[str, Tensor]:
    """Mean, standard deviation and RMSE of per-element errors: :func:`statistics` restricted
    to ``("mean", "std", "rmse")``, the three every metric logs.

    Args:
        values: ``(S,)`` errors in any unit (any float dtype; computed in float64).
        correction: as :func:`statistics`.

    Returns:
        ``{"mean", "std", "rmse"}``: float64 scalars in the unit of ``values``; NaN when ``S == 0``.
    """
    return statistics(values, correction, ("mean", "std", "rmse"))


def cat_state(state: list[Tensor] | Tensor) -> Tensor:
    """A concatenated list state (a tensor already after a DDP sync); empty float64 if none."""
    if isinstance(state, list) and not state:
        return torch.zeros(0, dtype=torch.float64)
    return dim_zero_cat(state)


#: Names the metric functions returned before they took the published (logged) names → the
#: published name of the same quantity; results written with the old names still read.
RENAMED: dict[str, str] = {
    **{
        f"{part}{stat}": f"rpe_{part}{stat}"
        for part in ("trans", "rot")
        for stat in ("", "_std", "_rmse")
    },
    "t_err": "drift_t_err",
    "r_err": "drift_r_err",
}


class MetricValues(dict):
    """A metric's results keyed by their published names, also readable by earlier names.

    Iterating, ``keys()``, ``items()`` and ``len()`` see the published names only (one name per
    quantity); ``values[old]``, ``values.get(old)`` and ``old in values`` still answer for the
    names of :data:`RENAMED` (``"trans"`` for ``"rpe_trans"``, ``"t_err"`` for ``"drift_t_err"``,
    …), so code written against them keeps working. A plain ``dict`` subclass: torchmetrics'
    ``compute`` rebuilds it as ``MetricValues(mapping)``, and it pickles as a dict does.
    """

    def __missing__(self, key: str) -> Any:
        if key in RENAMED and dict.__contains__(self, RENAMED[key]):
            return self[RENAMED[key]]
        raise KeyError(key)

    def __contains__(self, key: object) -> bool:
        return dict.__contains__(self, key) or (
            key in RENAMED and dict.__contains__(self, RENAMED[key])  # type: ignore[index]
        )

    def get(self, key: str, default: Any = None) -> Any:
        try:
            return self[key]
        except KeyError:
            return default
