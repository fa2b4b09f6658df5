"""The figures of a multirun's sparsity study (:mod:`mfg_lightning.report`): errors against
top-k and against w_s, and the active fraction against w_s, drawn from the finished jobs
that :mod:`.sweeps` read. They sit beside the sweeps they read, above
:mod:`mfg_lightning.pictures`."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from mfg_lightning.analysis.sweeps import TOP_K_KEY, W_S_KEY, JobRecord
from mfg_lightning.core.tables import finite_or_none

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: The figures of a multirun's sparsity study, as :func:`sweep_figures` names them.
SWEEP_FIGURES = ("error_vs_top_k.png", "error_vs_w_s.png", "active_fraction_vs_w_s.png")


def _group_label(job: JobRecord, keys: Sequence[str]) -> str:
    return ", ".join(f"{k.rsplit('.', 1)[-1]}={job.overrides.get(k, '')}" for k in keys) or "all"


def _error_panels(jobs: Sequence[JobRecord]) -> list[tuple[str, str | None, str]]:
    """(metric column, std column, axis label) of every error present in some finished job."""
    panels: list[tuple[str, str | None, str]] = []
    if any(j.metric("ate") is not None for j in jobs):
        panels.append(("ate", "ate_std", "ATE over 5-frame snippets (m)"))
    panels += [
        ("trans_err", None, "translation error per frame (m)"),
        ("rot_err", None, "rotation error per frame (rad)"),
    ]
    return panels


def _w_s_of(job: JobRecord) -> float | None:
    return finite_or_none(job.config_value(W_S_KEY))


def _sweep_figure(
    jobs: Sequence[JobRecord],
    swept: Sequence[str],
    x_of: Any,
    x_key: str,
    x_label: str,
    panels: Sequence[tuple[str, str | None, str]],
    x_scale: str,
    title: str,
) -> Figure:
    """One figure of panels (metric against x), one line per value of the other swept keys."""
    from matplotlib.figure import Figure as MplFigure

    group_keys = [k for k in swept if k != x_key]
    groups: dict[str, list[JobRecord]] = {}
    for j in jobs:
        groups.setdefault(_group_label(j, group_keys), []).append(j)
    from matplotlib.ticker import NullFormatter

    xs_all = sorted({x for x in (x_of(j) for j in jobs) if x is not None})
    width = max(5.0, 4.2 * len(panels))
    fig = MplFigure(figsize=(width, 3.6), dpi=110)
    axes = fig.subplots(1, len(panels), squeeze=False)
    for ax, (column, std_column, label) in zip(axes[0], panels, strict=True):
        for name, members in groups.items():
            pts = sorted(
                (x_of(j), j.metric(column), j.metric(std_column) if std_column else None)
                for j in members
                if x_of(j) is not None and j.metric(column) is not None
            )
            if not pts:
                continue
            xs, ys, es = zip(*pts, strict=True)
            yerr = [e or 0.0 for e in es] if std_column and any(e is not None for e in es) else None
            ax.errorbar(xs, ys, yerr=yerr, marker="o", capsize=3, label=name)
        if x_scale == "symlog":
            # w_s = 0 (no sparsity loss) must stay on a log-like axis: linear below the
            # smallest positive value
            positive = [x for x in xs_all if x > 0]
            ax.set_xscale("symlog", linthresh=min(positive) if positive else 1.0)
        else:
            ax.set_xscale(x_scale)
        # ticks at the swept values, labelled plainly (no 5×10¹)
        ax.set_xticks(xs_all, [f"{x:g}" for x in xs_all], fontsize="small")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.ticklabel_format(axis="y", useOffset=False, style="plain")
        ax.set_xlabel(x_label)
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    if len(labels) > 1:
        axes[0][-1].legend(handles, labels, fontsize="small")
    fig.suptitle(title, fontsize="medium")
    fig.tight_layout()
    return fig


def sweep_figures(
    jobs: Sequence[JobRecord], swept: Sequence[str]
) -> tuple[dict[str, Figure], dict[str, str]]:
    """The three plots of the sparsity study (file name → figure), and why any was not drawn.

    Only finished jobs are drawn. A plot needs at least two distinct values of its x variable.
    """
    done = [j for j in jobs if j.ok]
    images: dict[str, Figure] = {}
    skipped: dict[str, str] = {}
    top_ks = {j.top_k_percent() for j in done} - {None}
    w_ss = {_w_s_of(j) for j in done} - {None}
    panels = _error_panels(done)
    if len(top_ks) >= 2:
        images["error_vs_top_k.png"] = _sweep_figure(
            done,
            swept,
            JobRecord.top_k_percent,
            TOP_K_KEY,
            "hidden units kept at evaluation, k (%)",
            panels,
            "log",
            "error against top-k (paper §5.3, supplementary Figure 4)",
        )
    else:
        skipped["error_vs_top_k.png"] = f"top-k takes {len(top_ks)} value(s) among finished jobs"
    if len(w_ss) >= 2:
        x_label = "sparsity coefficient w_s"
        images["error_vs_w_s.png"] = _sweep_figure(
            done, swept, _w_s_of, W_S_KEY, x_label, panels, "symlog", "error against w_s"
        )
        active = [("active_fraction", None, "active hidden units per test input (fraction)")]
        images["active_fraction_vs_w_s.png"] = _sweep_figure(
            done,
            swept,
            _w_s_of,
            W_S_KEY,
            x_label,
            active,
            "symlog",
            "population sparsity against w_s (measured after top-k)",
        )
    else:
        reason = f"w_s takes {len(w_ss)} value(s) among finished jobs"
        skipped["error_vs_w_s.png"] = skipped["active_fraction_vs_w_s.png"] = reason
    return images, skipped
