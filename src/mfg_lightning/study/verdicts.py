"""What the report prints for a sentence whose stages have not run, and the relative deviation
the diagnostics print beside the paper's numbers (never a verdict: the verdicts are intervals
against bounds, :mod:`mfg_lightning.study.intervals`)."""

from __future__ import annotations

import math

__all__ = ["NOT_RUN", "relative_deviation"]

NOT_RUN = "not run yet"


def relative_deviation(ours: float | None, paper: float) -> float:
    """``|ours / paper − 1|`` (``|ours|`` when ``paper`` is 0; infinity when undefined)."""
    if ours is None or not math.isfinite(ours):
        return math.inf
    if paper == 0:
        return abs(ours)
    return abs(ours / paper - 1.0)
