"""The study's rules that read measurements: the smallest top-k within a tolerance and an error's
growth with moving-object coverage. The stages record them (:mod:`mfg_lightning.study.run`) and
the verdicts judge them (:mod:`mfg_lightning.study.sentences`, :mod:`mfg_lightning.study.claims`),
so they live here, once, away from the training code: an import contract (pyproject
``[tool.importlinter]``, ``verdicts-without-training``) keeps the verdict side from importing
:mod:`mfg_lightning.run.training`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

__all__ = ["growth", "growth_ends", "smallest_k", "smallest_k_by_ratio"]


def smallest_k(val: Mapping[str, Mapping[str, float]], tolerance: float) -> float | None:
    """The smallest k whose validation ATE is within ``tolerance`` of the full model's."""
    full = val.get("1", {}).get("ate")
    if full is None or not math.isfinite(full):
        return None
    ok = [float(k) for k, m in val.items() if m.get("ate", math.inf) <= (1 + tolerance) * full]
    return min(ok) if ok else 1.0


def smallest_k_by_ratio(ratios: Mapping[float, float | None], tol: float) -> float | None:
    """The smallest k whose ratio to all units' is ≤ 1 + ``tol``, scanning down from the
    largest k and stopping at the first that fails (a k below a failing one does not count)."""
    ok = None
    for k in sorted(ratios, reverse=True):
        r = ratios[k]
        if r is None or r > 1 + tol:
            break
        ok = k
    return ok


def growth_ends(bins: list[Mapping]) -> tuple[float, float] | None:
    """The mean errors of the most and of the least covered non-empty bins of moving-object
    coverage (None with fewer than two)."""
    filled = [b for b in bins if b["n"] and b["mean"] is not None]
    return (filled[-1]["mean"], filled[0]["mean"]) if len(filled) >= 2 else None


def growth(bins: list[Mapping]) -> float | None:
    """Mean error of the most covered non-empty bin over that of the least covered one."""
    ends = growth_ends(bins)
    return ends[0] / ends[1] if ends and ends[1] else None
