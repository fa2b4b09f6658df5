"""The report's diagnostics: the shape of the paper's tables and figures beside ours, from the
stages' cached results, each with its figure and its deviations from the paper, never turned into
verdicts (the verdicts are per sentence of the paper: :mod:`mfg_lightning.study.sentences`).

Every ``claim_*`` function takes the stage results it needs (None when not run yet) and returns a
:class:`Row` and the figure of its evidence (None when not run); the rows' words are
``templates/diagnostics.yaml`` and ``templates/diagnostics/*.md.j2``. The paper's figures are quoted
from its Tables 1 and 2, section 5 and the supplement. Convergence is not a claim of the paper:
:func:`mfg_lightning.study.figures.convergence_rows` reports it for every trained model.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

from mfg_lightning.core.config import load_yaml_mapping
from mfg_lightning.core.tables import fmt
from mfg_lightning.pictures import plots
from mfg_lightning.study.noise import ratio
from mfg_lightning.study.render import TEMPLATES, paragraph
from mfg_lightning.study.rules import smallest_k
from mfg_lightning.study.verdicts import NOT_RUN, relative_deviation

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
SEQS = ("09", "10")
#: Table 1's * over its † at k = 100 %, per test sequence.
PAPER_CENTRAL_OVER_FRAME = {
    s: PAPER_TABLE1_CENTRAL[i] / PAPER_TABLE1[1.0][i] for i, s in enumerate(SEQS)
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
#: The supplement's typical rotational unit |ω| over the typical translational unit |t|.
PAPER_UNIT_RATIO = 5.0


@dataclass(frozen=True)
class Rule:
    """One diagnostic row: the paper's table or figure it compares with, what it shows."""

    number: str
    claim: str
    paper: str
    parts: tuple[str, ...]


#: The diagnostics' rows, by number, from ``templates/diagnostics.yaml`` (the words).
RULES: dict[str, Rule] = {
    str(k): Rule(str(k), r["claim"], r["paper"], tuple(r["parts"]))
    for k, r in load_yaml_mapping(TEMPLATES / "diagnostics.yaml").items()
}


@dataclass
class Row:
    """One diagnostic: what the paper shows, what we measured, the figure's file."""

    number: str
    claim: str
    paper: str
    ours: str = NOT_RUN
    figure: str = ""

    @classmethod
    def of(cls, number: str) -> Row:
        rule = RULES[number]
        return cls(number, rule.claim, rule.paper)


def _dev(ours: float | None, paper: float) -> str:
    """The signed relative deviation of ours from the paper's, e.g. ``+3.4 %``."""
    d = relative_deviation(ours, paper)
    if not math.isfinite(d):
        return "–"
    sign = "+" if (ours or 0.0) >= paper else "−"
    return f"{sign}{100 * d:.1f} %"


def _vs(ours: float | None, paper: float) -> str:
    """Our ratio beside the paper's and the deviation, e.g. ``×1.05 (1.00, +5.0 %)``."""
    return f"×{fmt(ours, 2)} ({paper:.2f}, {_dev(ours, paper)})"


def _pct(x: float | None) -> float | None:
    """A fraction in percent (None stays None)."""
    return None if x is None else 100 * x


# --------------------------------------------------------------------------------------------
# The claims
# --------------------------------------------------------------------------------------------


def claim_table1(t1: dict | None) -> tuple[Row, Any]:
    """Table 1's shape: each k's ATE † over all units', and * / †, beside the paper's (seed 0,
    the main model; the seeds' spread is in the headline table)."""
    row = Row.of("1")
    if t1 is None:
        return row, None
    test = t1["test"]
    ks = sorted((float(k) for k in test), reverse=True)
    texts = []
    for i, s in enumerate(SEQS):
        full, c = test["1"].get(f"{s}/ate"), test["1"].get(f"{s}/ate_central")
        at = [f"{100 * k:g} % " + _vs(ratio(test[f"{k:g}"].get(f"{s}/ate"), full),
                                      PAPER_TABLE1[k][i] / PAPER_TABLE1[1.0][i])
              for k in ks if k < 1 and k in PAPER_TABLE1]  # fmt: skip
        texts.append(
            f"{s}: † {fmt(full)} at 100 %, ratios (paper's, deviation) " + ", ".join(at)
            + f"; * {fmt(c)}, * / † {_vs(ratio(c, full), PAPER_CENTRAL_OVER_FRAME[s])}"
        )  # fmt: skip
    row.ours = "; ".join(texts)
    panels = []
    for key, label in (("ate", "ATE † (m)"), ("ate_central", "ATE * (m)")):
        lines = {
            f"ours {s}": ([100 * k for k in ks], [test[f"{k:g}"].get(f"{s}/{key}") for k in ks])
            for s in SEQS
        }
        if key == "ate":
            pk = sorted(PAPER_TABLE1, reverse=True)
            for i, s in enumerate(SEQS):
                lines[f"paper {s}"] = ([100 * k for k in pk], [PAPER_TABLE1[k][i] for k in pk])
        panels.append((label, lines))
    return row, plots.line_figure(
        panels, "hidden units kept, k (%)", "ATE against k (test)", log_x=True, log_y=True
    )


def claim_sparsity(
    t1: dict | None, models: dict[str, dict], tol: float
) -> tuple[Row, Any, list[str]]:
    """The main model's validation ATE † against k; the w_s sweep (this project's extension)
    as extra lines, each labelled with the input scale it was trained at."""
    row = Row.of("2")
    sweep = []
    for name, m in models.items():
        scale = "" if "input_scale" in name else " (input_scale=1)"
        sweep.append(
            f"{name}{scale}: active {fmt(_pct(m.get('active_fraction')), 2)} %, smallest k "
            f"{fmt(_pct(m['k_star']), 1)} % (val), test ATE "
            f"{fmt(m['test_full'])} → {fmt(m['test_k_star'])} at that k"
            + ("; collapsed (no unit active on the average input)" if m.get("collapsed") else "")
        )
    if t1 is None:
        return row, _sweep_figure(models, None), sweep
    k_star = smallest_k(t1["val"], tol)
    full = t1["val"].get("1", {}).get("ate")
    at = t1["val"].get(f"{k_star:g}", {}).get("ate") if k_star is not None else None
    row.ours = (
        f"main model: the smallest k within {100 * tol:g} % of all units' validation ATE † "
        f"({fmt(full)}) is {fmt(_pct(k_star), 1)} % (ATE † {fmt(at)})"
    )
    return row, _sweep_figure(models, t1["val"]), sweep


def _sweep_figure(models: dict[str, dict], main_val: dict | None) -> Any:
    """The main model's validation ATE † against k (claim 2's evidence); the sweep's active
    fractions and smallest k when it has run."""
    if not models:
        if not main_val:
            return None
        ks = sorted((float(k) for k in main_val), reverse=True)
        lines = {"main model": ([100 * k for k in ks], [main_val[f"{k:g}"].get("ate") for k in ks])}
        return plots.line_figure(
            [("val ATE † (m)", lines)], "hidden units kept, k (%)",
            "Main model (w_s = 100): validation ATE against k", log_x=True, log_y=True,
        )  # fmt: skip
    panels = [
        (label, {"ours": [_pct(m.get(key)) for m in models.values()]})
        for key, label in (("active_fraction", "active fraction (%)"),
                           ("k_star", "smallest k within tolerance (%)"))
    ]  # fmt: skip
    title = "Sparsity against w_s (validation; this project's extension)"
    return plots.bar_figure(panels, list(models), title)


def claim_table2(t2: dict | None, offsets: list[int] | None = None) -> tuple[Row, Any]:
    """Table 2's shape on the Table-2-sized model: RPE translation against k beside the
    paper's ratios, and every method's rotation error."""
    row = Row.of("3")
    if t2 is None:
        return row, None
    mfg, classical = t2["mfg"], t2["classical"]
    full, paper = mfg["1"], PAPER_TABLE2[1.0][0]
    ratios = [
        f"{100 * k:g} % " + _vs(ratio(mfg.get(f"{k:g}", {}).get("rpe_trans"),
                                      full.get("rpe_trans")), PAPER_TABLE2[k][0] / paper)
        for k in (0.2, 0.15, 0.1, 0.05)
    ]  # fmt: skip
    others = [c for c in classical if "oracle" not in c["name"]]
    rots = "; ".join(f"{c['name']} {fmt(c['metrics'].get('rpe_rot'), 5)}" for c in others)
    row.ours = (
        f"{t2['train_pairs']} training / {t2['test_pairs']} test pairs"
        + (f" (offsets {', '.join(f'{o:+d}' for o in offsets)} only)" if offsets else "")
        + f"{_flow_label(t2)}; RPE trans {fmt(full.get('rpe_trans'))} at 100 %, ratios (paper's, "
        "deviation) " + ", ".join(ratios)
        + f"; RPE rot MFG {fmt(full.get('rpe_rot'), 5)}, {rots}"
    )  # fmt: skip
    names = [f"MFG {100 * float(k):g} %" for k in mfg] + [c["name"] for c in classical]
    panels = []
    for key, label in (("rpe_trans", "RPE translation (m)"), ("rpe_rot", "RPE rotation (rad)")):
        ours = [m[key] for m in mfg.values()] + [c["metrics"].get(key) for c in classical]
        panels.append((label, {"ours": ours}))
    return row, plots.bar_figure(panels, names, "Table 2's shape (test)", log_y=True)


def claim_robustness(mt: dict | None) -> tuple[Row, Any]:
    """Every method's rotation and translation errors by moving-object coverage."""
    row = Row.of("4")
    if mt is None:
        return row, None
    bins = mt["bins"]
    mfg_name = next(n for n in bins if n.startswith("MFG"))
    classical = {n: b for n, b in bins.items() if not n.startswith("MFG") and "oracle" not in n}

    def last_mean(b: dict) -> float | None:
        filled = [x for x in b["rot_bins"] if x["n"] and x["mean"] is not None]
        return filled[-1]["mean"] if filled else None

    best = min(classical, key=lambda n: last_mean(classical[n]) or math.inf, default=None)
    row.ours = paragraph("diagnostics/robustness.md.j2", mt=mt, mfg=mfg_name,
                         ours=last_mean(bins[mfg_name]), best=best,
                         best_abs=last_mean(classical[best]) if best else None)  # fmt: skip
    centres = [(lo + hi) / 2 * 100 for lo, hi in itertools.pairwise(mt["edges"])]
    panels = [
        (label, {n: (centres, [b["mean"] for b in r[key]]) for n, r in bins.items()})
        for key, label in (("rot_bins", "rotation error (rad)"),
                           ("trans_bins", "translation error (m)"))
    ]  # fmt: skip
    return row, plots.line_figure(
        panels, "image covered by moving objects (%, bin centre)",
        "Error against moving-object coverage (test, +1 pairs)", log_y=True,
    )  # fmt: skip


def one_motion_fractions(bs: dict, residual: float) -> dict[str, float]:
    """Per decoder (``"t"``, ``"omega"``) of a ``basis`` measurement: the fraction of its top
    units whose field one motion fits (relative residual ≤ ``residual``)."""
    return {
        k: sum(r <= residual for r in d["residual"]) / max(len(d["residual"]), 1)
        for k, d in bs["per_decoder"].items()
    }


def claim_basis(bs: dict | None, residual: float) -> tuple[Row, Any]:
    """The basis units of each decoder: one-motion fits, spread of directions, scale."""
    row = Row.of("5")
    if bs is None:
        return row, None
    explained = one_motion_fractions(bs, residual)
    row.ours = paragraph(
        "diagnostics/basis.md.j2", bs=bs, explained=explained, paper_ratio=PAPER_UNIT_RATIO
    )
    return row, _basis_figure(bs["per_decoder"])


def _basis_figure(per: dict[str, dict]) -> Any:
    """Each decoder's top units in rank order: the motion at activation 1 and at the unit's
    typical activation (the scale-free one)."""
    panels = []
    for key, label in (("t", "translational units: |t| (m)"),
                       ("omega", "rotational units: |ω| (rad)")):  # fmt: skip
        d = per[key]
        rank = list(range(1, len(d["units"]) + 1))
        typical = [m if m > 0 else None for m in d["motion_typical"]]
        panels.append((label, {"at activation 1": (rank, d["motion_at_1"]),
                               "at its typical activation": (rank, typical)}))  # fmt: skip
    return plots.line_figure(
        panels, "rank by the decoder's own column norm", "Basis units (validation)", log_y=True
    )


def claim_object_motion(om: dict | None) -> tuple[Row, Any]:
    """The object masks of the filters and the threshold, on exact and estimated flow."""
    row = Row.of("6")
    if om is None:
        return row, None
    cats = [("all", "iou"), ("all", "precision"), ("all", "recall"), ("all", "near/recall"),
            ("all", "far/recall"), ("slow", "recall"), ("fast", "recall")]  # fmt: skip
    om = {k: v for k, v in om.items() if isinstance(v, dict) and "scores" in v}
    row.ours = paragraph("diagnostics/object_motion.md.j2", om=om, cats=cats, label=_label)
    panels = [
        (f"{name} flow (threshold {r['threshold']['threshold']:g} px)",
         {label: [r["scores"][method].get(g, {}).get(k) for g, k in cats]
          for method, label in (("filters", "filters (§4)"),
                                ("threshold", "threshold (chosen on validation)"))})
        for name, r in om.items()
    ]  # fmt: skip
    names = [_label(g, k) for g, k in cats]
    return row, plots.bar_figure(panels, names, "Object masks (test, +1 pairs)")


def _label(group: str, key: str) -> str:
    return key if group == "all" else f"{group} {key}"


def claim_recipe(rc: dict | None) -> tuple[Row, Any]:
    """Row R: the CPU recipe against the paper's, each under the common rule (a diagnostic:
    the paper does not claim one recipe over another)."""
    row = Row.of("R")
    if rc is None:
        return row, None
    a, b = rc["cpu"], rc["paper"]
    long_enough = min(a.get("epochs", 0.0), b.get("epochs", 0.0)) >= 1.0 - 1e-9
    dev = _dev(b["val_ate"], a["val_ate"]) if long_enough else None
    row.ours = paragraph("diagnostics/recipe.md.j2", a=a, b=b, dev=dev)
    curves = {
        n: ([p["samples"] for p in r["curve"]], [p.get("val/ate") for p in r["curve"]])
        for n, r in (("CPU recipe", a), ("paper recipe", b))
    }
    return row, plots.line_figure(
        [("val ATE † (m)", curves)], "training samples seen", "Recipes (validation)", log_y=True
    )


def _flow_label(result: dict) -> str:
    """``", exact flow"`` or ``", DIS flow"`` from a trained model's overrides."""
    flows = [o.split("=", 1)[1] for o in result.get("overrides", []) if o.startswith("flow=")]
    return f", {flows[-1]} flow" if flows else ""
