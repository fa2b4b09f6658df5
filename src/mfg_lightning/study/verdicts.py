"""Verdicts of the reproduction study: holds / partly / does not hold, from stated thresholds.

A verdict compares a measured number with the paper's (or a measured ratio with the paper's
ratio) by relative deviation ``|ours / paper − 1|``: within ``holds`` (default 5 %) the claim
holds, within ``partly`` (default 20 %) it partly holds, beyond that it does not. Claims made of
several parts take the worst part's verdict (:func:`worst`) or count how many parts are met
(:func:`count_verdict`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

__all__ = [
    "HOLDS",
    "NOT_HOLD",
    "NOT_RUN",
    "PARTLY",
    "Thresholds",
    "combine_parts",
    "count_verdict",
    "no_worse_verdict",
    "relative_deviation",
    "relative_verdict",
    "worst",
]

HOLDS, PARTLY, NOT_HOLD = "holds", "partly", "does not hold"
NOT_RUN = "not run yet"
_ORDER = (HOLDS, PARTLY, NOT_HOLD)


@dataclass(frozen=True)
class Thresholds:
    """Relative deviations (fractions) within which a claim holds or partly holds."""

    holds: float = 0.05
    partly: float = 0.20

    def __post_init__(self) -> None:
        if not 0 <= self.holds <= self.partly:
            raise ValueError(
                f"verdict thresholds must satisfy 0 <= holds <= partly, got holds={self.holds}, "
                f"partly={self.partly}"
            )

    def text(self) -> str:
        return f"within {100 * self.holds:g} %: holds; within {100 * self.partly:g} %: partly"


def relative_deviation(ours: float | None, paper: float) -> float:
    """``|ours / paper − 1|`` (``|ours|`` when ``paper`` is 0; infinity when undefined)."""
    if ours is None or not math.isfinite(ours):
        return math.inf
    if paper == 0:
        return abs(ours)
    return abs(ours / paper - 1.0)


def relative_verdict(ours: float | None, paper: float, th: Thresholds = Thresholds()) -> str:
    """The verdict of one number against the paper's."""
    d = relative_deviation(ours, paper)
    return HOLDS if d <= th.holds else PARTLY if d <= th.partly else NOT_HOLD


def worst(verdicts: Iterable[str]) -> str:
    """The worst of several verdicts (does not hold < partly < holds)."""
    found = [v for v in verdicts]
    if not found:
        raise ValueError("worst() of no verdicts")
    return max(found, key=_ORDER.index)


def count_verdict(met: int, total: int) -> str:
    """All ``total`` parts met: holds; some: partly; none: does not hold."""
    if total <= 0:
        raise ValueError(f"count_verdict needs at least one part, got {total}")
    return HOLDS if met >= total else PARTLY if met > 0 else NOT_HOLD


def no_worse_verdict(
    ours: float | None, reference: float | None, th: Thresholds, higher_is_better: bool = False
) -> str:
    """Ours against a reference that it should match or beat: as good or better, or worse by
    at most ``holds`` (relative), holds; worse by at most ``partly``, partly; else does not hold
    (also when either is undefined)."""
    if ours is None or reference is None or not (math.isfinite(ours) and math.isfinite(reference)):
        return NOT_HOLD
    if reference == 0:
        return HOLDS if (ours >= 0 if higher_is_better else ours <= 0) else NOT_HOLD
    worse = 1.0 - ours / reference if higher_is_better else ours / reference - 1.0
    return HOLDS if worse <= th.holds else PARTLY if worse <= th.partly else NOT_HOLD


def combine_parts(verdicts: Iterable[str]) -> str:
    """A claim of several parts: every part holds, holds; none holds nor partly holds, does not
    hold; otherwise partly."""
    found = list(verdicts)
    if not found:
        return NOT_HOLD
    if all(v == HOLDS for v in found):
        return HOLDS
    if all(v == NOT_HOLD for v in found):
        return NOT_HOLD
    return PARTLY
