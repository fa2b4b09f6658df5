"""The report's figures that no diagnostic row owns: every judged part against its bound
(:func:`verdict_figure`) and every trained model's convergence (:func:`convergence_rows`, not a
claim of the paper: its table and validation curves)."""

from __future__ import annotations

import math
import re
from typing import Any

from mfg_lightning.core.tables import fmt
from mfg_lightning.pictures import plots

__all__ = ["CURVE_PANELS", "convergence_rows", "verdict_figure"]


def convergence_rows(models: dict[str, dict]) -> tuple[list[list[str]], Any]:
    """One row per trained model: steps, samples, whether the rule was met (or why it stopped),
    the best validation value of the metric its rule monitored (ATE †, or the rotation error
    under the rotation rule); and one figure with every model's validation ATE † curve."""
    rows, lines = [], {}
    for name, m in models.items():
        c = m.get("convergence") or {}
        curve = m.get("curve") or []
        ates = [p.get("val/ate") for p in curve]
        if c.get("converged"):
            state = f"converged at step {c.get('decay_start')} (decay to {c.get('decay_end')})"
        elif c.get("reason") == "budget":
            state = f"equal budget (decay from {c.get('decay_start')} to {c.get('decay_end')})"
        else:
            state = f"not converged at {m.get('steps')} steps ({c.get('reason') or 'no rule'})"
        monitor = str((c.get("rule") or {}).get("monitor") or "val/ate")
        watched = [v for p in curve if (v := p.get(monitor)) is not None and math.isfinite(v)]
        best = f"{fmt(min(watched), 5 if 'rot' in monitor else 4)} ({monitor})" if watched else "–"
        minutes = m.get("train_seconds", 0.0) / 60
        rows.append([name, str(m.get("steps")), str(m.get("samples_seen")), state, best,
                     f"{minutes:.0f}"])  # fmt: skip
        if curve:
            lines[name] = ([p["samples"] for p in curve], ates)
    if not lines:
        return rows, None
    panels = _curve_panels(lines)
    return rows, plots.curve_groups_figure(
        panels, "training samples seen", "val ATE † (m)", "Validation curves", log_y=True
    )


#: The convergence figure's panels: a model goes to the first whose prefix its name has.
CURVE_PANELS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("main setting", ("main", "exact-flow twin", "learned")),
    ("Table 2 setting", ("table2", "balance", "end to end")),
    ("size curve", ("size",)),
    ("sparsity, recipe", ("sparsity", "recipe")),
)


def _curve_panels(lines: dict[str, tuple]) -> list[tuple[str, dict[str, list[tuple]]]]:
    """The models' curves in :data:`CURVE_PANELS` (the rest under "other"), a model's seeds
    (``, seed N``, ``_seedN``) in one group."""
    panels: dict[str, dict[str, list[tuple]]] = {}
    for name, curve in lines.items():
        panel = next((t for t, prefixes in CURVE_PANELS if name.startswith(prefixes)), "other")
        group = re.sub(r"(, seed \d+|_seed\d+)$", "", name)
        panels.setdefault(panel, {}).setdefault(group, []).append(curve)
    order = [t for t, _ in CURVE_PANELS] + ["other"]
    return [(t, panels[t]) for t in order if t in panels]


def verdict_figure(judged: list[Any]) -> Any:
    """Every judged part's interval against its bound, on one axis: the distance from the bound
    in half-widths of the part's own interval, signed so that the claimed side is on the left
    for every part (holds: the whole bar left of 0; does not hold: right of it)."""
    from matplotlib.figure import Figure

    parts = [(j.sentence.key, p) for j in judged for p in j.parts if p.judged is not None]
    if not parts:
        return None
    lim = 6.0
    colour = {"holds": "tab:green", "does not hold": "tab:red"}
    fig = Figure(figsize=(10, 0.32 * len(parts) + 1.8))
    ax = fig.subplots()
    for i, (_, p) in enumerate(parts):
        iv = p.judged
        half = max((iv.hi - iv.lo) / 2, 1e-300)
        sign = 1.0 if p.direction == "<=" else -1.0
        centre = sign * (iv.value - p.bound) / half
        c = colour.get(p.verdict, "0.5")
        shown = min(max(centre, -lim), lim)
        if iv.hi == iv.lo:
            # no spread at all (the same value in every seed and pair): a point, not a bar
            ax.plot(shown, i, "D", color=c)
            continue
        lo, hi = max(centre - 1, -lim), min(centre + 1, lim)
        if lo < hi:
            ax.plot([lo, hi], [i, i], color=c, lw=4, solid_capstyle="butt")
        ax.plot(shown, i, "o" if shown == centre else ">" if centre > lim else "<", color=c)
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_xlim(-lim - 0.5, lim + 0.5)
    ax.set_yticks(range(len(parts)))
    # S10's bins name their size and speed last: shortened so that the tick label keeps them
    short = [p.label.replace("velocity error, ", "").replace(" of the image", "") for _, p in parts]
    ax.set_yticklabels([f"{k} {lab[:70]}" for (k, _), lab in zip(parts, short, strict=True)],
                       fontsize=7)  # fmt: skip
    ax.set_xlabel(
        "distance from the bound, in half-widths of the part's 95 % interval\n"
        "(left of 0: the claimed side; a triangle: beyond the axis; a diamond: no spread)"
    )
    ax.invert_yaxis()
    ax.set_title(
        "Verdicts per part\ngreen holds · red does not hold · grey inconclusive", fontsize=10
    )
    fig.tight_layout()
    return fig
