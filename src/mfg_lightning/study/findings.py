"""The findings the report's reading states: typed, computed from the stage results, and read by
the templates (``templates/reading/*.md.j2``) that put them into words.

A finding holds numbers and intervals, never words: each property that decides a conclusion
(:attr:`Central.where`, :attr:`FlowGain.gain`, :attr:`Robustness.fall`) is a number or a place
against a bound, and the template turns it into words through the filters of
:mod:`mfg_lightning.study.wording`. A test (``tests/test_study_templates.py``) moves a finding
across a bound and checks that the rendered words move with it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from mfg_lightning.core.tables import fmt
from mfg_lightning.study.intervals import t_quantile
from mfg_lightning.study.noise import Spread, Tolerance, ratio, tolerance
from mfg_lightning.study.parts import SEQS
from mfg_lightning.study.wording import SAME, position

__all__ = [
    "Cached",
    "Central",
    "FlowGain",
    "InputScale",
    "LearnedFlow",
    "Robustness",
    "RuleWeakness",
    "SizeCurve",
    "Table2Contrast",
    "star_ranges",
    "verdict_count",
]

#: A stage's cached result by name (None where it has not run).
Cached = Callable[[str], Any]


@dataclass
class Central:
    """ATE * / ATE † (a diagnostic): MFG's seed mean per test sequence, the paper's, the
    classical methods' lowest and highest on the same flow, and the flow's error by offset
    (``epe``: offset, EPE px, Fl %; empty before ``flow_error`` has run)."""

    ours: dict[str, float | None]
    paper: dict[str, float]
    bounds: dict[str, tuple[float, float]]
    epe: list[tuple[int, float, float]] = field(default_factory=list)
    #: the pixel-pooled EPE at ±2 over that at ±1
    far_ratio: float | None = None

    @property
    def ranges(self) -> list[str]:
        return star_ranges(self.bounds)

    @property
    def where(self) -> dict[str, list[str]]:
        """MFG's ratio against the classical range ("below", "inside", "above"): the sequences."""
        out: dict[str, list[str]] = {}
        for s in SEQS:
            if self.ours.get(s) is not None and s in self.bounds:
                out.setdefault(position(self.ours[s], *self.bounds[s]), []).append(s)
        return out


def star_ranges(bounds: Mapping[str, tuple[float, float]]) -> list[str]:
    """The classical methods' ATE * / ATE † range per test sequence ("09 ×a–×b")."""
    return [f"{s} ×{fmt(bounds[s][0], 2)}–×{fmt(bounds[s][1], 2)}" if s in bounds else f"{s} –"
            for s in SEQS]  # fmt: skip


@dataclass
class FlowGain:
    """What the exact flow changes for MFG and for IRLS (RPE rotation, rad, one Table-2-sized
    run each on exact and on DIS flow)."""

    mfg_exact: float | None
    mfg_dis: float | None
    irls_exact: float | None
    irls_dis: float | None

    @property
    def gain(self) -> float | None:
        """How much more the exact flow lowers IRLS's error than MFG's (the two falls' ratio)."""
        return ratio(ratio(self.irls_dis, self.irls_exact), ratio(self.mfg_dis, self.mfg_exact))

    @property
    def mixed(self) -> float | None:
        """MFG on exact flow over IRLS on DIS (the paper's Table 2 read literally)."""
        return ratio(self.mfg_exact, self.irls_dis)


@dataclass
class Table2Contrast:
    """The main model on the full split against the classical methods on DIS, and the
    Table-2-sized model's ratio over IRLS on the same flow (``small``, one seed)."""

    full: Spread
    irls: float | None
    best: float | None
    small: float | None

    @property
    def top(self) -> float | None:
        """The upper end of the seeds' 95 % interval (the mean with one seed)."""
        if self.full.std is None:
            return self.full.mean
        return self.full.mean + t_quantile(self.full.n - 1) * self.full.std / math.sqrt(self.full.n)

    @property
    def contrast(self) -> bool:
        """The large set beats every classical method (its interval below the best one's) while
        the small set does not beat IRLS by more than :data:`~wording.SAME`."""
        beats = self.top is not None and self.best is not None and self.top < self.best
        return self.small is not None and beats and (self.small or 0.0) >= SAME


@dataclass
class SizeCurve:
    """MFG's RPE rotation by training-set size (``points``: training pairs and the seeds'
    :class:`~mfg_lightning.study.noise.Spread`, smallest set first) and IRLS's on the same test
    pairs."""

    points: list[tuple[int, Spread]]
    irls: float | None

    @property
    def lowest(self) -> float | None:
        return min((sp.mean for _, sp in self.points if sp.mean is not None), default=None)

    @property
    def ends(self) -> tuple[tuple[int, Spread], tuple[int, Spread]] | None:
        """The smallest and the largest set, where the curve has two measured ends."""
        if len(self.points) < 2 or None in (self.points[0][1].mean, self.points[-1][1].mean):
            return None
        return self.points[0], self.points[-1]

    @property
    def moved(self) -> float | None:
        """The fall from the smallest set to the largest in the smallest set's sds."""
        ends = self.ends
        if ends is None or not ends[0][1].std:
            return None
        return (ends[0][1].mean - ends[1][1].mean) / ends[0][1].std  # type: ignore[operator]

    @property
    def below(self) -> list[int]:
        """The sizes whose MFG mean is below IRLS's."""
        if self.irls is None:
            return []
        return [n for n, sp in self.points if sp.mean is not None and sp.mean < self.irls]


@dataclass
class Robustness:
    """MFG's error growth from the least to the most covered bin (seed means), every classical
    method's, and the essential-matrix methods' (their fall, if any, is stated, not explained)."""

    edges: list[float]
    counts: list[int]
    rot: float | None
    trans: float | None
    others: dict[str, float | None]
    essential: list[float | None]

    @property
    def fall(self) -> bool:
        """Every essential-matrix method's growth is a fall beyond :data:`~wording.SAME`."""
        em = self.essential
        return bool(em) and all(g is not None and g * SAME < 1 for g in em)


@dataclass
class InputScale:
    """The model at another input scale's validation ATE † against the default's seeds (their
    mean ± :func:`~mfg_lightning.study.noise.tolerance`); the config's default beside."""

    scale: float
    default: float
    val: Spread
    other: float | None

    @property
    def tol(self) -> Tolerance | None:
        if self.val.n < 2 or self.other is None or not self.val.mean:
            return None
        return tolerance(self.val)

    @property
    def where(self) -> str:
        """ "below", "inside" or "above" the band (empty where it is not measured)."""
        if self.tol is None:
            return ""
        m, t = self.val.mean, self.tol.value
        return position(self.other, m * (1 - t), m * (1 + t))  # type: ignore[operator,arg-type]


@dataclass
class RuleWeakness:
    """The w_s = 0 model's best validation ATE † when its decay began (``before``) and after it
    (``after``), beside the rule's own least improvement and window (fractions)."""

    convergence: Mapping[str, Any]
    before: float | None
    after: float
    least: float
    window: float | None

    @property
    def gain(self) -> float | None:
        return 1 - self.after / self.before if self.before else None


@dataclass
class LearnedFlow:
    """The one learned-flow model's test scores against the range of the main model's seeds on
    the study's flow (``scores``: label → its value, the lowest and the highest seed's, decimals)
    and the two flows' test EPE at +1 (``epe``: region → the learned flow's, the study flow's)."""

    scores: dict[str, tuple[float, float, float, int]]
    epe: dict[str, tuple[float | None, float | None]]

    def place(self, label: str) -> str:
        """ "below", "inside" or "above" the seeds' range ("" where not measured)."""
        return position(*self.scores[label][:3]) if label in self.scores else ""

    def where(self, stem: str) -> dict[str, list[str]]:
        """The labels starting with ``stem`` by their place against the seeds' range."""
        out: dict[str, list[str]] = {}
        for k in (k for k in self.scores if k.startswith(stem)):
            out.setdefault(self.place(k), []).append(k)
        return {p: out[p] for p in ("below", "inside", "above") if p in out}

    def epe_ratio(self, region: str) -> float | None:
        """The learned flow's EPE over the study flow's on ``region``'s pixels."""
        return ratio(*self.epe.get(region, (None, None)))


def verdict_count(judged: list[Any]) -> dict[str, list[str]]:
    """The sentences' keys by verdict (a partial verdict's note left off), in first-seen order."""
    by: dict[str, list[str]] = {}
    for j in judged:
        by.setdefault(j.verdict.split(" (")[0], []).append(j.sentence.key)
    return by
