"""The 2 × 2 of the Table-2 sentences in the report (stages ``settle/*``,
:mod:`mfg_lightning.study.settle`): flow (exact, DIS) × method (MFG at every seed, the classical
methods) on the same test pairs, the mixed reading (MFG on exact flow against IRLS on DIS) as a
diagnostic, every method's mean, median and failure rate, and contiguous against strided
training pairs at a matched size. Tables, a figure and a paragraph; the verdicts themselves are
:mod:`mfg_lightning.study.sentences`' (whose interval code this reuses)."""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from typing import Any

import numpy as np

from mfg_lightning.core.tables import fmt
from mfg_lightning.study.intervals import BLOCK_PAIRS, Interval, bootstrap_se, difference, interval
from mfg_lightning.study.render import lines, paragraph, table
from mfg_lightning.study.sentences import (
    IRLS,
    MIN_SEEDS,
    PRINTED_TABLE2_ROT,
    Part,
    Settled,
    log_ratio_part,
)

__all__ = [
    "BLOCKS",
    "FAILURE_RAD",
    "block_errors",
    "contiguous_against_strided",
    "converge_section",
    "para_settle",
    "settle_section",
]

#: A rotation error above this is a failure: ten times the largest rotation between two frames
#: of the test pairs (~0.01 rad/frame on the KITTI trajectories), far beyond any method's
#: typical error: only a wrong solution gets there.
FAILURE_RAD = 0.1
_FLOW = {"exact": "exact flow (the paper's)", "dis": "DIS"}


#: Block lengths (test pairs) whose bootstrap standard errors the report prints beside the
#: verdicts' own (:data:`mfg_lightning.study.intervals.BLOCK_PAIRS`).
BLOCKS = (1, 5, 10, 20, 40, 80)


def block_errors(settled: Settled, blocks: tuple[int, ...] = BLOCKS) -> dict[str, list[float]]:
    """Per flow, the moving-block bootstrap's standard error of log(MFG / IRLS) (all units, the
    seeds' root mean square, as an interval combines them) at each block length: the evidence
    on which the verdicts' block length was chosen, from the current stage results."""
    out = {}
    for flow in settled.flows():
        rot, errs = settled.classical_rot(flow), settled.mfg_rot(flow, "1")
        ref = next((e for n, e in rot.items() if IRLS in n), None)
        if ref is None or not errs:
            continue
        out[flow] = []
        for b in blocks:
            ses = [bootstrap_se(lambda i, m=m, r=ref: np.log(m[i].mean(1) / r[i].mean(1)), len(m),
                                block=b) for m in errs]  # fmt: skip
            ses = [x for x in ses if x is not None]
            out[flow].append(math.sqrt(statistics.fmean(x * x for x in ses)) if ses else math.nan)
    return out


def _block_text(settled: Settled) -> str:
    """The standard errors by block length (block length in brackets), per flow."""
    return "; ".join(
        f"{_FLOW[f]}: " + ", ".join(f"{se:.3f} ({b})" for b, se in zip(BLOCKS, ses, strict=True))
        for f, ses in block_errors(settled).items()
    )


def rot_summary(errors: np.ndarray) -> tuple[float, float, float]:
    """Mean, median and failure rate (> :data:`FAILURE_RAD`) of per-pair rotation errors."""
    return float(errors.mean()), float(np.median(errors)), float((errors > FAILURE_RAD).mean())


def _sig(x: float) -> str:
    """Three significant digits: the methods' errors span 1e-5 to 1e-2 rad."""
    return f"{x:.3g}"


def _ratio_text(p: Part) -> str:
    return p.interval_text() if p.iv is not None else (p.floor or "–")


def _mfg_row(flow: str, label: str, errs: list[np.ndarray], irls: np.ndarray | None) -> list:
    stats = [rot_summary(e) for e in errs]
    mean = statistics.fmean(s[0] for s in stats)
    sd = statistics.stdev([s[0] for s in stats]) if len(stats) > 1 else None
    vs = _ratio_text(log_ratio_part(label, errs, irls)) if irls is not None else "–"
    return [
        _FLOW[flow], label, str(len(errs)),
        _sig(mean) + (f" ± {_sig(sd)}" if sd is not None else ""),
        _sig(statistics.fmean(s[1] for s in stats)),
        f"{100 * statistics.fmean(s[2] for s in stats):.1f} %", vs,
    ]  # fmt: skip


def _rows(settled: Settled) -> list[list[str]]:
    rows = []
    for flow in settled.flows():
        rot = settled.classical_rot(flow)
        irls = next((rot[n] for n in rot if IRLS in n), None)
        for k, label in (("1", "MFG (all units)"), ("0.15", "MFG (k = 15 %)")):
            if errs := settled.mfg_rot(flow, k):
                rows.append(_mfg_row(flow, label, errs, irls))
        for name, e in rot.items():
            mean, median, fail = rot_summary(e)
            rows.append([_FLOW[flow], name, "–", _sig(mean), _sig(median),
                         f"{100 * fail:.1f} %", "×1" if IRLS in name else "–"])  # fmt: skip
    return rows


def mixed_reading(settled: Settled) -> Part | None:
    """MFG trained and tested on exact flow over IRLS on DIS (a diagnostic, not a verdict: the
    paper's Table 2 compared with baselines whose numbers other papers published)."""
    if "exact" not in settled.seeds or "dis" not in settled.classical:
        return None
    rot = settled.classical_rot("dis")
    irls = next((n for n in rot if IRLS in n), None)
    errs = settled.mfg_rot("exact", "1")
    if not irls or not errs:
        return None
    return log_ratio_part("MFG on exact flow over IRLS on DIS", errs, rot[irls])


def contiguous_against_strided(settled: Settled) -> tuple[Interval, dict[str, Any]] | None:
    """log(strided MFG's mean rotation error / contiguous MFG's), both on the exact flow and the
    same test pairs: the difference of the two sets of seeds' mean log errors, its interval t
    over each set of seeds added in quadrature (a conservative stand-in for Welch's interval:
    the models differ, so there is no pairing). The contiguous side is the equal budget's, as
    the strided seeds' (whatever models the verdicts read).
    Returns it and each side's seeds, training pairs and log errors."""
    contiguous = settled.budget.get("exact") or {}
    if min(len(contiguous), len(settled.strided)) < MIN_SEEDS:
        return None
    sides = {}
    for name, runs in (("contiguous", contiguous), ("strided", settled.strided)):
        logs = _logs(runs)
        pairs = sorted({int(r["train_pairs"]) for r in runs.values()})
        sides[name] = {"logs": logs, "seeds": len(logs), "train_pairs": pairs}
    return difference(sides["strided"]["logs"], sides["contiguous"]["logs"]), sides


def _figure(settled: Settled) -> Any:
    from matplotlib.figure import Figure

    flows = settled.flows()
    if not flows:
        return None
    fig = Figure(figsize=(4.2 * len(flows) + 3.0, 3.6))
    axes = fig.subplots(1, len(flows), squeeze=False)[0]
    for ax, flow in zip(axes, flows, strict=True):
        for x, k in enumerate(("1", "0.15")):
            errs = [float(e.mean()) for e in settled.mfg_rot(flow, k)]
            ax.plot([x] * len(errs), errs, "o", color="tab:blue", alpha=0.7)
        for i, (name, e) in enumerate(settled.classical_rot(flow).items()):
            ax.axhline(float(e.mean()), color=f"C{i + 1}", lw=1.2, label=name)
        if flow == "exact" and settled.strided:
            errs = [float(np.mean(r["mfg"]["1"]["rot_err"])) for r in settled.strided.values()]
            ax.plot([2] * len(errs), errs, "s", color="tab:purple", alpha=0.7)
        ax.set_xticks([0, 1, 2] if flow == "exact" and settled.strided else [0, 1])
        ax.set_xticklabels(["MFG all", "MFG 15 %", "MFG strided"][: len(ax.get_xticks())])
        ax.set_xlim(-0.5, len(ax.get_xticks()) - 0.5)
        ax.set_yscale("log")
        ax.set_ylabel("mean rotation error (rad)")
        ax.set_title(_FLOW[flow])
    axes[-1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.suptitle("Table 2's setting: MFG per seed (dots) against the classical methods (lines)")
    fig.tight_layout()
    return fig


def _sequences(runs: dict[int, dict], data: Sequence[str]) -> list[str] | None:
    """The training sequences of a set of runs: their own override, else the study's ``data``
    overrides' (None where neither names them)."""
    ov = [*data, *next(iter(runs.values()))["overrides"]]
    seqs = dict(str(o).split("=", 1) for o in ov if "=" in str(o)).get("dataset.train_sequences")
    return None if seqs is None else [x.strip() for x in seqs.strip("[]").split(",") if x.strip()]


def _training_frames(runs: dict[int, dict]) -> str:
    """Which source frames a set of runs trained on, from their overrides."""
    ov = dict(o.split("=", 1) for o in next(iter(runs.values()))["overrides"] if "=" in o)
    seqs = ov.get("dataset.train_sequences", "the study's training sequences")
    if "dataset.frame_stride" in ov:
        return f"every {ov['dataset.frame_stride']}th source frame of {seqs}"
    return f"the first {ov.get('dataset.max_frames', '?')} frames of {seqs}"


def settle_section(settled: Settled) -> tuple[list[str], Any]:
    """The 2 × 2's tables (and its figure), or nothing before a seed and a flow's classical
    methods have run."""
    flows = settled.flows()
    if not flows:
        return [], None
    some = settled.seeds[flows[0]][min(settled.seeds[flows[0]])]
    heads = ("flow", "method", "seeds", "mean rotation error (rad)", "median (rad)", "failures",
             "over IRLS")  # fmt: skip
    cs, cs_table, frames = contiguous_against_strided(settled), "", None
    if cs is not None:
        rows = [
            [name, str(s["seeds"]), ", ".join(map(str, s["train_pairs"])),
             fmt(math.exp(statistics.fmean(s["logs"])), 5)]
            for name, s in cs[1].items()
        ]  # fmt: skip
        mean = "geometric mean of the seeds' mean rotation error (rad)"
        cs_table = table(("training pairs", "seeds", "pairs", mean), rows)
        frames = (_training_frames(settled.budget["exact"]), _training_frames(settled.strided))
    mixed = mixed_reading(settled)
    text = lines(
        "report/settle.md.j2", some=some, seeds=", ".join(f"{len(settled.seeds[f])} on {f}"
        for f in flows), steps=some.get("step_cap"), decay=float(
        (some.get("convergence") or {}).get("rule", {}).get("decay_fraction") or 0),
        failure=FAILURE_RAD, printed=PRINTED_TABLE2_ROT, table=table(heads, _rows(settled)),
        block=BLOCK_PAIRS, blocks=_block_text(settled), cs=cs, cs_table=cs_table, frames=frames,
        mixed=_ratio_text(mixed) if mixed is not None else "", reads=settled.reads,
        met=_met(settled.seeds), n=sum(map(len, settled.seeds.values())),
    )  # fmt: skip
    return text, _figure(settled)


def _met(by: dict[Any, dict[int, dict]]) -> int:
    """How many of the runs (``{key: {seed: result}}``) met their convergence rule."""
    return sum(bool(r["convergence"].get("converged")) for runs in by.values()
               for r in runs.values())  # fmt: skip


def _log_err(r: dict) -> float:
    """A run's log mean rotation error (all units)."""
    return math.log(float(np.mean(r["mfg"]["1"]["rot_err"])))


def _logs(runs: dict[int, dict]) -> list[float]:
    """Each seed's log mean rotation error, by seed."""
    return [_log_err(r) for _, r in sorted(runs.items())]


def converge_section(settled: Settled, rule: Sequence[str] = (), clamp: Any = None) -> list[str]:
    """The models trained under the rotation rule (stage ``converge``, ``rule``: its overrides;
    ``clamp``: the balancing weights' clamp that ``unclamped`` lifts) beside their references:
    per variant, its steps, how many met the rule, MFG's mean rotation error (all units) over
    IRLS's on the same pairs (:func:`log_ratio_part`) and over its reference's, paired by seed
    (t over the seeds' log ratios, :func:`interval`); the reference is the equal budget on the
    same flow, or for a variant that changes something else the converged exact-flow models."""
    rows, found = [], []
    for variant, runs in settled.converged.items():
        if not runs:
            continue
        flow = next(iter(runs.values()))["flow"]
        budget = variant in settled.budget
        ref = settled.budget[variant] if budget else settled.converged.get("exact", {})
        rot = settled.classical_rot(flow) if flow in settled.classical else {}
        irls = next((e for n, e in rot.items() if IRLS in n), None)
        errs = [np.asarray(r["mfg"]["1"]["rot_err"]) for _, r in sorted(runs.items())]
        part = log_ratio_part(variant, errs, irls) if irls is not None else None
        # paired by seed: a seed fixes the initialisation and the data order, which both runs
        # share (under the rule and the equal budget they are identical until the budget's
        # decay begins)
        common = sorted(set(runs) & set(ref)) if ref is not runs else []
        pairs = [_log_err(runs[s]) - _log_err(ref[s]) for s in common]
        moved = interval(pairs) if len(pairs) >= MIN_SEEDS else None
        steps = sorted(int(r["steps"]) for r in runs.values())
        met = _met({variant: runs})
        f = {"variant": variant, "flow": flow, "budget": budget, "moved": moved,
             "irls": _ratio_text(part) if part else "–", "part": part}  # fmt: skip
        found.append(f)
        rows.append([
            variant, _FLOW[flow], str(len(runs)), f"{steps[0]:,}–{steps[-1]:,}",
            f"{met} of {len(runs)}", _sig(math.exp(statistics.fmean(_logs(runs)))), f["irls"],
            "–" if moved is None else f"×{math.exp(moved.value):.3f} [×{math.exp(moved.lo):.3f}, "
            f"×{math.exp(moved.hi):.3f}]",
        ])  # fmt: skip
    if not rows:
        return []
    heads = ("variant", "flow", "seeds", "steps", "met the rule",
             "geometric mean rotation error (rad)", "over IRLS", "over its reference")  # fmt: skip
    text = lines("report/rotation_rule.md.j2", rule=list(rule), table=table(heads, rows),
                 found=found, reads=settled.reads, clamp=clamp)  # fmt: skip
    return [*text, ""]


def para_settle(settled: Settled, data: Sequence[str] = ()) -> str | None:
    """The reading of the 2 × 2 and of contiguous against strided pairs, from the results
    (``data``: the study's data overrides, whose training sequences a run without its own
    has)."""
    if not settled.flows():
        return None
    flows = []
    for flow in settled.flows():
        rot = settled.classical_rot(flow)
        irls = next((n for n in rot if IRLS in n), None)
        errs = settled.mfg_rot(flow, "1")
        if irls and errs:
            p = log_ratio_part("", errs, rot[irls])
            mean = statistics.fmean(float(e.mean()) for e in errs)
            irls_mean = float(rot[irls].mean())
            flows.append({"name": _FLOW[flow], "mean": mean, "seeds": len(errs),
                          "irls": irls_mean, "part": p, "text": _ratio_text(p)})  # fmt: skip
    more = 0
    if (cs := contiguous_against_strided(settled)) is not None:
        seqs = [_sequences(settled.budget["exact"], data), _sequences(settled.strided, data)]
        # a caveat to the reading where the sets also differ in how many sequences they draw on
        more = len(seqs[1]) - len(seqs[0]) if None not in seqs else 0  # type: ignore[arg-type]
    return paragraph("reading/settle.md.j2", flows=flows, cs=cs, more=more)
