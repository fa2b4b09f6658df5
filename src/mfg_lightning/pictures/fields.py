"""Labelled figures of what the network sees and predicts, for TensorBoard.

* :func:`field_figure`: one row per sample, one titled column each for the input flow, the
  ground-truth and predicted translational field ``v_t`` (unit inverse depth), the ground-truth
  and predicted rotational field ``v_ω``, and the residual (with the object-motion mask outlined
  when one was extracted). Every row ends in the colour wheel; every panel states the magnitude
  its rim colour stands for, and ground truth and prediction of a field share it, so that equal
  colours are equal velocities.
* :func:`basis_figure`: one sample's hidden activations, sorted, with the top-k cut and the
  count of active units drawn; beside them, the translational and rotational fields the most
  active units contribute (the paper's Figure 3 e–i: activation × the unit's basis field).

Flow colours are those of :mod:`mfg_lightning.pictures.colours` (Middlebury). Drawn on
matplotlib ``Figure`` objects without pyplot, with text sized to stay readable when TensorBoard
scales the image down to its card (about half its width).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mfg_lightning.pictures.colours import colour_wheel, flow_to_rgb

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "FIELD_COLUMNS",
    "FieldRow",
    "basis_figure",
    "field_figure",
    "field_max",
    "flow_estimate_figure",
    "unit_colour",
]

#: The column titles of :func:`field_figure` (the residual's is the caller's).
FIELD_COLUMNS = (
    "input\nflow",
    "v_t\nground truth",
    "v_t\npredicted",
    "v_ω\nground truth",
    "v_ω\npredicted",
)

#: Font sizes (points at 100 dpi) and the panel width (inches): TensorBoard shows an image
#: scaled to its card, about 500 px wide, half these figures' width; the text is then still
#: 10-11 screen pixels high (titles on two lines so that they fit their panel).
_TITLE, _LABEL, _SUPTITLE = 16, 14, 16
_PANEL_WIDTH = 1.45
_BASIS_PANEL_WIDTH = 2.0  # two columns only: room for small magnitudes' captions
_DPI = 100


@dataclass(frozen=True)
class FieldRow:
    """The fields of one sample, ``(2, H, W)`` pixels per frame each (numpy or CPU tensors).

    Attributes:
        label: the row's name (e.g. the sample id).
        flow: the input flow.
        v_t, v_t_pred: the ground-truth and predicted translational field at ρ = 1 m⁻¹.
        v_omega, v_omega_pred: the ground-truth and predicted rotational field.
        residual: what the predicted egomotion leaves of the flow.
        mask: ``(H, W)`` bool object-motion mask outlined on the residual, or None.
    """

    label: str
    flow: np.ndarray
    v_t: np.ndarray
    v_t_pred: np.ndarray
    v_omega: np.ndarray
    v_omega_pred: np.ndarray
    residual: np.ndarray
    mask: np.ndarray | None = None


def _np(field: object) -> np.ndarray:
    detach = getattr(field, "detach", None)
    if detach is not None:  # a tensor
        field = detach().float().cpu().numpy()
    return np.nan_to_num(np.asarray(field, dtype=np.float64))


def field_max(*fields: object) -> float:
    """The largest per-pixel magnitude over ``(2, H, W)`` fields (0 for none)."""
    return max((float(np.sqrt((_np(f) ** 2).sum(0)).max()) for f in fields), default=0.0)


def _new_figure(width: float, height: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=_DPI, layout="constrained")


def _show_field(ax: Axes, field: object, max_norm: float, caption: str | None = None) -> None:
    """A field in flow colours, saturating at ``max_norm``, captioned with it."""
    ax.imshow(flow_to_rgb(_np(field), max_norm), interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_xlabel(caption if caption is not None else f"max {max_norm:.3g} px", fontsize=_LABEL,
                  labelpad=2)  # fmt: skip


def _show_wheel(ax: Axes, caption: str = "rim = max") -> None:
    ax.imshow(colour_wheel(), interpolation="bilinear")
    ax.set_axis_off()
    ax.text(0.5, -0.08, caption, transform=ax.transAxes, ha="center", va="top", fontsize=_LABEL)


def field_figure(
    rows: Sequence[FieldRow], residual_title: str = "residual", title: str = ""
) -> Figure:
    """Rows of samples, columns :data:`FIELD_COLUMNS` and the residual, a colour wheel per row.

    Each panel's caption is the magnitude (pixels per frame) shown at full saturation: the
    flow's own, one shared by ``v_t`` ground truth and prediction, one shared by ``v_ω``'s, the
    residual's own. Pixels of the object-motion mask are outlined in black on the residual.

    Args:
        rows: one sample each, drawn top to bottom.
        residual_title: the last column's title (what the residual is).
        title: the figure's title.
    """
    if not rows:
        raise ValueError("field_figure needs at least one sample")
    height, width = _np(rows[0].flow).shape[-2:]
    panel_h = _PANEL_WIDTH * height / width
    n_cols = len(FIELD_COLUMNS) + 1
    fig = _new_figure(
        _PANEL_WIDTH * (n_cols + 0.55) + 0.7,
        (panel_h + 0.45) * len(rows) + 0.75 + 0.4 * bool(title),
    )
    grid = fig.add_gridspec(len(rows), n_cols + 1, width_ratios=[1.0] * n_cols + [0.55])
    headers = (*FIELD_COLUMNS, residual_title)
    for r, row in enumerate(rows):
        axes = [fig.add_subplot(grid[r, c]) for c in range(n_cols + 1)]
        m_t = field_max(row.v_t, row.v_t_pred)
        m_w = field_max(row.v_omega, row.v_omega_pred)
        scales = (field_max(row.flow), m_t, m_t, m_w, m_w, field_max(row.residual))
        fields = (row.flow, row.v_t, row.v_t_pred, row.v_omega, row.v_omega_pred, row.residual)
        for ax, field, scale in zip(axes, fields, scales, strict=False):
            _show_field(ax, field, scale)
        if row.mask is not None and np.asarray(row.mask).any():
            axes[5].contour(np.asarray(row.mask, dtype=float), levels=[0.5], colors="black",
                            linewidths=1.0)  # fmt: skip
        axes[0].set_ylabel(row.label, fontsize=_LABEL)
        _show_wheel(axes[-1])
        if r == 0:
            for ax, header in zip(axes, headers, strict=False):
                ax.set_title(header, fontsize=_TITLE)
            axes[-1].set_title("colour key", fontsize=_TITLE)
    if title:
        fig.suptitle(title, fontsize=_SUPTITLE)
    return fig


def unit_colour(index: int) -> str:
    """The colour of the ``index``-th most active unit in :func:`basis_figure`."""
    return f"C{index % 10}"


def basis_figure(
    activations: np.ndarray,
    units: Sequence[int],
    fields_t: Sequence[object],
    fields_omega: Sequence[object],
    kept: int | None = None,
    title: str = "",
) -> Figure:
    """One sample's hidden activations sorted, and the fields of its most active units.

    Left: every unit's activation (before top-k) in decreasing order (a logarithmic rank axis),
    the most active units as coloured stems, the top-k cut (``kept`` units survive it) as a
    dashed line and the last active unit (activation > 0) as a dotted one. Right: a row per
    listed unit, its translational and rotational contribution (activation × basis field), each
    captioned with the magnitude of its rim colour.

    Args:
        activations: ``(M,)`` the sample's hidden activations before top-k.
        units: the unit indices drawn on the right, most active first.
        fields_t, fields_omega: ``(2, H, W)`` each unit's contribution, in the order of ``units``.
        kept: how many units the top-k keeps (None: no top-k, every unit is kept).
        title: the figure's title.
    """
    acts = np.nan_to_num(np.asarray(activations, dtype=np.float64).reshape(-1))
    m = acts.size
    order = np.argsort(-acts, kind="stable")
    ranked = acts[order]
    n_units = len(units)
    height, width = (_np(fields_t[0]).shape[-2:]) if n_units else (1, 2)
    panel_w = _BASIS_PANEL_WIDTH
    panel_h = panel_w * height / width
    fig = _new_figure(5.0 + 2 * panel_w + 1.2, max(4.2, (panel_h + 0.6) * n_units + 1.1))
    grid = fig.add_gridspec(max(n_units, 1), 4, width_ratios=[5.0, panel_w, panel_w, 1.0])
    ax = fig.add_subplot(grid[:, 0])
    rank = np.arange(1, m + 1)
    ax.fill_between(rank, ranked, step="mid", color="0.6", lw=0, label="all units")
    position = {int(u): int(np.nonzero(order == u)[0][0]) + 1 for u in units}
    for i, u in enumerate(units):  # named in their fields' titles, in the same colour
        x, a = position[int(u)], acts[int(u)]
        ax.vlines(x, 0, a, color=unit_colour(i), lw=4)
        ax.plot([x], [a], "o", color=unit_colour(i), ms=8)
    active = int((acts > 0).sum())
    ax.axvline(active + 0.5, color="black", ls=":", lw=1.5, label=f"active (> 0): {active} of {m}")
    if kept is not None and kept < m:
        ax.axvline(kept + 0.5, color="crimson", ls="--", lw=2,
                   label=f"top-k cut: {kept} kept ({100 * kept / m:.3g} %)")  # fmt: skip
    else:
        ax.plot([], [], " ", label="no top-k: every unit kept")
    ax.set_xscale("log")
    ax.set_xlim(0.7, m * 1.3)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("unit rank by activation", fontsize=_LABEL)
    ax.set_ylabel("activation", fontsize=_LABEL)
    ax.tick_params(labelsize=_LABEL - 1)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=_LABEL - 1, loc="upper right")
    ax.set_title("hidden activations, sorted", fontsize=_TITLE)
    for i, (u, f_t, f_w) in enumerate(zip(units, fields_t, fields_omega, strict=True)):
        for c, (field, name) in enumerate(((f_t, "v_t"), (f_w, "v_ω")), start=1):
            pax = fig.add_subplot(grid[i, c])
            _show_field(pax, field, field_max(field))
            pax.set_title(f"unit {int(u)}: {name}", fontsize=_LABEL, color=unit_colour(i))
    if n_units:
        _show_wheel(fig.add_subplot(grid[0, 3]))
    if title:
        fig.suptitle(title, fontsize=_SUPTITLE)
    return fig


#: End-point errors at or above this many pixels get the brightest colour of
#: :func:`flow_estimate_figure`'s error panel.
FLOW_ERROR_MAX = 10.0


def flow_estimate_figure(
    image0: Sequence[np.ndarray],
    image1: Sequence[np.ndarray],
    exact: Sequence[np.ndarray],
    estimated: Sequence[np.ndarray],
    labels: Sequence[str],
    title: str = "",
) -> Figure:
    """A learned flow against the exact one, a row per pair: both frames, the exact flow, the
    estimate in the same colour scale, its end-point error (magma, 0 to
    :data:`FLOW_ERROR_MAX` px; black where the exact flow is unknown) captioned with its mean.

    Args:
        image0, image1: ``(H, W, 3)`` uint8 RGB frames.
        exact, estimated: ``(2, H, W)`` flows in pixels (exact: NaN where unknown).
        labels: each row's label (the pair).
        title: the figure's title.
    """
    from matplotlib import colormaps

    if not labels:
        raise ValueError("flow_estimate_figure needs at least one pair")
    height, width = np.asarray(image0[0]).shape[:2]
    panel_w = 2.6
    panel_h = panel_w * height / width
    fig = _new_figure(
        panel_w * 5.45 + 0.7, (panel_h + 0.45) * len(labels) + 0.75 + 0.4 * bool(title)
    )
    grid = fig.add_gridspec(len(labels), 6, width_ratios=[1.0] * 5 + [0.45])
    headers = ("frame t", "frame t + offset", "exact flow", "estimated flow", "end-point error")
    for r in range(len(labels)):
        gt = np.asarray(exact[r], dtype=np.float64)
        est = np.asarray(estimated[r], dtype=np.float64)
        known = np.isfinite(gt).all(axis=0)
        scale = field_max(np.where(known, gt, 0.0))
        epe = np.where(known, np.sqrt(((est - np.nan_to_num(gt)) ** 2).sum(0)), 0.0)
        error = colormaps["magma"](np.clip(epe / FLOW_ERROR_MAX, 0, 1))[..., :3]
        error[~known] = 0
        mean = float(epe[known].mean()) if known.any() else float("nan")
        axes = [fig.add_subplot(grid[r, c]) for c in range(6)]
        for ax, image in zip(axes[:2], (image0[r], image1[r]), strict=True):
            ax.imshow(image, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
        _show_field(axes[2], np.where(known, gt, 0.0), scale)
        _show_field(axes[3], est, scale, f"same scale ({scale:.3g} px)")
        axes[4].imshow(error, interpolation="nearest")
        axes[4].set_xticks([])
        axes[4].set_yticks([])
        axes[4].set_xlabel(f"mean {mean:.2f} px (0–{FLOW_ERROR_MAX:g} px)", fontsize=_LABEL,
                           labelpad=2)  # fmt: skip
        axes[0].set_ylabel(labels[r], fontsize=_LABEL)
        _show_wheel(axes[5])
        if r == 0:
            for ax, header in zip(axes, headers, strict=False):
                ax.set_title(header, fontsize=_TITLE)
            axes[5].set_title("colour key", fontsize=_TITLE)
    if title:
        fig.suptitle(title, fontsize=_SUPTITLE)
    return fig
