"""The report's rows: one per claim, from the stages' cached results, each with its figure.

Every ``claim_*`` function takes the stage results it needs (None when not run yet) and returns a
:class:`Row` and the figure of its evidence (None when not run). The paper's figures are quoted
from its Tables 1 and 2, section 5 and the supplementary tables.
"""

from __future__ import annotations

import itertools
import math
import statistics
from dataclasses import dataclass
from typing import Any

from mfg_lightning.core.tables import fmt
from mfg_lightning.pictures import plots
from mfg_lightning.study.verdicts import (
    HOLDS,
    NOT_HOLD,
    NOT_RUN,
    PARTLY,
    Thresholds,
    count_verdict,
    relative_verdict,
    worst,
)

#: Table 1 (†, frame by frame), ATE 09 / 10 (m) by k.
PAPER_TABLE1 = {
    1.0: (0.012, 0.013),
    0.1: (0.012, 0.013),
    0.05: (0.012, 0.013),
    0.04: (0.013, 0.013),
    0.03: (0.014, 0.014),
    0.02: (0.018, 0.017),
    0.01: (0.049, 0.034),
    0.005: (0.120, 0.076),
}
PAPER_TABLE1_CENTRAL = (0.020, 0.023)
#: Table 1's * over its † at k = 100 %, per test sequence.
PAPER_CENTRAL_OVER_FRAME = {
    "09": PAPER_TABLE1_CENTRAL[0] / PAPER_TABLE1[1.0][0],
    "10": PAPER_TABLE1_CENTRAL[1] / PAPER_TABLE1[1.0][1],
}
#: Table 2, RPE translation (m) and rotation (rad) by k.
PAPER_TABLE2 = {
    1.0: (0.1769, 0.0011),
    0.25: (0.1769, 0.0011),
    0.2: (0.1788, 0.0011),
    0.15: (0.1900, 0.0011),
    0.1: (0.2849, 0.0018),
    0.05: (0.6973, 0.0026),
}


@dataclass
class Row:
    """One claim: what the paper says, what we measured, the verdict, the figure's file."""

    number: str
    claim: str
    paper: str
    ours: str = NOT_RUN
    verdict: str = NOT_RUN
    figure: str = ""


def _seqs(metrics: dict[str, float]) -> list[str]:
    return sorted({k.split("/")[0] for k in metrics if "/" in k})


def claim_table1(t1: dict | None, th: Thresholds) -> tuple[Row, Any]:
    row = Row(
        "1",
        "Table 1's shape: ATE 09/10 by k, † and *",
        "† 0.012/0.013 at k = 100, 10, 5 %; 0.018/0.017 at 2 %; 0.049/0.034 at 1 %; "
        "* 0.020/0.023 (ratios ATE(5 %)/ATE(100 %) = 1.00; * / † = 1.67/1.77)",
    )
    if t1 is None:
        return row, None
    test = t1["test"]
    seqs = _seqs(test["1"])
    ks = sorted((float(k) for k in test), reverse=True)
    parts, verdicts, central_verdicts = [], [], []
    for s in seqs:
        full = test["1"].get(f"{s}/ate")
        at5 = test.get("0.05", {}).get(f"{s}/ate")
        ratio = at5 / full if full and at5 is not None else None
        verdicts.append(relative_verdict(ratio, 1.0, th))
        central = test["1"].get(f"{s}/ate_central")
        # The * protocol's cost over † (the paper's own ratio, so that the synthetic data's
        # different scale of ATE does not decide the verdict).
        paper_ratio = PAPER_CENTRAL_OVER_FRAME.get(s)
        central_ratio = central / full if central is not None and full else None
        if paper_ratio is not None:
            central_verdicts.append(relative_verdict(central_ratio, paper_ratio, th))
        parts.append(
            f"{s}: † {fmt(full)} (all) → {fmt(at5)} (5 %, ×{fmt(ratio, 2)}) → "
            f"{fmt(test.get('0.01', {}).get(f'{s}/ate'))} (1 %); "
            f"* {fmt(central)} (* / † ×{fmt(central_ratio, 2)})"
        )
    trained = " ".join(t1.get("train_overrides", [])) or "the default offsets"
    row.ours = f"(model trained with {trained}) " + "; ".join(parts)
    # Two parts, the shape in k (†) and the centre-frame protocol (*): both met holds, one
    # partly, neither does not hold (the report's rule for claims of several parts).
    halves = [worst(v) for v in (verdicts, central_verdicts) if v]
    row.verdict = (
        NOT_HOLD
        if not halves or all(v == NOT_HOLD for v in halves)
        else HOLDS
        if all(v == HOLDS for v in halves)
        else PARTLY
    )
    panels = []
    for key, label in (("ate", "ATE † (m)"), ("ate_central", "ATE * (m)")):
        lines = {
            f"ours {s}": ([100 * k for k in ks], [test[f"{k:g}"].get(f"{s}/{key}") for k in ks])
            for s in seqs
        }
        if key == "ate":
            for i, s in enumerate(("09", "10")):
                pk = sorted(PAPER_TABLE1, reverse=True)
                lines[f"paper {s}"] = ([100 * k for k in pk], [PAPER_TABLE1[k][i] for k in pk])
        panels.append((label, lines))
    fig = plots.line_figure(
        panels, "hidden units kept, k (%)", "ATE against k", log_x=True, log_y=True
    )
    return row, fig


def claim_sparsity(models: dict[str, dict], th: Thresholds, tol: float) -> tuple[Row, Any]:
    row = Row(
        "2",
        "sparsity against w_s (and input scale)",
        "w_s = 100: ~5 % of units suffice (k = 5 % keeps Table 1's ATE); sparser with larger w_s",
    )
    if not models:
        return row, None
    names = list(models)
    af = [models[n]["active_fraction"] for n in names]
    kstar = [models[n]["k_star"] for n in names]
    row.ours = "; ".join(
        f"{n}: active {fmt(100 * a if a is not None else None, 1)} %, smallest k within "
        f"{100 * tol:g} % (val) {fmt(100 * k if k is not None else None, 1)} % "
        f"(test ATE {fmt(models[n]['test_full'])} → {fmt(models[n]['test_k_star'])})"
        for n, a, k in zip(names, af, kstar, strict=True)
    )
    ws = [(models[n]["w_s"], models[n]["active_fraction"]) for n in names if models[n]["plain"]]
    ws.sort()
    monotone = len(ws) > 1 and all(
        a is not None and b is not None and b <= a for (_, a), (_, b) in itertools.pairwise(ws)
    )
    main = [models[n]["k_star"] for n in names if models[n]["plain"] and models[n]["w_s"] == 100]
    small = bool(main) and main[0] is not None and main[0] <= 0.05 * (1 + th.holds)
    row.verdict = count_verdict(int(monotone) + int(small), 2)
    fig = plots.bar_figure(
        [
            ("active fraction (%)", {"ours": [None if a is None else 100 * a for a in af]}),
            (
                "smallest k within tolerance (%)",
                {"ours": [None if k is None else 100 * k for k in kstar]},
            ),
        ],
        names,
        "Sparsity against w_s (validation)",
    )
    return row, fig


def claim_table2(t2: dict | None, th: Thresholds) -> tuple[Row, Any]:
    row = Row(
        "3",
        "Table 2's shape (VKITTI-sized set): RPE by k, against classical methods",
        "RPE trans 0.1769 (all) = 25 % → 0.1788 (20 %) → 0.2849 (10 %) → 0.6973 (5 %); rot "
        "0.0011, better than the classical baseline's 0.0014",
    )
    if t2 is None:
        return row, None
    mfg, classical = t2["mfg"], t2["classical"]
    full = mfg["1"]
    ratio20 = mfg["0.2"]["rpe_trans"] / full["rpe_trans"] if full.get("rpe_trans") else None
    ratio10 = mfg["0.1"]["rpe_trans"] / full["rpe_trans"] if full.get("rpe_trans") else None
    best_rot = min(
        (c["metrics"].get("rpe_rot", math.inf) for c in classical if "oracle" not in c["name"]),
        default=math.inf,
    )
    shape = worst(
        [
            relative_verdict(ratio20, 0.1788 / 0.1769, th),
            relative_verdict(ratio10, 0.2849 / 0.1769, th),
        ]
    )
    rot_better = full.get("rpe_rot", math.inf) <= best_rot
    row.verdict = shape if rot_better else worst([shape, PARTLY])
    row.ours = (
        f"{t2['train_pairs']} training / {t2['test_pairs']} test pairs; RPE trans "
        + " → ".join(f"{fmt(mfg[k]['rpe_trans'])} ({100 * float(k):g} %)" for k in mfg)
        + f" (×{fmt(ratio20, 2)} at 20 %, ×{fmt(ratio10, 2)} at 10 %; paper ×1.01, ×1.61); rot "
        f"{fmt(full.get('rpe_rot'), 5)} against the best classical {fmt(best_rot, 5)}"
    )
    names = [f"MFG {100 * float(k):g} %" for k in mfg] + [c["name"] for c in classical]
    trans = [m["rpe_trans"] for m in mfg.values()] + [
        c["metrics"].get("rpe_trans") for c in classical
    ]
    rot = [m["rpe_rot"] for m in mfg.values()] + [c["metrics"].get("rpe_rot") for c in classical]
    fig = plots.bar_figure(
        [("RPE translation (m)", {"ours": trans}), ("RPE rotation (rad)", {"ours": rot})],
        names,
        "Table 2's shape",
        log_y=True,
    )
    return row, fig


def claim_robustness(rb: dict | None) -> tuple[Row, Any]:
    row = Row(
        "4",
        "robustness to independently moving objects",
        "MFG marginalises moving objects: its error grows less with their coverage than the "
        "classical methods'",
    )
    if rb is None:
        return row, None
    g = {n: r["growth"] for n, r in rb["methods"].items()}
    mfg = [v for n, v in g.items() if n.startswith("MFG")]
    other = [v for n, v in g.items() if not n.startswith("MFG") and v is not None]
    m = mfg[0] if mfg else None
    if m is None or not other:
        row.verdict = NOT_HOLD
    else:
        row.verdict = (
            HOLDS if m <= min(other) else PARTLY if m <= statistics.median(other) else NOT_HOLD
        )
    row.ours = (
        "rotation error, most / least covered bin: "
        + "; ".join(f"{n} ×{fmt(v, 2)}" for n, v in g.items())
        + f" (bins {rb['edges']}, samples per bin {rb['counts']})"
    )
    centres = [
        (lo + hi) / 2 * 100 for lo, hi in zip(rb["edges"][:-1], rb["edges"][1:], strict=True)
    ]
    panels = [
        (label, {n: (centres, [b["mean"] for b in r[key]]) for n, r in rb["methods"].items()})
        for key, label in (
            ("rot_bins", "rotation error (rad)"),
            ("trans_bins", "translation error (m)"),
        )
    ]
    fig = plots.line_figure(
        panels,
        "image covered by moving objects (%, bin centre)",
        "Error against moving-object coverage (test)",
        log_y=True,
    )
    return row, fig


def claim_basis(bs: dict | None, residual: float) -> tuple[Row, Any]:
    row = Row(
        "5",
        "basis selectivity (supplementary Figures 5–8)",
        "units select one motion each, spread over directions; |t| ~0.01, |ω| ~0.03–0.15 per unit",
    )
    if bs is None:
        return row, None
    from mfg_lightning.analysis.basis import selectivity_figure

    n = len(bs["residual_t"])
    expl_t = sum(r <= residual for r in bs["residual_t"])
    expl_w = sum(r <= residual for r in bs["residual_w"])
    t_ok = bs["t_norm_median"] is not None and 0.005 <= bs["t_norm_median"] <= 0.02
    w_ok = bs["w_norm_median"] is not None and 0.03 <= bs["w_norm_median"] <= 0.15
    explained = n and (expl_t + expl_w) >= 0.8 * 2 * n
    row.verdict = count_verdict(int(bool(explained)) + int(t_ok) + int(w_ok), 3)
    row.ours = (
        f"of the {n} largest units, one translation explains {expl_t}, one rotation {expl_w} "
        f"(relative residual ≤ {residual:g}); median |t| {fmt(bs['t_norm_median'])}, |ω| "
        f"{fmt(bs['w_norm_median'])}; resultant length of directions t "
        f"{fmt(bs['t_resultant'], 2)}, "
        f"ω {fmt(bs['w_resultant'], 2)} (0: spread evenly, 1: one direction)"
    )
    return row, selectivity_figure(bs["rows"])


def claim_object_motion(om: dict | None) -> tuple[Row, Any]:
    row = Row(
        "6",
        "object motion: the paper's filters against a threshold",
        "the filters keep slow, distant movers that a threshold loses",
    )
    if om is None:
        return row, None
    f, t = om["filters"], om["threshold"]

    def get(d: dict, group: str, key: str) -> float | None:
        return d.get(group, {}).get(key)

    far = (get(f, "all", "far/recall") or 0) > (get(t, "all", "far/recall") or 0)
    slow = (get(f, "slow", "recall") or 0) > (get(t, "slow", "recall") or 0)
    row.verdict = count_verdict(int(far) + int(slow), 2)
    cats = [
        ("all", "iou"),
        ("all", "recall"),
        ("all", "precision"),
        ("all", "near/recall"),
        ("all", "far/recall"),
        ("slow", "recall"),
        ("fast", "recall"),
    ]
    row.ours = "filters / threshold: " + "; ".join(
        f"{_label(g, k)} {fmt(get(f, g, k), 3)} / {fmt(get(t, g, k), 3)}" for g, k in cats
    )
    names = [_label(g, k) for g, k in cats]
    fig = plots.bar_figure(
        [
            (
                "score",
                {
                    "filters (§4)": [get(f, g, k) for g, k in cats],
                    "threshold": [get(t, g, k) for g, k in cats],
                },
            )
        ],
        names,
        "Object masks (test)",
    )
    return row, fig


def _label(group: str, key: str) -> str:
    return key if group == "all" else f"{group} {key}"


def claim_learning_curve(lc: dict | None, th: Thresholds) -> tuple[Row, Any]:
    row = Row(
        "7",
        "learning curve of the main model: did the budget converge?",
        "trained to convergence (batch 1, lr 1e-5; length not stated)",
    )
    if lc is None or not lc["points"]:
        return row, None
    pts = lc["points"]
    x = [p["samples"] for p in pts]
    # Validation on every Nth frame (dataset.frame_stride) has no five-frame chain: its † ATE
    # is NaN throughout, and the centre-frame ATE (*) is the curve's ATE then.
    key, name = "val/ate", "val ATE †"
    if not any(math.isfinite(p.get(key, math.nan)) for p in pts):
        key, name = "val/ate_central", "val ATE * (no † ATE: validation on every Nth frame)"
    final = pts[-1].get(key, math.nan)
    three_q = min(pts, key=lambda p: abs(p["samples"] - 0.75 * x[-1])).get(key, math.nan)
    change = (three_q - final) / final if final and math.isfinite(final) else None
    row.verdict = relative_verdict(None if change is None else 1 + change, 1.0, th)
    row.ours = (
        f"{name} {fmt(pts[0].get(key))} ({x[0]} samples) → {fmt(three_q)} (75 %) → "
        f"{fmt(final)} ({x[-1]} samples): {fmt(None if change is None else 100 * change, 1)} % "
        f"over the last quarter ({'converged' if row.verdict == HOLDS else 'not converged'} "
        f"by the thresholds); test ATE at the end {fmt(lc.get('test_ate'))}"
    )
    panels = [
        (label, {"validation": (x, [p.get(key) for p in pts])})
        for key, label in (
            (key, "ATE † (m)" if key == "val/ate" else "ATE * (m)"),
            ("val/rpe_trans", "RPE trans (m)"),
            ("val/active_fraction", "active fraction"),
        )
    ]
    return row, plots.line_figure(panels, "training samples seen", "Learning curve (main model)")


def claim_recipe(rc: dict | None, th: Thresholds) -> tuple[Row, Any]:
    row = Row(
        "R",
        "CPU recipe against the paper's (same samples seen)",
        "batch 1, Adam lr 1e-5, betas (0.99, 0.999), constant rate",
    )
    if rc is None:
        return row, None
    a, b = rc["cpu"], rc["paper"]
    row.verdict = relative_verdict(b["val_ate"], a["val_ate"], th)
    row.ours = (
        f"{a['samples_seen']} samples: CPU recipe (batch {a['recipe']['batch_size']}, lr "
        f"{a['recipe']['lr']:g}, {a['recipe']['scheduler'] or 'constant'}) val ATE "
        f"{fmt(a['val_ate'])}, test {fmt(a['test_ate'])}; paper recipe val ATE "
        f"{fmt(b['val_ate'])}, test {fmt(b['test_ate'])} (verdict: paper's against CPU's)"
    )
    panels = [
        (
            "val ATE † (m)",
            {
                n: ([p["samples"] for p in r["curve"]], [p["val/ate"] for p in r["curve"]])
                for n, r in (("CPU recipe", a), ("paper recipe", b))
            },
        )
    ]
    return row, plots.line_figure(panels, "training samples seen", "Recipes, same samples")
