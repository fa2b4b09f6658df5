"""The report's conclusion words, each computed from the number it describes.

Every comparative or quantifier of the generated reading (:mod:`mfg_lightning.study.prose`,
:mod:`mfg_lightning.study.settle_report`, :mod:`mfg_lightning.study.causes`) comes from one of
these functions, so that rerunning a stage with another outcome rewrites the words as well as the
digits. The thresholds are stated once, in ``conf/reproduce.yaml``'s ``statistics.wording``:

* :data:`SAME` (×1.1): two positive numbers within a factor 1.1 of each other are "about" equal.
  A difference under 10 % is below the resolution of the quantities the reading compares: the
  paper's Table 1 ratios are known to ±8.3 % (0.012 / 0.012, :func:`~mfg_lightning.study.noise.
  print_precision`) and the main model's seeds spread by 4–10 % relative sd (the report's noise
  paragraph), so a smaller step is not read as a direction.
* :data:`MUCH` (×1.5): from half as much again a difference reads "much".
* :data:`SEVERAL` (×3): "several times" means, in plain English, more than twice; it is used from
  ×3 on, and between ×1.5 and ×3 the words say "much".

Where an interval exists the words compare the interval, not its point estimate
(:func:`side`, :func:`position`): below, inside / not distinguishable, above.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from mfg_lightning.study.constants import STATISTICS

__all__ = [
    "MUCH",
    "SAME",
    "SEVERAL",
    "change",
    "compare",
    "count",
    "factor",
    "number",
    "percent",
    "position",
    "recipe_text",
    "rule_met",
    "side",
    "spelled",
]

#: Within this factor two numbers are "about" the same, from ``MUCH`` a difference is "much"
#: larger or smaller, from ``SEVERAL`` "several times" (``conf/reproduce.yaml``'s
#: ``statistics.wording``; see the module docstring).
SAME = float(STATISTICS.wording.same)
MUCH = float(STATISTICS.wording.much)
SEVERAL = float(STATISTICS.wording.several)


def count(x: int | float) -> str:
    """A count with thin-space thousands, as the report writes them (25 838)."""
    return f"{int(x):,}".replace(",", "\u202f")


def percent(x: float | None, digits: int = 1) -> str:
    """A fraction as a percentage ("–" when undefined)."""
    return "–" if x is None or not math.isfinite(x) else f"{100 * x:.{digits}f} %"


def spelled(n: int) -> str:
    """A small count in words ("one" … "nine"), as prose writes it; larger ones in digits."""
    words = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine")
    return words[n] if 0 <= n < len(words) else str(n)


def number(x: float) -> str:
    """A setting as a person writes it: ``1e-05`` → ``1e-5``, ``0.999`` → ``0.999``."""
    text = f"{float(x):g}"
    mantissa, e, exponent = text.partition("e")
    return f"{mantissa}e{int(exponent)}" if e else text


def factor(r: float | None) -> float | None:
    """How far ``r`` is from 1 either way (``max(r, 1 / r)``); None where ``r`` is undefined or
    not positive."""
    if r is None or not math.isfinite(r) or r <= 0:
        return None
    return max(r, 1.0 / r)


def compare(
    r: float | None, more: str = "worse", less: str = "better", same: str = "about as good as"
) -> str:
    """Words for "A … B" where ``r = A / B``: "several times worse than" (r ≥ :data:`SEVERAL`),
    "much worse than" (≥ :data:`MUCH`), "worse than" (≥ :data:`SAME`), ``same`` within
    :data:`SAME` either way, and the mirror images with ``less`` below 1."""
    f = factor(r)
    if f is None:
        return "not comparable with"
    if f < SAME:
        return same
    word = more if r >= 1 else less  # type: ignore[operator]
    if f >= SEVERAL:
        return f"several times {word} than"
    if f >= MUCH:
        return f"much {word} than"
    return f"{word} than"


def change(before: float | None, after: float | None, digits: int = 2) -> str:
    """How a positive quantity moves from ``before`` to ``after``: "falls ×3.2", "rises ×1.4",
    or "stays within 10 %" (:data:`SAME`); "is not measured" where either is undefined."""
    if before is None or after is None or before <= 0 or after <= 0:
        return "is not measured"
    f = factor(after / before)
    if f is None or f < SAME:
        return f"stays within {100 * (SAME - 1):.0f} %"
    return f"{'falls' if after < before else 'rises'} ×{f:.{digits}f}"


def position(value: float, lo: float, hi: float) -> str:
    """Where ``value`` lies against the range or band [``lo``, ``hi``]: "below", "inside" or
    "above" (the ends count as inside)."""
    return "below" if value < lo else "above" if value > hi else "inside"


def side(lo: float, hi: float, bound: float = 0.0) -> str:
    """Where an interval [``lo``, ``hi``] lies against ``bound``: "below" or "above" when it
    excludes it, "not distinguishable from" when it contains it (a point estimate on one side
    decides nothing)."""
    return "below" if hi < bound else "above" if lo > bound else "not distinguishable from"


def rule_met(c: Mapping[str, Any], rule: str = "the rule") -> str:
    """Whether a run's convergence record ``c`` met ``rule`` (``reason`` "plateau") or stopped
    for another reason (a step, time or budget cap), and at which step its decay began."""
    start = c.get("decay_start")
    if c.get("converged", c.get("reason") == "plateau"):
        return f"met {rule}" + (f" at step {count(start)}" if start is not None else "")
    why = f"did not meet {rule} ({c.get('reason') or 'no reason recorded'})"
    return why + (f" and began its decay at step {count(start)}" if start is not None else "")


def recipe_text(recipe: Mapping[str, Any]) -> str:
    """A run's recorded recipe in words ("batch 1, Adam lr 1e-5, betas 0.99 / 0.999")."""
    betas = recipe.get("betas") or []
    text = f"batch {recipe['batch_size']}, {recipe['optimizer']} lr {number(recipe['lr'])}"
    if betas:
        text += ", betas " + " / ".join(number(b) for b in betas)
    return text + (f", {recipe['scheduler']} schedule" if recipe.get("scheduler") else "")
