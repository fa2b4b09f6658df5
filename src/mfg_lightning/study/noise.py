"""The seed spread of the study's measurements, and the print precision of the paper's numbers.

The main model is trained at several seeds (the same pairs, convergence rule and step cap; the
seed sets the initialisation and the data order). Every measurement a verdict uses is taken from
each seed's model, so each has a mean and a spread over seeds (:class:`Spread`); the verdicts'
intervals are built from it by :mod:`mfg_lightning.study.intervals`. Nothing here reads files:
the views of each seed's results are built by :func:`mfg_lightning.study.sentences.seed_views`.

* :func:`print_precision`: a number printed as 0.012 stands for anything in [0.0115, 0.0125);
* :func:`tolerance` (:class:`Tolerance`): the larger of a print precision and two sample
  standard deviations of a spread, relative to its mean: the margin a configuration choice (the
  input scale) must beat on validation before the report says the evidence supports it.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

from mfg_lightning.core.tables import fmt

__all__ = [
    "SEED_SIGMAS",
    "Spread",
    "Tolerance",
    "print_precision",
    "ratio",
    "spread_of",
    "tolerance",
]

#: Standard deviations of the seed spread that a verdict tolerates.
SEED_SIGMAS = 2.0


@dataclass(frozen=True)
class Spread:
    """One measurement over the seeds that have it: ``values`` in seed order, ``seeds`` their
    seeds."""

    values: tuple[float, ...]
    seeds: tuple[int, ...] = ()

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def mean(self) -> float | None:
        return statistics.fmean(self.values) if self.values else None

    @property
    def std(self) -> float | None:
        """The sample standard deviation (None with fewer than two seeds)."""
        return statistics.stdev(self.values) if self.n >= 2 else None

    @property
    def relative_std(self) -> float | None:
        """``std / |mean|`` (None when undefined)."""
        if self.std is None or not self.mean:
            return None
        return self.std / abs(self.mean)

    def text(self, digits: int = 4) -> str:
        """``mean ± std (n seeds)``, or the single value with ``(1 seed)``."""
        if not self.values:
            return "–"
        if self.n == 1:
            return f"{fmt(self.mean, digits)} (1 seed)"
        return f"{fmt(self.mean, digits)} ± {fmt(self.std, digits)} ({self.n} seeds)"


def spread_of(
    views: Mapping[int, Mapping[str, Any]], measure: Callable[[Mapping[str, Any]], float | None]
) -> Spread:
    """``measure`` of every seed's view where it is defined and finite, in seed order."""
    vals, seeds = [], []
    for seed in sorted(views):
        try:
            v = measure(views[seed])
        except (KeyError, TypeError, ZeroDivisionError):
            v = None
        if v is not None and math.isfinite(v):
            vals.append(float(v))
            seeds.append(seed)
    return Spread(tuple(vals), tuple(seeds))


def print_precision(*printed: str) -> float:
    """The relative uncertainty that rounding leaves in a product or ratio of numbers printed
    as ``printed`` (decimal strings as the paper prints them): the sum over them of half a unit
    in the last printed place over the value. ``print_precision("0.012", "0.012")`` is
    0.0005/0.012 · 2 = 0.0833."""
    total = 0.0
    for p in printed:
        d = Decimal(p)
        if d == 0:
            raise ValueError(f"print_precision: a printed zero has no relative precision ({p!r})")
        half_unit = Decimal(5) * Decimal(10) ** (d.as_tuple().exponent - 1)
        total += float(half_unit / abs(d))
    return total


@dataclass(frozen=True)
class Tolerance:
    """A verdict's relative tolerance and where it comes from."""

    value: float
    printed: float
    seeds: float | None
    n_seeds: int

    @property
    def source(self) -> str:
        if self.seeds is not None and self.seeds >= self.printed:
            return f"{SEED_SIGMAS:g} sd of {self.n_seeds} seeds"
        if self.printed > 0:
            return "the paper's print precision"
        return "none measured" if self.seeds is None else f"{self.n_seeds} seeds agree exactly"

    def text(self) -> str:
        return f"±{100 * self.value:.1f} % ({self.source})"


def tolerance(spread: Spread | None, printed: float = 0.0) -> Tolerance:
    """The larger of ``printed`` (relative) and :data:`SEED_SIGMAS` relative standard
    deviations of ``spread`` (which may be the spread of another, analogous measurement: the
    caller says so)."""
    rel = spread.relative_std if spread is not None else None
    seeds = None if rel is None else SEED_SIGMAS * rel
    return Tolerance(max(printed, seeds or 0.0), printed, seeds, spread.n if spread else 0)


def ratio(a: float | None, b: float | None) -> float | None:
    """``a / b``; None when either is undefined, not finite, or ``b`` is 0."""
    if a is None or b is None or not b or not (math.isfinite(a) and math.isfinite(b)):
        return None
    return a / b
