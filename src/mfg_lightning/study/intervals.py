"""Verdicts that can fail: a 95 % interval per judged value and three outcomes.

Every part of a sentence's verdict (:mod:`mfg_lightning.study.sentences`) is a value with a
95 % interval (:class:`Interval`) compared with a bound in the direction the sentence claims:

* **holds**: the whole interval lies on the claimed side of the bound;
* **does not hold**: the whole interval lies on the other side;
* **inconclusive**: the interval straddles the bound, or it covers every value the quantity can
  take (a fraction's [0, 1]: no measurement could have decided it).

The interval (:func:`interval`) is built from what varies:

* **over seeds**, where several models were trained: Student's t at ``n − 1`` degrees of freedom
  on the seeds' mean, ``t · sd / √n`` (SciPy's quantiles);
* **a grid value over seeds** (a chosen k, which a t interval would take off the grid): the
  seeds' median and the exact sign test's interval (:func:`median_interval`);
* **over test pairs**, where the stage kept per-pair values: the paired moving-block
  bootstrap's standard error of the value (:func:`bootstrap_se`: runs of :data:`BLOCK_PAIRS`
  consecutive pairs, whose errors are correlated; the same resampled pairs for both sides of a
  comparison), ``1.96 · se``, since every seed is tested on the same pairs and their spread
  does not contain the test set's sampling;
* **a stand-in seed spread** where one model is judged: the sample sd of the same measurement
  over ``n`` seeds of another model at the same data size, ``t · sd · √(1 + 1/n)`` (a
  prediction interval for one more draw);

and the parts present add in quadrature. A bound read off the paper's printed numbers is itself
known only to their print precision (:func:`mfg_lightning.study.noise.print_precision`: 0.012 /
0.012 is known to ±8.3 %), so the interval is widened by that fraction of the bound on each
side (:meth:`Interval.widened`).

A ratio is judged only when its denominator is at least a stated floor (:data:`FLOORS`);
below it the part is **no verdict** and says so. A sentence holds when every part holds, does
not hold when at least one part does not hold, and is otherwise **partly** (some parts hold,
the rest are inconclusive) or **inconclusive** (none holds) (:func:`combine`).

A sentence judged in several parts makes several claims at once: at 95 % each, one of ``m``
independent parts would be decided wrongly by chance far more often than one time in twenty
(S10's 18 parts: 1 − 0.95¹⁸ = 60 %). The parts of one sentence are therefore a family, decided
by Holm's step-down procedure at a family level of 95 % (:func:`holm`), which rebuilds each
interval at its own level from the ingredients it keeps (:attr:`Interval.terms`).

Holm's procedure and the bootstrap are this module's own: Holm's reads intervals (a bound's
print precision, a domain, a strict bound), which a p-value does not carry, and the bootstrap
draws every resample at once. ``tests/test_study_intervals.py`` checks both against maintained
implementations: statsmodels' ``multipletests(method="holm")`` on the p-values dual to the
intervals (the same decisions on every family of the committed report), arch's
``MovingBlockBootstrap`` (the same resampled indices from the same generator, so the same
standard errors).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import stats

from mfg_lightning.study.constants import STATISTICS

__all__ = [
    "BLOCK_PAIRS",
    "BOOTSTRAP_DRAWS",
    "FLOORS",
    "HOLDS",
    "INCONCLUSIVE",
    "NOT_HOLD",
    "NO_SPREAD",
    "NO_VERDICT",
    "PARTLY",
    "Claim",
    "Interval",
    "bootstrap_se",
    "combine",
    "construction",
    "difference",
    "holm",
    "interval",
    "interval_verdict",
    "median_interval",
    "quantile",
    "t_quantile",
]

HOLDS, NOT_HOLD, INCONCLUSIVE, PARTLY = "holds", "does not hold", "inconclusive", "partly"
NO_VERDICT = "no verdict"
#: The construction of an interval built from one value and nothing that varies.
NO_SPREAD = "one value, no spread measured"
#: Resamples of the paired bootstrap, test pairs per block of the moving-block bootstrap, and the
#: smallest denominator a judged ratio may have per quantity: ``conf/reproduce.yaml``'s
#: ``statistics`` block, which says why each is what it is.
BOOTSTRAP_DRAWS = int(STATISTICS.bootstrap_draws)
BLOCK_PAIRS = int(STATISTICS.block_pairs)
FLOORS: dict[str, float] = dict(STATISTICS.floors)


# cached: Holm's procedure rebuilds intervals at a few levels many times
@lru_cache(maxsize=512)
def t_quantile(df: int, level: float = 0.95) -> float:
    """The two-sided Student's t quantile at ``level`` for ``df`` ≥ 1 degrees of freedom
    (SciPy's ``t.ppf``; t(2) = 4.303, t(4) = 2.776)."""
    if df < 1:
        raise ValueError(f"t_quantile needs at least one degree of freedom, got {df}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"t_quantile needs a level in (0, 1), got {level}")
    return float(stats.t.ppf(1 - (1 - level) / 2, df))


@lru_cache(maxsize=512)
def quantile(df: int, level: float = 0.95) -> float:
    """The two-sided quantile of an interval's term: Student's t at ``df`` ≥ 1 degrees of
    freedom, the normal distribution's at ``df = 0``."""
    if df == 0:
        return float(stats.norm.ppf(1 - (1 - level) / 2))
    return t_quantile(df, level)


@dataclass(frozen=True)
class Interval:
    """A value and its 95 % interval ``[lo, hi]``; ``how`` says what it was built from.

    Attributes:
        terms: the ingredients of the half-width, ``(df, scale)`` each (``df`` ≥ 1: Student's t
            at ``df`` degrees of freedom; 0: the normal distribution): the half-width at a level
            is ``√Σ (quantile(df, level) · scale)²`` plus ``pad``. Empty: the interval is known
            at 95 % only.
        pad: a fixed widening on each side (a bound's print precision), at every level.
    """

    value: float
    lo: float
    hi: float
    how: str = ""
    terms: tuple[tuple[int, float], ...] = ()
    pad: float = 0.0

    def widened(self, fraction: float, bound: float) -> Interval:
        """Widened by ``fraction · |bound|`` on each side (the bound's print precision)."""
        if fraction <= 0:
            return self
        w = fraction * abs(bound)
        how = f"{self.how}; ±{100 * fraction:.1f} % of the bound (the paper's print precision)"
        return Interval(self.value, self.lo - w, self.hi + w, how.lstrip("; "), self.terms,
                        self.pad + w)  # fmt: skip

    def at(self, level: float) -> Interval:
        """The same interval rebuilt at ``level`` (itself where it has no :attr:`terms`)."""
        if not self.terms or level == 0.95:
            return self
        half = math.sqrt(sum((quantile(df, level) * sc) ** 2 for df, sc in self.terms))
        half += self.pad
        return Interval(self.value, self.value - half, self.value + half, self.how, self.terms,
                        self.pad)  # fmt: skip

    def text(self, fmt_value: Callable[[float], str]) -> str:
        return f"{fmt_value(self.value)} [{fmt_value(self.lo)}, {fmt_value(self.hi)}]"


def bootstrap_se(
    stat: Callable[[np.ndarray], np.ndarray],
    n_pairs: int,
    draws: int = BOOTSTRAP_DRAWS,
    seed: int = 0,
    block: int = BLOCK_PAIRS,
) -> float | None:
    """The standard error of a statistic over test pairs by the paired moving-block bootstrap.

    Args:
        stat: the statistic of every resample at once: ``(draws, n)`` indices of the pairs
            (one resample a row) → ``(draws,)`` values. Every side of a comparison reads the
            same rows, which makes it paired.
        n_pairs: the test pairs, in their temporal order (sequence by sequence, frame by frame).
        draws, seed: resamples and the generator's seed.
        block: pairs per block (:data:`BLOCK_PAIRS`; 1: the plain bootstrap). A resample is
            ``⌈n / block⌉`` runs of consecutive pairs from uniform starts, cut to ``n``; a run
            may span the boundary between two test sequences, which only mixes their errors.

    Returns:
        The sd of the finite values (None with fewer than two pairs, or fewer than half of the
        resamples finite).
    """
    if n_pairs < 2:
        return None
    block = max(1, min(int(block), n_pairs))
    runs = -(-n_pairs // block)
    starts = np.random.default_rng(seed).integers(0, n_pairs - block + 1, (draws, runs))
    idx = (starts[:, :, None] + np.arange(block)).reshape(draws, -1)[:, :n_pairs]
    with np.errstate(divide="ignore", invalid="ignore"):
        vals = np.asarray(stat(idx), dtype=float)
    vals = vals[np.isfinite(vals)]
    return float(np.std(vals, ddof=1)) if len(vals) >= max(2, draws // 2) else None


def construction(n_seeds: int, boot: bool, proxy: tuple[int, str] | None = None) -> str:
    """The interval's construction in words (the report prints it beside each part)."""
    parts = []
    if n_seeds >= 2:
        parts.append(f"t over {n_seeds} seeds")
    if proxy is not None:
        parts.append(f"the sd of {proxy[1]} over {proxy[0]} seeds")
    if boot:
        parts.append(f"paired bootstrap over the test pairs in blocks of {BLOCK_PAIRS}")
    return " + ".join(parts) if parts else NO_SPREAD


def interval(
    values: Sequence[float],
    boot_se: Sequence[float | None] = (),
    proxy: tuple[float, int, str] | None = None,
) -> Interval | None:
    """The 95 % interval of the mean of ``values`` (one per seed).

    Args:
        values: the value of every seed (finite ones are kept).
        boot_se: per seed, the paired bootstrap's standard error over the test pairs (None where
            not computed); their root mean square is the test pairs' part.
        proxy: ``(sd, n, what)``: where ``values`` has one seed, the sample sd of the same
            measurement over ``n`` seeds of another model at the same data size (``what``).

    Returns:
        The :class:`Interval`, or None when no value is finite.
    """
    xs = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not xs:
        return None
    mean = statistics.fmean(xs)
    terms: list[tuple[int, float]] = []
    if len(xs) >= 2:
        terms.append((len(xs) - 1, statistics.stdev(xs) / math.sqrt(len(xs))))
    used_proxy = None
    if len(xs) == 1 and proxy is not None and proxy[1] >= 2 and math.isfinite(proxy[0]):
        terms.append((proxy[1] - 1, proxy[0] * math.sqrt(1 + 1 / proxy[1])))
        used_proxy = (proxy[1], proxy[2])
    ses = [float(s) for s in boot_se if s is not None and math.isfinite(s)]
    if ses:
        terms.append((0, math.sqrt(statistics.fmean(s * s for s in ses))))
    half = math.sqrt(sum((quantile(df) * sc) ** 2 for df, sc in terms))
    how = construction(len(xs), bool(ses), used_proxy)
    return Interval(mean, mean - half, mean + half, how, tuple(terms))


def difference(a: Sequence[float], b: Sequence[float]) -> Interval | None:
    """The mean of ``a`` minus the mean of ``b`` (two sets of seeds of different models, so no
    pairing), each side's t half-width added in quadrature: a conservative stand-in for
    Welch's interval."""
    ia, ib = interval(a), interval(b)
    if ia is None or ib is None:
        return None
    half = math.hypot(ia.value - ia.lo, ib.value - ib.lo)
    d = ia.value - ib.value
    how = f"t over {len(a)} and {len(b)} seeds, in quadrature"
    return Interval(d, d - half, d + half, how, ia.terms + ib.terms)


def median_interval(
    values: Sequence[float], domain: tuple[float, float], level: float = 0.95
) -> Interval | None:
    """The median of ``values`` (one per seed) and its distribution-free interval, for values on
    a grid (a chosen k), where a t interval leaves the grid (a negative k).

    The interval is the order statistics ``[x_(r), x_(n+1−r)]`` of the largest ``r`` whose
    coverage of the median, ``1 − 2 · P(B ≤ r − 1)`` with ``B ~ Binomial(n, ½)``, is at least
    ``level``: the values the exact sign test does not reject. Where no ``r`` reaches it (fewer
    than 6 seeds at 95 %: ``[min, max]`` of 5 covers 93.75 %) it is the whole ``domain``: the
    seeds cannot place the median at that level. Known at ``level`` only (no
    :attr:`Interval.terms`): for a sentence of one part.
    """
    xs = sorted(float(v) for v in values if v is not None and math.isfinite(v))
    if not xs:
        return None
    n = len(xs)
    r = max((c for c in range(1, n // 2 + 1) if 1 - 2 * stats.binom.cdf(c - 1, n, 0.5) >= level),
            default=0)  # fmt: skip
    if r:
        lo, hi = xs[r - 1], xs[n - r]
        how = f"sign test over {n} seeds: order statistics {r} and {n + 1 - r}"
    else:
        lo, hi = domain
        how = (f"sign test over {n} seed{'s' * (n != 1)}: their range covers the median with "
               f"{100 * (1 - 2 * 0.5**n):.1f} % at most, below {100 * level:g} %, so the "
               "interval is the whole grid")  # fmt: skip
    return Interval(float(np.median(xs)), float(lo), float(hi), how)


def interval_verdict(
    iv: Interval | None,
    bound: float,
    direction: str,
    domain: tuple[float, float] | None = None,
    strict: bool = False,
) -> str:
    """holds / does not hold / inconclusive (see the module docstring); ``domain``: the values
    the quantity can take (an interval covering all of it is inconclusive whatever its side).
    ``strict``: the bound itself is on the wrong side (better than, not as good as). No interval
    (nothing measured): :data:`NO_VERDICT`."""
    if direction not in ("<=", ">="):
        raise ValueError(f"direction must be '<=' or '>=', got {direction!r}")
    if iv is None or not (math.isfinite(iv.lo) and math.isfinite(iv.hi)):
        return NO_VERDICT
    if domain is not None and iv.lo <= domain[0] and iv.hi >= domain[1]:
        return INCONCLUSIVE
    # a mean of equal values (0.05, 0.05, 0.05) is 0.05000000000000001: not beyond its bound
    eps = 1e-12 * max(1.0, abs(bound))
    # strict: a claim of "better than" is not shown by an interval that sits on the bound (a
    # method that detects nothing has exactly the no-motion error)
    e = -eps if strict else eps
    if direction == "<=":
        claimed, other = iv.hi <= bound + e, iv.lo > bound + e
    else:
        claimed, other = iv.lo >= bound - e, iv.hi < bound - e
    return HOLDS if claimed else NOT_HOLD if other else INCONCLUSIVE


def combine(verdicts: Sequence[str]) -> str:
    """A sentence's verdict from its parts' (parts without a verdict left out): every part
    holds, holds; one does not hold, does not hold; some hold and the rest are inconclusive,
    partly; none holds, inconclusive."""
    judged = [v for v in verdicts if v != NO_VERDICT]
    if not judged:
        return NO_VERDICT
    if any(v == NOT_HOLD for v in judged):
        return NOT_HOLD
    if all(v == HOLDS for v in judged):
        return HOLDS
    return PARTLY if any(v == HOLDS for v in judged) else INCONCLUSIVE


@dataclass(frozen=True)
class Claim:
    """One part of a family for :func:`holm`: its interval at 95 % and its bound, the claimed
    direction, the domain and strictness of :func:`interval_verdict`."""

    iv: Interval
    bound: float
    direction: str
    domain: tuple[float, float] | None = None
    strict: bool = False

    def verdict(self, level: float = 0.95) -> str:
        return interval_verdict(
            self.iv.at(level), self.bound, self.direction, self.domain, self.strict
        )

    def decisiveness(self) -> float:
        """Holm's order: −log of the dual p-value (the smallest α whose interval at 1 − α is
        decided; bisection on :meth:`verdict`): ∞ if decided at every level, 0 if at none."""
        decided = lambda a: self.verdict(1 - a) in (HOLDS, NOT_HOLD)  # noqa: E731
        if decided(lo := 1e-15) or not decided(hi := 1 - 1e-9):
            return math.inf if decided(lo) else 0.0
        for _ in range(60):
            lo, hi = (lo, m) if decided(m := math.sqrt(lo * hi)) else (m, hi)
        return -math.log(hi)


def holm(claims: Sequence[Claim], family: float = 0.05) -> list[tuple[str, float]]:
    """Holm's step-down procedure over one sentence's parts: the verdict of every claim and the
    level it was judged at, in the claims' order.

    The claims are taken from the smallest p-value (:meth:`Claim.decisiveness`); the ``i``-th
    (from 0) of ``m`` is judged at ``1 − family / (m − i)``. While each is decided (holds or
    does not hold) at its level the next is taken; the first that is not, and every claim after
    it, is inconclusive. One claim: its verdict at ``1 − family``, unchanged."""
    m = len(claims)
    order = sorted(range(m), key=lambda i: -claims[i].decisiveness())
    out: dict[int, tuple[str, float]] = {}
    for step, i in enumerate(order):
        level = 1 - family / (m - step)
        v = claims[i].verdict(level)
        out[i] = (v, level)
        if v not in (HOLDS, NOT_HOLD):
            out.update({j: (INCONCLUSIVE, level) for j in order[step + 1 :]})
            break
    return [out[i] for i in range(m)]
