"""What a verdict is made of: a judged :class:`Part` (a value, its interval, a bound), a
:class:`Judged` sentence, the 2 × 2's results (:class:`Settled`), every seed's view of the main
setting (:func:`seed_views`) and the paper's printed numbers the bounds are read from. The
sentences themselves are :mod:`mfg_lightning.study.sentences` (S1–S8) and
:mod:`mfg_lightning.study.objects` (S9, S10).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mfg_lightning.core.tables import fmt
from mfg_lightning.study import rules
from mfg_lightning.study.intervals import (
    FLOORS,
    HOLDS,
    INCONCLUSIVE,
    NO_SPREAD,
    NO_VERDICT,
    NOT_HOLD,
    Claim,
    Interval,
    bootstrap_se,
    combine,
    holm,
    interval,
    interval_verdict,
)
from mfg_lightning.study.noise import ratio
from mfg_lightning.study.quotes import Sentence
from mfg_lightning.study.verdicts import NOT_RUN

View = Mapping[str, Any]
SEQS = ("09", "10")
#: Table 1 (†) as printed, ATE 09 / 10 (m), by k: strings, so that their print precision is known.
PRINTED_TABLE1 = {
    1.0: ("0.012", "0.013"),
    0.05: ("0.012", "0.013"),
    0.02: ("0.018", "0.017"),
}
#: Table 2's rotation errors as printed (rad): MFG and Jaegle et al.'s robust continuous method.
PRINTED_TABLE2_ROT = ("0.0011", "0.0014")
#: Table 2's RPE translation as printed (m), all units and k = 20 %: its print precision is the
#: tolerance of "without translation performance drop" (S5).
PRINTED_TABLE2_TRANS = ("0.1769", "0.1788")
#: The name stems of the classical rows S4, S6 and S7 read.
IRLS, PLAIN_LS = "IRLS", "continuous least squares"


@dataclass
class Part:
    """One judged part: its label, our value and its 95 % interval, the bound, the claimed
    direction and the verdict.

    Attributes:
        scale: ``"log"`` when the value is the log of a ratio (printed as ×ratio), else
            ``"linear"``.
        widen: the bound's print precision (relative), added to the interval on each side.
        domain: the values the quantity can take (an interval covering it is inconclusive).
        floor: set when a denominator is below its floor (:data:`FLOORS`): no verdict, and why.
    """

    label: str
    iv: Interval | None
    bound: float
    direction: str
    scale: str = "linear"
    widen: float = 0.0
    domain: tuple[float, float] | None = None
    floor: str = ""
    note: str = ""
    digits: int = 3
    strict: bool = False
    verdict: str = field(init=False)
    #: the level the verdict was judged at (Holm's, within the sentence: :meth:`Judged.close`)
    level: float = field(init=False, default=0.95)

    def __post_init__(self) -> None:
        if self.iv is not None and self.iv.how == NO_SPREAD and not self.floor:
            # one value and nothing that varies: a zero-width interval would decide anything
            self.floor = "one seed and no other spread measured: no interval"
        if self.floor:
            self.verdict = NO_VERDICT
            return
        self.verdict = interval_verdict(
            self.judged, self.bound, self.direction, self.domain, self.strict
        )

    @property
    def judged(self) -> Interval | None:
        """The interval the verdict reads: ours, widened by the bound's print precision."""
        return None if self.iv is None else self.iv.widened(self.widen, self.bound)

    @property
    def value(self) -> float | None:
        """The value judged, on the scale it prints in (a ratio for a log ratio)."""
        if self.iv is None:
            return None
        return math.exp(self.iv.value) if self.scale == "log" else self.iv.value

    def interval_text(self) -> str:
        """``value [lo, hi]`` of the judged interval, on the printed scale ("–": none)."""
        iv = self.judged
        return (
            "–" if iv is None else f"{self.show(iv.value)} [{self.show(iv.lo)}, {self.show(iv.hi)}]"
        )

    def claim(self) -> Claim | None:
        """The part as one claim of its sentence's family (None: no interval, or no verdict)."""
        if self.floor or self.verdict == NO_VERDICT or self.judged is None:
            return None
        return Claim(self.judged, self.bound, self.direction, self.domain, self.strict)

    def show(self, x: float) -> str:
        return f"×{fmt(math.exp(x), self.digits)}" if self.scale == "log" else fmt(x, self.digits)

    @property
    def sign(self) -> str:
        """The claimed side as printed: ≤ / ≥, or < / > where the bound itself fails (strict)."""
        return {"<=": "≤<", ">=": "≥>"}[self.direction][self.strict]

    def text(self) -> str:
        sign, note = self.sign, f"; {self.note}" if self.note else ""
        if self.floor:
            return f"{self.label}: {self.floor}{note} — {self.verdict}"
        if self.iv is None:
            return f"{self.label}: not measured{note} — {self.verdict}"
        return (
            f"{self.label}: {self.interval_text()} {sign} {self.show(self.bound)} "
            f"({self.judged.how}){self.holm_text()}{note} — {self.verdict}"
        )

    def holm_text(self) -> str:
        """``; judged at L % (Holm): [lo, hi]``, where Holm's procedure set a level not 95 %."""
        if self.level == 0.95 or self.judged is None:
            return ""
        iv, pct = self.judged.at(self.level), f"{100 * self.level:.2f}"
        return f"; judged at {pct} % (Holm): [{self.show(iv.lo)}, {self.show(iv.hi)}]"


@dataclass
class Judged:
    """A sentence, its parts and its verdict; ``beside``: what a reader needs next to it."""

    sentence: Sentence
    parts: list[Part] = field(default_factory=list)
    verdict: str = NOT_RUN
    beside: str = ""
    #: the sentence whose parts are this one's to the last digit, and why ("": none)
    same_as: str = ""
    same_why: str = ""

    def close(self) -> Judged:
        """The parts with an interval decided together by Holm's procedure (:func:`holm`),
        then the sentence's verdict from its parts'."""
        family = [(p, c) for p in self.parts if (c := p.claim()) is not None]
        for (p, _), (v, level) in zip(family, holm([c for _, c in family]), strict=True):
            p.verdict, p.level = v, level
        self.verdict = combine([p.verdict for p in self.parts]) if self.parts else NOT_RUN
        if self.verdict == NO_VERDICT:
            self.verdict = NOT_RUN if all(p.iv is None for p in self.parts) else NO_VERDICT
        return self

    def deciding(self) -> Part | None:
        """The one part that decides the verdict (the README's headline): where the sentence
        holds, the binding part (the least decisive, :meth:`~mfg_lightning.study.intervals.
        Claim.decisiveness`); where it does not hold, the most decisive failing part; otherwise
        the part Holm's procedure stopped at (the most decisive inconclusive one)."""
        want = self.verdict if self.verdict in (HOLDS, NOT_HOLD) else INCONCLUSIVE
        rank = [(c.decisiveness() if (c := p.claim()) else -math.inf, p)
                for p in self.parts if p.verdict == want]  # fmt: skip
        pick = min if want == HOLDS else max  # the first of equals
        return pick(rank, key=lambda r: r[0], default=(0, None))[1]


@dataclass
class Settled:
    """The 2 × 2's stage results (:mod:`mfg_lightning.study.settle`): per flow, every seed's
    model and the classical methods' ``settle_classical/<flow>``; the strided seeds'
    ``settle/strided_seed<n>``; per variant, the models trained under the rotation rule
    (``converge/<variant>_seed<n>``). ``seeds`` (what the verdicts read) holds the converged
    models once every flow has all of ``converge.seeds`` (the exact ones' objects then those of
    the object test set, ``objects/seed<n>``, once it has run at every seed), else the equal
    budget's (``settle/<flow>_seed<n>``, also in ``budget``); ``reads`` names which."""

    seeds: dict[str, dict[int, dict]] = field(default_factory=dict)
    classical: dict[str, dict] = field(default_factory=dict)
    strided: dict[int, dict] = field(default_factory=dict)
    budget: dict[str, dict[int, dict]] = field(default_factory=dict)
    converged: dict[str, dict[int, dict]] = field(default_factory=dict)
    reads: str = "settle"

    @classmethod
    def load(cls, cached: Callable[[str], dict | None], cfg: Any) -> Settled:
        out = cls()

        def runs(stem: str, seeds: Any) -> dict[int, dict]:
            got = {int(s): cached(f"{stem}_seed{int(s)}") for s in seeds}
            return {s: r for s, r in got.items() if r is not None}

        conv = cfg.get("converge") or {"variants": [], "seeds": []}
        variants = [v for group in conv["variants"] for v in group]
        out.converged = {str(v): runs(f"converge/{v}", conv["seeds"]) for v in variants}
        flows = [str(f) for f in cfg.settle.flows]
        full = all(len(out.converged.get(f, {})) == len(conv["seeds"]) > 0 for f in flows)
        out.reads = "converge" if full else "settle"
        for flow in flows:
            out.budget[flow] = runs(f"settle/{flow}", cfg.settle.seeds)
            out.seeds[flow] = dict(out.converged[flow] if full else out.budget[flow])
            if (c := cached(f"settle_classical/{flow}")) is not None:
                out.classical[flow] = c
        out.strided = runs("settle/strided", cfg.settle.strided.seeds)
        # S9 and S10 read the converged exact-flow models on the object test set
        # (objects/seed<n>) once every seed has been evaluated on it: one test set for all
        objects = {s: cached(f"objects/seed{s}") for s in out.seeds.get("exact", {})}
        if full and objects and None not in objects.values():
            for s, o in objects.items():
                r = out.seeds["exact"][s]
                out.seeds["exact"][s] = {**r, "objects": o["objects"], "object_set": o}
        return out

    def flows(self) -> list[str]:
        """The flows with at least one seed and the classical methods."""
        return [f for f, by in self.seeds.items() if by and f in self.classical]

    def mfg_rot(self, flow: str, k: str) -> list[np.ndarray]:
        """MFG's per-pair rotation errors at top-k ``k`` on ``flow``, one array per seed."""
        return [np.asarray(r["mfg"][k]["rot_err"]) for _, r in sorted(self.seeds[flow].items())
                if k in r["mfg"]]  # fmt: skip

    def classical_rot(self, flow: str) -> dict[str, np.ndarray]:
        """Every classical method's per-pair rotation errors on ``flow`` (the oracle left out)."""
        rows = self.classical[flow]["classical"]
        return {r["name"]: np.asarray(r["rot_err"]) for r in rows if "oracle" not in r["name"]}


def seed_views(cached: Callable[[str], dict | None], main_seed: int, seeds: list[int]) -> dict:
    """Every seed's results of the main setting: ``{seed: {"trained", "table1", "methods",
    "basis", "object_motion"}}`` (a value None where not run); seed ``main_seed`` from the
    ``main`` stages, the others from ``seeds/seed<n>``."""
    views = {}
    if (main := cached("main")) is not None:
        views[main_seed] = {
            "trained": main,
            **{k: cached(k) for k in ("table1", "methods", "basis", "object_motion")},
        }
    for s in seeds:
        if (r := cached(f"seeds/seed{s}")) is not None:
            views[int(s)] = {"trained": r, **{k: r.get(k) for k in
                             ("table1", "methods", "basis", "object_motion")}}  # fmt: skip
    return views


def test_at(v: View, k: float, key: str) -> float | None:
    """The main model's central-test metric ``key`` at top-k ``k`` (``1``: all units)."""
    return v["table1"]["test"][f"{k:g}"].get(key)


def ratio_at(v: View, k: float, key: str) -> float | None:
    """``key`` at ``k`` over ``key`` with all units, on the central test."""
    return ratio(test_at(v, k, key), test_at(v, 1.0, key))


def mfg_bins(v: View) -> Mapping[str, Any]:
    bins = v["methods"]["bins"]
    return bins[next(n for n in bins if n.startswith("MFG (all"))]


def growth(v: View, key: str) -> float | None:
    """MFG's mean error (``rot_bins`` / ``trans_bins``) in the most covered non-empty bin of
    moving-object coverage over that in the least covered one (:func:`~mfg_lightning.study.
    rules.growth`)."""
    return rules.growth(mfg_bins(v)[key])


#: Seeds a part of the 2 × 2 needs: with one, its seed spread is not measured and its interval
#: would be the test pairs' alone.
MIN_SEEDS = 2


def few_seeds(n: int) -> str:
    return f"{n} seed{'s' * (n != 1)}: the seed spread is not measured yet (at least {MIN_SEEDS})"


def floor_text(den: float, kind: str, unit: str) -> str:
    return (
        f"the denominator {fmt(den, 3)} {unit} is below its floor ({FLOORS[kind]:g} {unit}), "
        "so the ratio is not a verdict"
    )


def log_ratio_part(
    label: str, ours: list[np.ndarray], ref: np.ndarray, note: str = "", seed: int = 0
) -> Part:
    """``log(mean(ours) / mean(ref))`` ≤ 0, per seed (``ours``: every seed's per-pair rotation
    errors; ``ref``: the reference method's on the same pairs), its interval t over the seeds
    plus the paired bootstrap over the pairs. A reference below the rotation floor is no
    verdict."""
    den = float(ref.mean())
    if len(ours) < MIN_SEEDS:
        return Part(label, None, 0.0, "<=", scale="log", floor=few_seeds(len(ours)))
    if den < FLOORS["rotation"]:
        return Part(label, None, 0.0, "<=", scale="log", floor=floor_text(den, "rotation", "rad"))
    vals, ses = [], []
    for m in ours:
        if len(m) != len(ref):
            raise ValueError(f"{label}: {len(m)} pairs against the reference's {len(ref)}")
        vals.append(math.log(float(m.mean()) / den))
        ses.append(
            bootstrap_se(lambda i, m=m: np.log(m[i].mean(1) / ref[i].mean(1)), len(m), seed=seed)
        )
    return Part(label, interval(vals, ses), 0.0, "<=", scale="log", note=note, strict=True)
