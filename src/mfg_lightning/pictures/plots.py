"""Trajectory figures: every method over the ground truth, drift per segment length, error along
the trajectory; ATE against top-k (an evaluation's sweep) and a multirun's error and sparsity
against top-k and w_s; and figures as PNG bytes or RGB arrays (for files and TensorBoard).

Drawn with matplotlib's object-oriented API on an Agg canvas (no pyplot state, no display), so
they work in tests, on servers and inside training processes. Each method keeps one colour in
every figure (the order methods are given in); the ground truth is black. Lengths are in metres.

:func:`trajectory_curves` computes what the figures show for one method on one sequence, with the
metrics of :mod:`mfg_lightning.metrics` (alignment, per-pose errors, drift per segment length);
:func:`sequence_figures` draws the three figures of one sequence.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mfg_lightning.core.tables import finite_or_none

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from torch import Tensor

    from mfg_lightning.metrics import Alignment

__all__ = [
    "PLOT_MODES",
    "SEQUENCE_FIGURES",
    "TrajectoryCurves",
    "bar_figure",
    "curve_groups_figure",
    "curves_from_alignment",
    "drift_by_length_figure",
    "error_along_trajectory_figure",
    "figure_png",
    "figure_rgb",
    "line_figure",
    "log_figures",
    "method_colour",
    "save_figures",
    "sequence_figures",
    "top_k_figure",
    "trajectory_curves",
    "trajectory_figure",
    "write_trajectory_figures",
]

#: Ground truth is drawn in black, methods in the qualitative ``tab10`` colours.
GT_COLOUR = "black"
_DPI = 120


def method_colour(index: int) -> str:
    """The colour of the ``index``-th method (``tab10``, cycling after ten)."""
    return f"C{index % 10}"


def figure_png(fig: Figure) -> bytes:
    """A figure as PNG bytes (Agg canvas; no display or pyplot state needed)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def figure_rgb(fig: Figure) -> np.ndarray:
    """A figure rendered to an ``(H, W, 3)`` uint8 RGB array (TensorBoard's ``add_image``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


@dataclass(frozen=True)
class TrajectoryCurves:
    """What the figures show of one method on one sequence (numpy, float64, metres).

    Attributes:
        gt_xyz: ``(M, 3)`` ground-truth positions of the estimated (matched) frames, in the frame
            the method was aligned in.
        pred_xyz: ``(M, 3)`` aligned estimated positions.
        distance: ``(M,)`` ground-truth path length from the ground truth's first frame.
        error: ``(M,)`` per-pose position error after alignment (the whole-trajectory ATE's).
        drift: ``{segment length (m): (t_err %, r_err deg/100 m)}`` for the lengths with at
            least one complete segment (empty on a path shorter than 100 m).
        scale: the fitted scale of the alignment.
    """

    gt_xyz: np.ndarray
    pred_xyz: np.ndarray
    distance: np.ndarray
    error: np.ndarray
    drift: dict[float, tuple[float, float]]
    scale: float


def trajectory_curves(
    pred: Tensor, target: Tensor, align: str = "none", n_to_align: int | None = None
) -> TrajectoryCurves:
    """Align one estimate and compute the curves of :class:`TrajectoryCurves`.

    Args:
        pred: ``(N, 4, 4)`` estimated camera-to-world poses, in frame order.
        target: ``(N, 4, 4)`` ground-truth camera-to-world poses of the same frames (metres).
        align, n_to_align: as :func:`mfg_lightning.metrics.align_trajectory`.
    """
    from mfg_lightning.metrics import align_trajectory

    return curves_from_alignment(align_trajectory(pred, target, align, n_to_align))


def curves_from_alignment(
    aligned: Alignment,
    frames: Tensor | None = None,
    reference: Tensor | None = None,
    segments: tuple[Tensor, Tensor, Tensor] | None = None,
) -> TrajectoryCurves:
    """The curves of :class:`TrajectoryCurves` of an already aligned estimate.

    Args:
        aligned: the alignment of the (matched) estimate.
        frames: ``(M,)`` the ground-truth frame of each aligned pose (poses matched to a
            ground truth with more frames); None: the poses are every frame.
        reference: ``(N, 4, 4)`` the whole ground truth (with ``frames``): the distance
            travelled is measured along it.
        segments: the KITTI segment errors ``(t_err, r_err, length)`` already computed
            (:func:`mfg_lightning.metrics.kitti_segment_errors`); None: computed here.
    """
    from mfg_lightning.metrics import ate_traj_errors, kitti_drift_by_length, kitti_segment_errors

    gt = aligned.target[:, :3, 3]
    path = gt if frames is None or reference is None else reference[:, :3, 3].to(gt)
    steps = (path[1:] - path[:-1]).norm(dim=-1)
    distance = np.concatenate([[0.0], steps.cumsum(0).cpu().numpy()])
    if frames is not None and reference is not None:
        distance = distance[frames.cpu().numpy()]
    if segments is None:
        segments = kitti_segment_errors(
            aligned.pred, aligned.target, frames=frames, reference=reference
        )
    by_length = kitti_drift_by_length(*segments)
    return TrajectoryCurves(
        gt_xyz=gt.cpu().numpy(),
        pred_xyz=aligned.pred[:, :3, 3].cpu().numpy(),
        distance=distance,
        error=ate_traj_errors(aligned).cpu().numpy(),
        drift={k: (float(v["t_err"]), float(v["r_err"])) for k, v in by_length.items()},
        scale=float(aligned.scale),
    )


def _new_figure(width: float, height: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=_DPI, layout="constrained")


#: evo's ``--plot_mode`` values: the axes a trajectory is drawn on (``xyz``: in 3D).
PLOT_MODES: tuple[str, ...] = ("xz", "xy", "yx", "yz", "zx", "zy", "xyz")


def trajectory_figure(
    gt_xz: np.ndarray, methods: Mapping[str, np.ndarray], title: str = "", axes: str = "xz"
) -> Figure:
    """Every method over the ground truth, seen along ``axes`` (default the x–z plane, KITTI's
    ground plane, top-down; ``xy`` for z-up data such as TUM and EuRoC; ``xyz`` in 3D).

    Args:
        gt_xz: ``(N, len(axes))`` ground-truth positions on ``axes`` in metres.
        methods: method name → ``(N_m, len(axes))`` its positions, in colour order.
        title: the figure title.
        axes: one of :data:`PLOT_MODES`.
    """
    fig = _new_figure(6.4, 6.0)
    ax = fig.add_subplot(projection="3d" if len(axes) == 3 else None)
    ax.plot(*gt_xz.T, color=GT_COLOUR, lw=2.2, label="ground truth")
    for i, (name, xz) in enumerate(methods.items()):
        ax.plot(*xz.T, color=method_colour(i), lw=1.3, label=name)
    # Hollow and on top: a method that barely moves stays visible inside it.
    ax.plot(*gt_xz[:1].T, "o", color=GT_COLOUR, mfc="none", ms=9, mew=1.5,
            label="start", zorder=5)  # fmt: skip
    if len(axes) == 2:
        ax.set_aspect("equal", adjustable="datalim")
    else:  # equal scales on the three axes (matplotlib's 3D "equal")
        ax.set_box_aspect(np.ptp(np.concatenate([gt_xz, *methods.values()]), axis=0) + 1e-9)
        ax.set_zlabel(f"{axes[2]} (m)")
    ax.set_xlabel(f"{axes[0]} (m)")
    ax.set_ylabel(f"{axes[1]} (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title(title, fontsize="medium")
    return fig


def drift_by_length_figure(
    methods: Mapping[str, Mapping[float, tuple[float, float]]], title: str = ""
) -> Figure:
    """KITTI drift against segment length, translation (%) and rotation (deg/100 m) panels.

    Args:
        methods: method name → ``{segment length (m): (t_err %, r_err deg/100 m)}``.
        title: the figure title.
    """
    from mfg_lightning.metrics.drift import KITTI_SEGMENT_LENGTHS as KITTI_LENGTHS

    fig = _new_figure(9.0, 3.6)
    axes = fig.subplots(1, 2)
    empty = True
    for i, (name, drift) in enumerate(methods.items()):
        if not drift:
            continue
        empty = False
        lengths = sorted(drift)
        for ax, part in zip(axes, (0, 1), strict=True):
            ax.plot(lengths, [drift[x][part] for x in lengths], "o-", color=method_colour(i),
                    label=name)  # fmt: skip
    for ax, label in zip(
        axes, ("translation error (%)", "rotation error (deg/100 m)"), strict=True
    ):
        ax.set_xlabel("segment length (m)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.set_xticks(KITTI_LENGTHS)
        ax.set_xlim(KITTI_LENGTHS[0] - 50, KITTI_LENGTHS[-1] + 50)
        ax.set_ylim(bottom=0)
        if empty:
            ax.set_yticks([])
            ax.text(0.5, 0.5, "no complete 100 m segment", ha="center", va="center",
                    transform=ax.transAxes)  # fmt: skip
    if not empty:
        axes[1].legend(loc="best", fontsize="small")
    fig.suptitle(title, fontsize="medium")
    return fig


def error_along_trajectory_figure(
    methods: Mapping[str, tuple[np.ndarray, np.ndarray]], title: str = ""
) -> Figure:
    """Per-pose position error against the distance travelled, one line per method.

    Args:
        methods: method name → ``(distance (N,), error (N,))``, both in metres.
        title: the figure title.
    """
    fig = _new_figure(8.0, 3.6)
    ax = fig.add_subplot()
    for i, (name, (distance, error)) in enumerate(methods.items()):
        ax.plot(distance, error, color=method_colour(i), lw=1.2, label=name)
    ax.set_xlabel("distance travelled (m)")
    ax.set_ylabel("position error (m)")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title(title, fontsize="medium")
    return fig


#: The figures of :func:`sequence_figures`, in their order.
SEQUENCE_FIGURES = ("trajectory", "drift", "error")


def sequence_figures(
    sequence: str,
    curves: Mapping[str, TrajectoryCurves],
    align: str = "none",
    kinds: Sequence[str] = SEQUENCE_FIGURES,
) -> dict[str, Figure]:
    """The figures of one sequence: ``trajectory``, ``drift`` and ``error``.

    What ``evaluate`` writes, and what training logs at each validation
    (:class:`mfg_lightning.run.figures.TensorBoardFigures`).

    Args:
        sequence: its name, for the titles.
        curves: method name → its :class:`TrajectoryCurves` on this sequence (colour order).
        align: the alignment used, for the titles (``origin``: the first poses made equal).
        kinds: the figures to draw, of :data:`SEQUENCE_FIGURES`.
    """
    if not curves:
        raise ValueError(f"no method to draw for sequence {sequence}")
    unknown = set(kinds) - set(SEQUENCE_FIGURES)
    if unknown:
        raise ValueError(f"unknown sequence figures {sorted(unknown)}: use {SEQUENCE_FIGURES}")
    aligned = "not aligned" if align == "none" else f"{align}-aligned"
    first = next(iter(curves.values()))
    draw = {
        "trajectory": lambda: trajectory_figure(
            first.gt_xyz[:, [0, 2]],
            {name: c.pred_xyz[:, [0, 2]] for name, c in curves.items()},
            f"sequence {sequence}: top-down (x–z), {aligned}",
        ),
        "drift": lambda: drift_by_length_figure(
            {name: c.drift for name, c in curves.items()},
            f"sequence {sequence}: KITTI drift per segment length, {aligned}",
        ),
        "error": lambda: error_along_trajectory_figure(
            {name: (c.distance, c.error) for name, c in curves.items()},
            f"sequence {sequence}: position error along the trajectory, {aligned}",
        ),
    }
    return {kind: draw[kind]() for kind in SEQUENCE_FIGURES if kind in kinds}


def save_figures(figures: Mapping[str, Figure], directory: str | Path, prefix: str) -> list[Path]:
    """Write each figure as ``<directory>/<kind>_<prefix>.png`` (atomically).

    Args:
        figures: kind (e.g. ``"trajectory"``) → figure, as :func:`sequence_figures` returns.
        directory: where to write.
        prefix: the part after the kind, e.g. the sequence name.

    Returns:
        The paths written, in the order of ``figures``.
    """
    from mfg_lightning.core.atomic import atomic_write_bytes

    paths = []
    for kind, fig in figures.items():
        path = Path(directory) / f"{kind}_{prefix}.png"
        atomic_write_bytes(path, figure_png(fig))
        paths.append(path)
    return paths


def log_figures(experiment: object, figures: Mapping[str, Figure], tag: str, step: int = 0) -> None:
    """Add each figure to a TensorBoard ``SummaryWriter`` as image ``<tag>/<kind>``."""
    for kind, fig in figures.items():
        experiment.add_image(f"{tag}/{kind}", figure_rgb(fig), step, dataformats="HWC")


def write_trajectory_figures(
    sequences: Mapping[str, tuple[Tensor, Tensor]],
    directory: str | Path,
    experiment: object | None = None,
    method: str = "MFG",
    tag: str = "test",
    align: str = "none",
) -> list[Path]:
    """The figures of :func:`sequence_figures` for one method's predicted trajectories, as PNG
    files and (given a TensorBoard ``SummaryWriter``) images ``<tag>/<seq>/<kind>``.

    Every figure is drawn before the first file is written.

    Args:
        sequences: sequence → ``(pred, gt)``, ``(N, 4, 4)`` camera-to-world poses each (metres).
        directory: where the PNGs go (``<kind>_<seq>.png``).
        experiment: a ``SummaryWriter`` (e.g. ``TensorBoardLogger.experiment``), or None.
        method: the legend's name for the predictions.
        tag: TensorBoard tag prefix.
        align: the alignment of the predictions before they are drawn
            (:func:`mfg_lightning.metrics.align_trajectory`; ``none``: as they are), named in
            the titles.

    Returns:
        The PNG paths written.
    """
    figures = {
        seq: sequence_figures(seq, {method: trajectory_curves(pred, gt, align)}, align)
        for seq, (pred, gt) in sequences.items()
    }
    paths = []
    for seq, figs in figures.items():
        paths += save_figures(figs, directory, seq)
        if experiment is not None:
            log_figures(experiment, figs, f"{tag}/{seq}")
    return paths


def top_k_figure(
    results: Mapping[float, Mapping[str, float | None]], sequences: list[str]
) -> Figure:
    """ATE against k % (log axis), one line per sequence and a dashed one over all: the paper's
    supplementary Figure 4.

    Args:
        results: k (fraction of hidden units kept) → the test metrics of that k
            (``test/<seq>/ate``, ``test/<seq>/ate_std``, ``test/ate``, ``test/ate_std``; metres).
        sequences: the test sequences, one line each.
    """
    fig = _new_figure(5.5, 3.5)
    ax = fig.add_subplot()
    ks = sorted(results)
    for s in [*sequences, None]:
        key = f"test/{s}/ate" if s else "test/ate"
        y = [results[k].get(key) for k in ks]
        if all(v is None for v in y):
            continue
        e = [results[k].get(f"{key}_std") or 0.0 for k in ks]
        y = [float("nan") if v is None else v for v in y]
        ax.errorbar(
            [100 * k for k in ks], y, yerr=e, marker="o", capsize=3,
            label=f"sequence {s}" if s else "all", linestyle="-" if s else "--",
        )  # fmt: skip
    ax.set_xscale("log")
    ax.set_xlabel("hidden units kept, k (%)")
    ax.set_ylabel("ATE over 5-frame snippets (m)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return fig


# --------------------------------------------------------------------------------------------
# Generic panels (mfg_lightning.reproduce's figures)
# --------------------------------------------------------------------------------------------

#: One line of a :func:`line_figure` panel: label → (x values, y values); None y: not drawn.
#: ``name → (x, y)``, or ``(x, y, y error)``: an error bar of ± the error at each point (None:
#: none there), e.g. the seeds' standard deviation.
Lines = Mapping[
    str,
    tuple[Sequence[float], Sequence[float | None]]
    | tuple[Sequence[float], Sequence[float | None], Sequence[float | None]],
]


def line_figure(
    panels: Sequence[tuple[str, Lines]],
    x_label: str,
    title: str = "",
    log_x: bool = False,
    log_y: bool = False,
) -> Figure:
    """Side-by-side panels of lines with markers, one colour per label (the same in every panel).

    Args:
        panels: ``(y label, lines)`` per panel.
        x_label: the shared x axis label.
        title: the figure's title.
        log_x, log_y: logarithmic axes.
    """
    from matplotlib.ticker import EngFormatter, FixedLocator, FuncFormatter, NullFormatter

    # many lines: the legend goes beside the panels, where it hides no curve
    many = len({n for _, lines in panels for n in lines}) > 4
    fig = _new_figure(4.2 * max(len(panels), 1) + (2.6 if many else 0.0), 3.4)
    for ax, lines, index in _side_by_side(fig, panels, log_y):
        xs: set[float] = set()
        for name, (x, y, *err) in lines.items():
            colour = method_colour(index(name))
            ax.plot(x, _nan_for_none(y), marker="o", color=colour, label=name)
            if err:
                ax.errorbar(x, _nan_for_none(y), yerr=[0.0 if e is None else float(e)
                            for e in err[0]], fmt="none", ecolor=colour, capsize=4)  # fmt: skip
            xs.update(float(v) for v in x)
        ax.set_xlabel(x_label)
        if log_x:
            ax.set_xscale("log")
            if 0 < len(xs) <= 8:
                # ticks at the measured x only: a decade's default labels (3×10³ 4×10³ …) run
                # into each other on a short axis
                ax.xaxis.set_major_locator(FixedLocator(sorted(xs)))
                ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:,.0f}"))
                ax.xaxis.set_minor_formatter(NullFormatter())
        else:
            # 20k rather than 20000: long tick labels run into each other
            ax.xaxis.set_major_formatter(EngFormatter(sep=""))
        ax.grid(True, which="both", alpha=0.3)
    if many and fig.axes:
        first = fig.axes[0]
        handles, labels = first.get_legend_handles_labels()
        if first.get_legend() is not None:
            first.get_legend().remove()
        fig.legend(handles, labels, fontsize="small", loc="outside right upper")
    if title:
        fig.suptitle(title)
    return fig


#: One group of curves: its members' ``(x, y)`` (y None: a gap), drawn in one colour.
CurveGroup = Sequence[tuple[Sequence[float], Sequence[float | None]]]


def curve_groups_figure(
    panels: Sequence[tuple[str, Mapping[str, CurveGroup]]],
    x_label: str,
    y_label: str,
    title: str = "",
    log_y: bool = False,
    columns: int = 2,
) -> Figure:
    """Panels in a grid, each with groups of curves: one colour and one legend entry per group
    (its member count when several, e.g. the seeds of one setting), the colours counted within
    a panel, so that no two groups of a panel share one (``line_figure`` gives every line of
    every panel its own, which repeat after ten).

    Args:
        panels: ``(panel title, {group label: its curves})`` per panel.
        x_label, y_label: the shared axis labels.
        title: the figure's title.
        log_y: a logarithmic y axis.
        columns: panels per row.
    """
    from matplotlib.ticker import EngFormatter

    cols = max(1, min(columns, len(panels)))
    rows = max(1, -(-len(panels) // cols))
    fig = _new_figure(5.0 * cols, 3.4 * rows)
    axes = fig.subplots(rows, cols, squeeze=False, sharex=True, sharey=True)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    for ax, (panel, groups) in zip(axes.flat, panels, strict=False):
        for index, (label, curves) in enumerate(groups.items()):
            colour = method_colour(index)
            name = f"{label} ({len(curves)})" if len(curves) > 1 else label
            for member, (x, y) in enumerate(curves):
                ax.plot(x, _nan_for_none(y), marker="o", ms=3, lw=1.2, color=colour,
                        label=name if member == 0 else None)  # fmt: skip
        ax.set_title(panel, fontsize="medium")
        if log_y:
            ax.set_yscale("log")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))
        ax.grid(True, which="both", alpha=0.3)
        if groups:
            ax.legend(fontsize="x-small")
    for ax in axes[-1, :]:
        ax.set_xlabel(x_label)
    for ax in axes[:, 0]:
        ax.set_ylabel(y_label)
    if title:
        fig.suptitle(title)
    return fig


def _nan_for_none(values: Sequence[float | None]) -> list[float]:
    """Floats to plot: NaN (a gap) where a value is None or not finite."""
    return [float("nan") if finite_or_none(v) is None else float(v) for v in values]


def _side_by_side(
    fig: Figure, panels: Sequence[tuple[str, Mapping[str, Any]]], log_y: bool
) -> Iterator[tuple[Any, Mapping[str, Any], Callable[[str], int]]]:
    """One axis per ``(y label, series)`` panel, side by side: yields the axis, its series and
    the index of a series name among all panels' (its colour and place, the same in every
    panel); the first panel gets the legend once the caller has drawn it."""
    names = list(dict.fromkeys(n for _, series in panels for n in series))
    for i, (y_label, series) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        ax.set_ylabel(y_label)
        if log_y:
            ax.set_yscale("log")
        yield ax, series, names.index
        if i == 0 and series:
            ax.legend(fontsize="small")


def bar_figure(
    panels: Sequence[tuple[str, Mapping[str, Sequence[float | None]]]],
    categories: Sequence[str],
    title: str = "",
    log_y: bool = False,
    references: Sequence[tuple[str, float] | None] | None = None,
) -> Figure:
    """Side-by-side panels of grouped bars: per panel a y label and, per series (one colour
    each, the same in every panel), one value per category (None: no bar). ``references``: per
    panel, a ``(label, value)`` drawn as a dashed horizontal line (None: none)."""
    fig = _new_figure(max(4.2 * len(panels), 1.1 * len(categories) * len(panels)), 3.8)
    n = max(len({k for _, series in panels for k in series}), 1)
    x = np.arange(len(categories))
    width = 0.8 / n
    refs = list(references or [None] * len(panels))
    for p, (ax, series, index) in enumerate(_side_by_side(fig, panels, log_y)):
        if refs[p] is not None:
            label, value = refs[p]
            ax.axhline(value, color="black", linestyle="--", linewidth=1.0, label=label)
        for name, values in series.items():
            j = index(name)
            ax.bar(x + (j - (n - 1) / 2) * width, _nan_for_none(values), width, label=name,
                   color=method_colour(j))  # fmt: skip
        ax.set_xticks(x, list(categories), rotation=30, ha="right", fontsize="small")
        ax.grid(True, axis="y", alpha=0.3)
    if title:
        fig.suptitle(title)
    return fig
