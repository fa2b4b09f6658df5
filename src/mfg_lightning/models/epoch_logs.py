"""Epoch-level values that a module logs already reduced over every DDP process."""

from __future__ import annotations

import re
import warnings

from lightning.fabric.utilities.warnings import PossibleUserWarning

__all__ = ["reduced_epoch_logs"]


def reduced_epoch_logs(*prefixes: str) -> None:
    """Declare the epoch-level values a module logs under ``prefixes`` (``"val/"``) already
    reduced over every process (the evaluator's gather, a torchmetrics ``compute``). Lightning
    advises ``sync_dist=True`` for each of them under DDP (about a hundred lines a run); for these
    values it would only average identical numbers again, so its advice is silenced for these
    names only (a process-wide warning filter; installing it twice keeps one)."""
    if not prefixes:  # an empty alternation would silence the advice for every name
        raise ValueError("reduced_epoch_logs needs at least one name prefix")
    names = "|".join(re.escape(p) for p in prefixes)
    warnings.filterwarnings(
        "ignore",
        message=rf"It is recommended to use `self\.log\('({names})",
        category=PossibleUserWarning,
    )
