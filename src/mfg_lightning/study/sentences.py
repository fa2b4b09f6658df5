"""The paper's sentences and their verdicts: one verdict per quoted sentence.

Each :class:`Sentence` quotes the paper (section, words) and states how it is measured: a
quantity, the bound the sentence implies and the direction in which the sentence claims it (a
sentence that says "without any drop" claims ``ATE(k) / ATE(100 %) ≤ 1``). A sentence is judged
in parts (per test sequence, per decoder, per flow…); each part is a value with a 95 % interval
(over seeds, over test pairs by the paired bootstrap, or both) that holds, does not hold or is
inconclusive against its bound (:mod:`mfg_lightning.study.intervals` states the construction).

What the paper's tables show beyond its sentences (Table 1's ratios at every k, ATE * / ATE †,
Table 2's ratios, the recipes, the w_s sweep) is printed beside as diagnostics
(:mod:`mfg_lightning.study.claims`), never turned into verdicts.

Where the values come from:

* S1–S3, S7, S8: the main model at every seed (:func:`seed_views`: seed 0 is stage ``main``
  with ``table1``, ``methods``, ``basis`` and ``object_motion``; seed n is ``seeds/seed<n>``);
* S4–S6, S9, S10: Table 2's setting at every seed on each flow (:class:`Settled`, the stages
  ``settle/*`` and ``settle_classical/*`` of :mod:`mfg_lightning.study.settle`), with per-pair
  values that the paired bootstrap resamples.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mfg_lightning.core.tables import fmt
from mfg_lightning.study.intervals import (
    FLOORS,
    INCONCLUSIVE,
    NO_SPREAD,
    NO_VERDICT,
    Claim,
    Interval,
    bootstrap_se,
    combine,
    difference,
    holm,
    interval,
    interval_verdict,
    median_interval,
)
from mfg_lightning.study.noise import print_precision, ratio, spread_of
from mfg_lightning.study.quotes import SENTENCES, Sentence
from mfg_lightning.study.verdicts import NOT_RUN

__all__ = ["SENTENCES", "Judged", "Part", "Sentence", "Settled", "judge_all", "seed_views"]

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

    def text(self) -> str:
        sign = self.direction.replace("<=", "≤").replace(">=", "≥")
        note = f"; {self.note}" if self.note else ""
        if self.floor:
            return f"{self.label}: {self.floor}{note} — {self.verdict}"
        if self.iv is None:
            return f"{self.label}: not measured{note} — {self.verdict}"
        holm = ""
        if self.level != 0.95:
            iv = self.judged.at(self.level)
            holm = (
                f"; judged at {100 * self.level:.2f} % (Holm): [{self.show(iv.lo)}, "
                f"{self.show(iv.hi)}]"
            )
        return (
            f"{self.label}: {self.interval_text()} {sign} {self.show(self.bound)} "
            f"({self.judged.how}){holm}{note} — {self.verdict}"
        )


@dataclass
class Judged:
    """A sentence, its parts and its verdict; ``beside``: what a reader needs next to it."""

    sentence: Sentence
    parts: list[Part] = field(default_factory=list)
    verdict: str = NOT_RUN
    beside: str = ""

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


@dataclass
class Settled:
    """The 2 × 2's stage results (:mod:`mfg_lightning.study.settle`): per flow, every seed's
    ``settle/<flow>_seed<n>`` and the classical methods' ``settle_classical/<flow>``; the
    strided seeds' ``settle/strided_seed<n>``."""

    seeds: dict[str, dict[int, dict]] = field(default_factory=dict)
    classical: dict[str, dict] = field(default_factory=dict)
    strided: dict[int, dict] = field(default_factory=dict)

    @classmethod
    def load(cls, cached: Callable[[str], dict | None], cfg: Any) -> Settled:
        out = cls()
        for flow in cfg.settle.flows:
            got = {int(s): cached(f"settle/{flow}_seed{int(s)}") for s in cfg.settle.seeds}
            out.seeds[str(flow)] = {s: r for s, r in got.items() if r is not None}
            if (c := cached(f"settle_classical/{flow}")) is not None:
                out.classical[str(flow)] = c
        for s in cfg.settle.strided.seeds:
            if (r := cached(f"settle/strided_seed{int(s)}")) is not None:
                out.strided[int(s)] = r
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


# --------------------------------------------------------------------------------------------
# The seeds' views and the measurements on one view
# --------------------------------------------------------------------------------------------


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


def _mfg_bins(v: View) -> Mapping[str, Any]:
    bins = v["methods"]["bins"]
    return bins[next(n for n in bins if n.startswith("MFG (all"))]


def _growth_of(bins: list) -> tuple[float, float] | None:
    """The mean errors of the most and of the least covered non-empty bins."""
    filled = [b for b in bins if b["n"] and b["mean"] is not None]
    return (filled[-1]["mean"], filled[0]["mean"]) if len(filled) >= 2 else None


def growth(v: View, key: str) -> float | None:
    """MFG's mean error (``rot_bins`` / ``trans_bins``) in the most covered non-empty bin of
    moving-object coverage over that in the least covered one."""
    ends = _growth_of(_mfg_bins(v)[key])
    return ends[0] / ends[1] if ends else None


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


# --------------------------------------------------------------------------------------------
# The sentences
# --------------------------------------------------------------------------------------------


def judge_all(
    views: Mapping[int, View],
    settled: Settled | None,
    basis_residual: float,
    one_motion: float,
    ate_tolerance: float,
) -> list[Judged]:
    """Every sentence's verdict, in :data:`SENTENCES`' order (not run where its stage is not):
    S1–S3, S7 and S8 on the main model's seeds (``views``), S4–S6, S9 and S10 on the 2 × 2
    (``settled``)."""
    settled = settled or Settled()
    main = {s: v for s, v in views.items() if v.get("table1")}
    out = [
        _s1(main),
        _s2(main),
        _s3(main, ate_tolerance),
        _s4(settled),
        _s5(settled, main),
        _s6(settled),
        _s7({s: v for s, v in views.items() if v.get("methods")}),
        _s8({s: v for s, v in views.items() if v.get("basis")}, basis_residual, one_motion),
        *_object_sentences(settled),
    ]
    return [j.close() for j in out]


def _over_seeds(
    views: Mapping[int, View], label: str, measure: Callable[[View], float | None],
    bound: float, direction: str, **kw: Any,
) -> Part:  # fmt: skip
    """A part whose value is ``measure`` of every seed's view, its interval t over the seeds."""
    return Part(label, interval(spread_of(views, measure).values), bound, direction, **kw)


def _s1(views: Mapping[int, View]) -> Judged:
    j = Judged(SENTENCES["S1"])
    if not views:
        return j
    margins = []
    for i, s in enumerate(SEQS):
        p = print_precision(PRINTED_TABLE1[0.05][i], PRINTED_TABLE1[1.0][i])
        margins.append(p)
        j.parts.append(
            _over_seeds(views, f"ATE † {s}", lambda v, s=s: ratio_at(v, 0.05, f"{s}/ate"),
                        1 + p, "<=")
        )  # fmt: skip
    margin = min(margins)
    for key, label in (("rpe_trans", "RPE translation"), ("rpe_rot", "RPE rotation")):
        j.parts.append(
            _over_seeds(views, label, lambda v, key=key: ratio_at(v, 0.05, key), 1 + margin, "<=")
        )
    j.beside = (
        "'Without any drop' is read at the paper's resolution: Table 1 prints 0.012 / 0.012 on "
        f"09 and 0.013 / 0.013 on 10, which cannot show a drop below {100 * margins[0]:.1f} % "
        f"and {100 * margins[1]:.1f} %; the bound is 1 plus that (the RPE parts, which Table 1 "
        "does not print, take the smaller)."
    )
    return j


def _s2(views: Mapping[int, View]) -> Judged:
    j = Judged(SENTENCES["S2"])
    if not views:
        return j
    for i, s in enumerate(SEQS):
        a, b = PRINTED_TABLE1[0.02][i], PRINTED_TABLE1[1.0][i]
        j.parts.append(
            _over_seeds(views, f"ATE † {s}", lambda v, s=s: ratio_at(v, 0.02, f"{s}/ate"),
                        float(a) / float(b), "<=", widen=print_precision(a, b))
        )  # fmt: skip
    return j


def _s3(views: Mapping[int, View], ate_tolerance: float) -> Judged:
    from mfg_lightning.study.stages import smallest_k

    j = Judged(SENTENCES["S3"])
    if not views:
        return j
    # the study's own rule (sparsity.ate_tolerance), as the main model's k is chosen: a
    # tolerance widened by the seeds' spread would let noisier seeds choose smaller k
    within = ate_tolerance
    ks = [k for _, v in sorted(views.items()) if (k := smallest_k(v["table1"]["val"], within))]
    grid = sorted({float(k) for v in views.values() for k in v["table1"]["val"]})
    # k is a grid value: the sign test's interval stays on it (a t interval went below 0 %)
    domain = (grid[0], grid[-1])
    j.parts.append(
        Part("smallest k on validation", median_interval(ks, domain), 0.05, "<=", domain=domain,
             note=f"per seed {', '.join(f'{100 * k:g} %' for k in ks)}; 'within' is "
             f"{100 * within:.1f} % of all units' validation ATE † (sparsity.ate_tolerance, "
             "the rule that chooses the main model's k)")
    )  # fmt: skip
    return j


#: Seeds a part of the 2 × 2 needs: with one, its seed spread is not measured and its interval
#: would be the test pairs' alone.
MIN_SEEDS = 2


def _few_seeds(n: int) -> str:
    return f"{n} seed{'s' * (n != 1)}: the seed spread is not measured yet (at least {MIN_SEEDS})"


def _floor_text(den: float, kind: str, unit: str) -> str:
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
        return Part(label, None, 0.0, "<=", scale="log", floor=_few_seeds(len(ours)))
    if den < FLOORS["rotation"]:
        return Part(label, None, 0.0, "<=", scale="log", floor=_floor_text(den, "rotation", "rad"))
    vals, ses = [], []
    for m in ours:
        if len(m) != len(ref):
            raise ValueError(f"{label}: {len(m)} pairs against the reference's {len(ref)}")
        vals.append(math.log(float(m.mean()) / den))
        ses.append(
            bootstrap_se(lambda i, m=m: np.log(m[i].mean(1) / ref[i].mean(1)), len(m), seed=seed)
        )
    return Part(label, interval(vals, ses), 0.0, "<=", scale="log", note=note, strict=True)


def _best_classical(rot: Mapping[str, np.ndarray]) -> str | None:
    return min(rot, key=lambda n: float(rot[n].mean()), default=None)


def _table2_beside(settled: Settled) -> str:
    n = {f: len(settled.seeds[f]) for f in settled.flows()}
    pairs = sorted(
        {int(r.get("train_pairs", 0)) for by in settled.seeds.values() for r in by.values()}
    )
    return (
        f"Table 2's setting ({', '.join(f'{p:,}' for p in pairs)} training pairs) at "
        + ", ".join(f"{n[f]} seeds on {_FLOW_NAME[f]}" for f in n)
        + ", each trained for the same budget; the classical methods on the same flow and pairs. "
        "The exact flow is the paper's protocol (its Table 2 used Virtual KITTI's ground-truth "
        "flow); DIS is the estimated flow the main model reads."
    )


_FLOW_NAME = {"exact": "exact flow", "dis": "DIS flow"}


def _s4(settled: Settled) -> Judged:
    j = Judged(SENTENCES["S4"])
    for flow in settled.flows():
        rot = settled.classical_rot(flow)
        ours = settled.mfg_rot(flow, "1")
        irls = next((n for n in rot if IRLS in n), None)
        best = _best_classical(rot)
        for name in dict.fromkeys(x for x in (irls, best) if x):
            what = "IRLS" if name == irls else "the best"
            j.parts.append(log_ratio_part(f"{_FLOW_NAME[flow]}, MFG over {what} ({name})", ours,
                                          rot[name]))  # fmt: skip
    if j.parts:
        j.beside = _table2_beside(settled)
    return j


def _k_changes_nothing(settled: Settled, flow: str, k: str) -> bool:
    """Whether MFG at ``k`` has all units' errors on every pair of every seed of ``flow``."""
    at_k, full = settled.mfg_rot(flow, k), settled.mfg_rot(flow, "1")
    return bool(at_k) and all(np.array_equal(a, b) for a, b in zip(at_k, full, strict=True))


def _s6(settled: Settled) -> Judged:
    j = Judged(SENTENCES["S6"])
    for flow in settled.flows():
        rot = settled.classical_rot(flow)
        best = _best_classical(rot)
        ours = settled.mfg_rot(flow, "0.15")
        if best and ours:
            j.parts.append(
                log_ratio_part(f"{_FLOW_NAME[flow]}, MFG at k = 15 % over the best ({best})",
                               ours, rot[best])
            )  # fmt: skip
    if j.parts:
        j.beside = _table2_beside(settled)
        same = [f for f in settled.flows() if _k_changes_nothing(settled, f, "0.15")]
        if same:
            j.beside += (
                f" On {', '.join(same)} flow k = 15 % keeps every unit that fires (its errors "
                "are all units' to the last digit), so S6 measures what S4 measures there."
            )
    return j


def _s5(settled: Settled, main: Mapping[int, View]) -> Judged:
    """The smallest k of each model within its paper table's print precision of its own
    all-units score, compared in log: the Table-2-sized model's (exact flow, every seed) minus
    the main model's (every seed), ≥ half a step of the k grid."""
    j = Judged(SENTENCES["S5"])
    seeds = settled.seeds.get("exact") or {}
    if not seeds or not main:
        return j
    tol2 = print_precision(*PRINTED_TABLE2_TRANS)
    tol1 = print_precision(PRINTED_TABLE1[0.05][0], PRINTED_TABLE1[1.0][0])

    def small_ks(tol: float) -> list[float]:
        ks = []
        for _, r in sorted(seeds.items()):
            full = r["mfg"]["1"]["metrics"].get("rpe_trans")
            rs = {float(k): ratio(m["metrics"].get("rpe_trans"), full) for k, m in r["mfg"].items()}
            ks.append(smallest_k_by_ratio(rs, tol))
        return [k for k in ks if k is not None]

    small, symmetric = small_ks(tol2), small_ks(tol1)
    kitti = []
    for _, v in sorted(main.items()):
        ks = sorted({float(k) for k in v["table1"]["test"]}, reverse=True)
        worst = {k: max((ratio_at(v, k, f"{s}/ate") or math.inf) for s in SEQS) for k in ks}
        if (k := smallest_k_by_ratio(worst, tol1)) is not None:
            kitti.append(k)
    if not small or not kitti:
        return j
    if len(small) < MIN_SEEDS:
        j.parts.append(Part("smallest k, Table-2-sized set over the main model's", None, 0.0,
                            ">=", scale="log", floor=_few_seeds(len(small))))  # fmt: skip
        return j
    grid = sorted({float(k) for r in seeds.values() for k in r["mfg"]})
    step = min((math.log(hi / lo) for lo, hi in itertools.pairwise(grid)), default=0.0)
    iv, sym = (difference([math.log(k) for k in ks], [math.log(k) for k in kitti])
               for ks in (small, symmetric))  # fmt: skip
    # one tolerance on both sides, beside: the verdict is the rule stated before the 2 × 2 ran
    sym = Part("", sym, step / 2, ">=", scale="log")
    j.parts.append(
        Part("smallest k, Table-2-sized set over the main model's", iv, step / 2, ">=",
             scale="log", note=f"per seed {', '.join(f'{100 * k:g} %' for k in small)} against "
             f"{', '.join(f'{100 * k:g} %' for k in kitti)}, each within its table's print "
             f"precision of all units' (Table 2's RPE translation ±{100 * tol2:.2f} %, Table "
             f"1's ATE ±{100 * tol1:.1f} %); the bound is half the k grid's smallest step; read "
             f"with Table 1's ±{100 * tol1:.1f} % on both sides (beside, not the verdict) the "
             f"small set's k are {', '.join(f'{100 * k:g} %' for k in symmetric)} and the ratio "
             f"{sym.interval_text()}: {sym.verdict} on that reading")
    )  # fmt: skip
    j.beside = (
        "Its k on exact flow (the paper's protocol) against the DIS-trained main model's, as the "
        "paper set its ground-truth-flow model's against its KITTI (PWC-Net flow) model's."
    )
    return j


def _classical_growth(views: Mapping[int, View], stem: str, key: str) -> tuple[str, list] | None:
    """A classical method's bins (``rot_bins`` / ``trans_bins``) from the view that has them."""
    for _, v in sorted(views.items()):
        for name, b in v["methods"]["bins"].items():
            if stem in name and "MFG" not in name:
                return name, b[key]
    return None


def _s7(views: Mapping[int, View]) -> Judged:
    """The reading stated before any number was seen is the verdict: MFG's own error growth
    from the least to the most covered bin of moving-object coverage ≤ 1, rotation and
    translation (log, t over the seeds). The comparative reading (its growth over the
    continuous least-squares methods') is printed beside, not judged: it was proposed after the
    growths were seen (changes.json)."""
    j = Judged(SENTENCES["S7"])
    if not views:
        return j
    beside = []
    for key, kind, unit in (("rot_bins", "rotation", "rad"), ("trans_bins", "translation", "m")):
        least = spread_of(views, lambda v, key=key: _growth_of(_mfg_bins(v)[key])[1])
        part_label = f"{kind} error, most / least covered"
        if least.mean is not None and least.mean < FLOORS[kind]:
            j.parts.append(Part(part_label, None, 0.0, "<=", scale="log",
                                floor=_floor_text(least.mean, kind, unit)))  # fmt: skip
            continue
        g = spread_of(views, lambda v, key=key: growth(v, key))
        logs = [math.log(x) for x in g.values if x > 0]
        j.parts.append(Part(part_label, interval(logs), 0.0, "<=", scale="log"))
        for stem in (PLAIN_LS, IRLS):
            found = _classical_growth(views, stem, key)
            ends = _growth_of(found[1]) if found else None
            if ends is None or ends[1] < FLOORS[kind]:
                continue
            theirs = math.log(ends[0] / ends[1])
            iv = interval([x - theirs for x in logs])
            if iv is not None:
                beside.append(
                    f"{kind}, MFG's growth over {found[0]}'s (×{fmt(math.exp(theirs), 2)}): "
                    f"×{fmt(math.exp(iv.value), 2)} [×{fmt(math.exp(iv.lo), 2)}, "
                    f"×{fmt(math.exp(iv.hi), 2)}]"
                )
    j.beside = (
        "The verdict is the reading stated before the numbers were seen: robust means MFG's "
        "errors do not grow as moving objects cover more of the image. The comparative "
        "reading ('an advantage' over methods without a sparse representation), proposed after "
        "the growths were seen and therefore not the verdict, 95 % interval over MFG's seeds "
        "with the classical growth taken as measured: " + ("; ".join(beside) or "–") + ". The "
        "essential-matrix methods' growths are in diagnostic 4."
    )
    return j


def one_motion_fraction(v: View, decoder: str, residual: float, firing: bool) -> float | None:
    """Of a decoder's top units (``firing``: those that fire on validation), the fraction
    whose field one motion fits (relative residual ≤ ``residual``)."""
    d = v["basis"]["per_decoder"][decoder]
    res = [r for r, f in zip(d["residual"], d["firing_rate"], strict=True) if f > 0 or not firing]
    return sum(r <= residual for r in res) / len(res) if res else None


def _s8(views: Mapping[int, View], residual: float, one_motion: float) -> Judged:
    j = Judged(SENTENCES["S8"])
    if not views:
        return j
    for dec, label in (("t", "translational units"), ("omega", "rotational units")):
        fired = spread_of(views, lambda v, dec=dec: v["basis"]["summary"][dec]["fired"])
        firing = Part(
            "firing", interval(spread_of(
                views, lambda v, dec=dec: one_motion_fraction(v, dec, residual, True)).values),
            one_motion, ">=", domain=(0.0, 1.0),
        )  # fmt: skip
        j.parts.append(
            _over_seeds(views, f"{label}, all top units",
                        lambda v, dec=dec: one_motion_fraction(v, dec, residual, False),
                        one_motion, ">=", domain=(0.0, 1.0),
                        note=f"of the top units {fired.text(2)} fire; of those one motion fits "
                        f"{firing.interval_text()} ({firing.verdict} against the same bound; "
                        "not the verdict)")
        )  # fmt: skip
    j.beside = (
        "The verdict reads every top unit (by column norm), the reading stated before any "
        "number was seen; the units that fire on validation are shown beside, not judged "
        "(changes.json). The scale of a unit's motion (the supplement's |t| ~0.01, |ω| "
        "~0.03–0.15, |ω| / |t| ≈ 5) is not judged: the supplement's Euler-coordinate axes "
        "state no unit."
    )
    return j


def _counts(pairs: Mapping[str, list]) -> tuple[np.ndarray, ...]:
    return tuple(np.asarray(pairs[k], dtype=float) for k in ("tp", "fp", "fn"))


def _pooled(counts: tuple[np.ndarray, ...], key: str, idx: np.ndarray | None = None) -> Any:
    """IoU or precision pooled over the pairs (``idx``: ``(draws, n)`` resamples, one value
    each; None: all pairs once) from per-pair pixel counts; NaN where nothing was counted."""
    tp, fp, fn = counts if idx is None else (c[idx] for c in counts)
    axis = -1
    den = tp.sum(axis) + fp.sum(axis) + (fn.sum(axis) if key == "iou" else 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, tp.sum(axis) / den, np.nan)


def _mask_part(seeds: Mapping[int, dict], key: str, label: str) -> Part:
    if len(seeds) < MIN_SEEDS:
        return Part(label, None, 0.0, ">=", floor=_few_seeds(len(seeds)))
    vals, ses = [], []
    for s, r in sorted(seeds.items()):
        f = _counts(r["objects"]["pairs"]["filters"])
        t = _counts(r["objects"]["pairs"]["threshold"])
        d = float(_pooled(f, key) - _pooled(t, key))
        if not math.isfinite(d):
            continue
        vals.append(d)
        ses.append(
            bootstrap_se(lambda i, f=f, t=t: _pooled(f, key, i) - _pooled(t, key, i), len(f[0]),
                         seed=s)
        )  # fmt: skip
    return Part(label, interval(vals, ses), 0.0, ">=", domain=(-1.0, 1.0), strict=True)


def velocity_bins(r: dict) -> list[dict[str, Any]]:
    """S10's bins of one seed: per object size × speed bin, the test pairs with objects in it,
    the pixels, and the filters' and the threshold's pooled velocity error (px/frame)."""
    o = r["objects"]
    sizes, speeds = o["size_bins"], o["speed_bins"]
    f, t = o["pairs"]["filters"], o["pairs"]["threshold"]
    pix = np.asarray(f["pixels"], dtype=float)
    ef, et = np.asarray(f["err"], dtype=float), np.asarray(t["err"], dtype=float)
    out = []
    for b in range(pix.shape[1]):
        i, k = divmod(b, len(speeds) - 1)
        n = pix[:, b].sum()
        out.append({
            "size": (sizes[i], sizes[i + 1]), "speed": (speeds[k], speeds[k + 1]),
            "pairs": int((pix[:, b] > 0).sum()), "pixels": int(n),
            "filters": float(ef[:, b].sum() / n) if n else None,
            "threshold": float(et[:, b].sum() / n) if n else None,
            "column": b,
        })  # fmt: skip
    return out


def _velocity_parts(seeds: Mapping[int, dict], b: dict) -> list[Part]:
    """S10's parts in one object size × speed bin: the filters' velocity error minus the error
    of reporting no motion (the objects' own speed: the absolute reading, "faithful" at the
    least), and minus the plain threshold's (px/frame, t over the seeds plus the paired
    bootstrap). A bin whose objects are in fewer than ``FLOORS["pairs"]`` test pairs is
    inconclusive: a wide range of sizes and speeds is not shown where it was not measured."""
    col = b["column"]
    size = f"size {100 * b['size'][0]:g}–{100 * b['size'][1]:g} % of the image"
    speed = f"speed {b['speed'][0]:g}–{b['speed'][1]:g} px" if b["speed"][1] < 999 else (
        f"speed ≥ {b['speed'][0]:g} px")  # fmt: skip
    where = f"{size}, {speed}"
    if b["pairs"] < FLOORS["pairs"]:
        missing = Part(f"velocity error, {where}", None, 0.0, "<=",
                       floor=f"objects in {b['pairs']} test pairs, below the floor of "
                       f"{FLOORS['pairs']:g}: not measured")  # fmt: skip
        missing.verdict = INCONCLUSIVE
        return [missing]
    columns = {}
    for s, r in sorted(seeds.items()):
        p = r["objects"]["pairs"]
        columns[s] = {
            "pix": np.asarray(p["filters"]["pixels"], dtype=float)[:, col],
            "filters": np.asarray(p["filters"]["err"], dtype=float)[:, col],
            "threshold": np.asarray(p["threshold"]["err"], dtype=float)[:, col],
        }
        if "speed" in p:
            columns[s]["no motion"] = np.asarray(p["speed"], dtype=float)[:, col]
    parts = []
    for other in ("no motion", "threshold"):
        if not all(other in c for c in columns.values()):
            continue
        vals, ses = [], []
        for s, c in columns.items():
            vals.append(float((c["filters"].sum() - c[other].sum()) / c["pix"].sum()))

            def diff(i: np.ndarray, c: dict = c, other: str = other) -> np.ndarray:
                return (c["filters"][i].sum(1) - c[other][i].sum(1)) / c["pix"][i].sum(1)

            ses.append(bootstrap_se(diff, len(c["pix"]), seed=s))
        means = {k: float(np.mean([c[k].sum() / c["pix"].sum() for c in columns.values()]))
                 for k in ("filters", other)}  # fmt: skip
        note = (
            f"filters {fmt(means['filters'], 3)} px, {other} {fmt(means[other], 3)} px (seed "
            f"means); {b['pixels']} object pixels in {b['pairs']} pairs"
        )
        parts.append(Part(f"velocity error, filters − {other} (px), {where}",
                          interval(vals, ses), 0.0, "<=", note=note, strict=True))  # fmt: skip
    return parts


def _grid_edges(seeds: Mapping[int, dict]) -> str:
    """A warning for the seeds whose filter constants were chosen at the edge of their grid (a
    larger value might have done better on validation), or nothing."""
    edge = []
    for s, r in sorted(seeds.items()):
        fc = r["objects"].get("filters_choice") or {}
        grid = [tuple(float(x) for x in k.split(",")) for k in fc.get("iou", {})]
        for i, name in enumerate(("theta_d", "theta_p")):
            values = [g[i] for g in grid]
            if values and float(fc[name]) in (min(values), max(values)):
                edge.append(f"seed {s} {name} {fc[name]:g}")
    if not edge:
        return ""
    return (
        f" At the edge of the filters' grid: {', '.join(edge)}; a wider grid might favour the "
        "filters."
    )


def _object_sentences(settled: Settled) -> list[Judged]:
    """S9 and S10 on the exact-flow Table-2-sized models' object masks and velocities (every
    seed, per-pair counts: t over the seeds plus the paired bootstrap)."""
    j9, j10 = Judged(SENTENCES["S9"]), Judged(SENTENCES["S10"])
    seeds = {s: r for s, r in (settled.seeds.get("exact") or {}).items() if r.get("objects")}
    if not seeds:
        return [j9, j10]
    j9.parts += [_mask_part(seeds, "iou", "mask IoU, filters − threshold"),
                 _mask_part(seeds, "precision", "precision, filters − threshold")]  # fmt: skip
    if len(seeds) < MIN_SEEDS:
        label = "velocity error, filters − threshold (px), every size × speed bin"
        j10.parts.append(Part(label, None, 0.0, "<=", floor=_few_seeds(len(seeds))))
    else:
        j10.parts += [
            p for b in velocity_bins(seeds[min(seeds)]) for p in _velocity_parts(seeds, b)
        ]
    beside = (
        f"The exact-flow Table-2-sized models ({len(seeds)} seeds), the threshold and the "
        "filters' constants chosen on validation for each; the exact-flow twin's masks (one "
        "model) are diagnostic 6." + _grid_edges(seeds)
    )
    j9.beside = beside
    j10.beside = beside + (
        " An object is an 8-connected component of the true mask, binned by its area and mean "
        "true speed; a pixel's velocity error is |extracted − true object flow|, a missed "
        "object costing its whole speed. Both methods extract the same residual flow and differ "
        "in the pixels they keep, so their difference prices the masks' misses and false "
        "pixels in velocity units; the absolute reading's bound is the error of reporting no "
        "motion (the objects' own speed). A bin not measured is inconclusive."
    )
    return [j9, j10]
