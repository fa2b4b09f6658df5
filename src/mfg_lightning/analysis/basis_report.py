"""The figures and files of ``python -m mfg_lightning.analyze_basis``: the entry point builds the
module and the dataset from the checkpoint and calls :func:`analyze`, which computes with
:mod:`mfg_lightning.analysis.basis` and draws here.

Files written into ``out_dir``, each atomically:

* ``basis_selectivity.csv``: the ``n_units`` units of largest norm, in decreasing order:
  ``unit, norm, tx, ty, tz, wx, wy, wz`` (supplementary Figures 6 and 8);
* ``basis_translational.png`` / ``basis_rotational.png``: their basis fields in the Middlebury
  flow colours, each field normalised by its own largest magnitude (Figures 5 and 7);
* ``selectivity_3d.png``: preferred translations and rotations as 3D scatters;
* ``examples.png``: for ``n_examples`` test inputs (one column pair each), the paper's Figure 2
  layout: RGB and input flow, the hidden activation heat map, ground-truth and predicted
  translational / rotational fields, then the ``top_units`` most active units' contributions
  (activation × basis field);
* population sparsity over the test split, measured on the encoder's activations *before*
  top-k (a unit is active when its activation is > 0): ``active_units_per_input.csv`` (one row
  per input) and ``active_units_histogram.png``; ``unit_firing.csv`` (one row per unit: how often
  it fires, its mean activation, its norm rank) and ``unit_firing.png``;
* ``summary.json``: the model, the intrinsics used, the statistics above and the file list.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from mfg_lightning.analysis.basis import (
    SELECTIVITY_COLUMNS,
    PopulationStats,
    decoder_norms,
    population_statistics,
    selectivity_rows,
    unit_fields,
)
from mfg_lightning.core import geometry
from mfg_lightning.core.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.core.tables import Column, Table
from mfg_lightning.data.sample import FLOW, FLOW_VALID, model_inputs
from mfg_lightning.pictures.colours import activation_map, flow_to_rgb, scalar_to_rgb
from mfg_lightning.pictures.plots import figure_png
from mfg_lightning.run.checkpoints import CheckpointSizeError

if TYPE_CHECKING:
    import lightning as L
    from matplotlib.figure import Figure

    from mfg_lightning.models.mfg import MFG
    from mfg_lightning.models.mfg_module import MFGLitModule

log = logging.getLogger("mfg_lightning.analysis.basis")


def basis_grid_figure(
    fields: Tensor, labels: Sequence[str], title: str, columns: int = 10
) -> Figure:
    """Basis fields in flow colours, a tile each, row by row (Figures 5 and 7).

    Args:
        fields: ``(U, 2, H, W)`` pixels; each tile is normalised by its own largest magnitude
            (the fields' norms differ by orders of magnitude; the grid shows their patterns).
        labels: a caption per tile (e.g. the unit index).
    """
    from matplotlib.figure import Figure

    n = len(fields)
    columns = max(1, min(columns, n))
    rows = max(1, math.ceil(n / columns))
    height, width = fields.shape[-2:] if n else (1, 1)
    tile_w = 1.5
    tile_h = tile_w * height / width + 0.22  # room for the caption
    fig = Figure(figsize=(columns * tile_w, rows * tile_h + 0.4), dpi=110)
    axes = fig.subplots(rows, columns, squeeze=False)
    for i, ax in enumerate(axes.flat):
        ax.set_axis_off()
        if i < n:
            ax.imshow(flow_to_rgb(fields[i]), interpolation="nearest")
            ax.set_title(labels[i], fontsize=6, pad=2)
    fig.suptitle(title, fontsize="medium")
    top = 1 - 0.4 / fig.get_figheight()
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=top, wspace=0.05, hspace=0.3)
    return fig


def selectivity_figure(rows: Sequence[dict[str, float]]) -> Figure:
    """Preferred translations (m) and rotations (rad) of the listed units as 3D scatters,
    coloured by norm rank (Figures 6 and 8 drawn instead of tabulated)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4.6), dpi=110)
    rank = np.arange(len(rows))
    for i, (keys, name, unit) in enumerate(
        ((("tx", "ty", "tz"), "translation", "m"), (("wx", "wy", "wz"), "rotation", "rad"))
    ):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        pts = np.array([[r[k] for k in keys] for r in rows], dtype=np.float64).reshape(-1, 3)
        sc = ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=rank, cmap="viridis_r", s=14)
        ax.scatter([0], [0], [0], marker="+", c="k", s=40)
        for axis, k in zip("xyz", keys, strict=True):
            getattr(ax, f"set_{axis}label")(f"{k} ({unit})", fontsize=8)
        ax.tick_params(labelsize=6)
        ax.set_title(f"preferred {name} per unit (activation 1)", fontsize=9)
        if i == 1:
            cb = fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.12)
            cb.set_label("rank by decoder norm", fontsize=8)
    return fig


@torch.no_grad()
def examples_figure(net: MFG, samples: Sequence[dict[str, Any]], top_units: int = 5) -> Figure:
    """Test inputs in the layout of the supplementary Figure 2, a pair of columns each.

    Rows: the RGB frame (or the inverse depth, or blank) and the input flow; the hidden
    activation heat map (brighter: more active); the ground-truth translational (unit depth) and
    rotational fields; the predicted ones; then the ``top_units`` most active units, each as its
    activation times its translational | rotational basis field. Ground truth and prediction
    of a field type share one colour normalisation; unit rows are normalised per tile.
    """
    from matplotlib.figure import Figure

    device = net.decoder_t.weight.device
    n = len(samples)
    height, width = net.height, net.width
    n_rows = 4 + top_units
    col_w = 1.6
    row_h = col_w * height / width + 0.3
    fig = Figure(figsize=(2 * n * col_w, n_rows * row_h), dpi=110)
    grid = fig.add_gridspec(
        n_rows, 2 * n, wspace=0.06, hspace=0.45, left=0.01, right=0.99, top=0.97, bottom=0.01
    )
    for c, sample in enumerate(samples):
        flow = model_inputs({k: sample[k][None] for k in (FLOW, FLOW_VALID)}).flow
        hidden, _ = net.encode(flow.to(device))
        v_t, v_w = net.decode(hidden)
        K = sample["intrinsics"][None].float()
        t, w = geometry.pose_to_motion(sample["pose"][None].double())
        gt_t = geometry.translational_field(t.float(), K, height, width)
        gt_w = geometry.rotational_field(w.float(), K, height, width)
        left, right = 2 * c, 2 * c + 1

        def panel(row: int, col: int, image: np.ndarray, title: str, span: int = 1) -> None:
            ax = fig.add_subplot(grid[row, col : col + span])
            ax.imshow(image, interpolation="nearest", aspect="auto")
            ax.set_title(title, fontsize=6, pad=2)
            ax.set_axis_off()

        if "rgb" in sample:
            first = sample["rgb"].permute(1, 2, 0).cpu().numpy().astype(np.uint8)
        elif "depth" in sample:
            first = scalar_to_rgb(1.0 / sample["depth"].clamp_min(1e-3))
        else:
            first = np.zeros((height, width, 3), dtype=np.uint8)
        panel(0, left, first, str(sample.get("sample_id", f"input {c}"))[-24:])
        panel(0, right, flow_to_rgb(flow[0]), "input flow")
        panel(1, left, activation_map(hidden[0]), "hidden activations", span=2)
        # ground truth and prediction share a normalisation per field type: same colour, same
        # velocity
        norm_t = max(float(gt_t[0].norm(dim=0).max()), float(v_t[0].norm(dim=0).max()))
        norm_w = max(float(gt_w[0].norm(dim=0).max()), float(v_w[0].norm(dim=0).max()))
        panel(2, left, flow_to_rgb(gt_t[0], norm_t), "GT v_t (ρ = 1)")
        panel(2, right, flow_to_rgb(gt_w[0], norm_w), "GT v_ω")
        panel(3, left, flow_to_rgb(v_t[0], norm_t), "predicted v_t")
        panel(3, right, flow_to_rgb(v_w[0], norm_w), "predicted v_ω")
        k = min(top_units, net.hidden_units)
        values, idx = hidden[0].topk(k)
        f_t, f_w = unit_fields(net, idx.cpu())
        for r, (a, j) in enumerate(zip(values.tolist(), idx.tolist(), strict=True)):
            panel(4 + r, left, flow_to_rgb(a * f_t[r]), f"unit {j} a={a:.3g} v_t")
            panel(4 + r, right, flow_to_rgb(a * f_w[r]), f"unit {j} v_ω")
    return fig


def active_units_figure(stats: PopulationStats) -> Figure:
    """Histogram of the number of active units per test input, with its mean and median."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 3.5), dpi=110)
    ax = fig.subplots()
    a = stats.active_per_input.numpy()
    if a.size:
        bins = np.arange(a.min(), a.max() + 2) - 0.5 if a.max() - a.min() < 60 else 40
        ax.hist(a, bins=bins, color="tab:blue", alpha=0.8)
        ax.axvline(float(a.mean()), color="k", linestyle="--", label=f"mean {a.mean():.1f}")
        median = float(np.median(a))
        ax.axvline(median, color="tab:red", linestyle=":", label=f"median {median:g}")
        ax.legend(fontsize="small")
    ax.set_xlabel(f"active hidden units per input (of {stats.hidden_units})")
    ax.set_ylabel("test inputs")
    ax.set_title(f"population sparsity over {stats.n_inputs} test inputs", fontsize="medium")
    fig.tight_layout()
    return fig


def firing_figure(stats: PopulationStats, norms: Tensor) -> Figure:
    """How often each unit fires: sorted (rank-frequency) and against its decoder norm."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.6), dpi=110)
    ax_rank, ax_norm = fig.subplots(1, 2)
    rates = stats.firing_rates.numpy()
    ax_rank.plot(np.arange(1, len(rates) + 1), np.sort(rates)[::-1], marker=".", markersize=3)
    ax_rank.set_xlabel("unit, by firing rate")
    ax_rank.set_ylabel("fraction of test inputs on which it fires")
    ax_rank.set_ylim(-0.02, 1.02)
    ax_rank.grid(alpha=0.3)
    ax_norm.scatter(norms.numpy(), rates, s=8, alpha=0.7)
    ax_norm.set_xlabel("decoder weight norm")
    ax_norm.set_ylabel("firing rate")
    ax_norm.set_ylim(-0.02, 1.02)
    ax_norm.grid(alpha=0.3)
    fig.suptitle(
        f"unit firing over {stats.n_inputs} test inputs "
        f"({int((stats.firing_counts == 0).sum())} of {stats.hidden_units} never fire)",
        fontsize="medium",
    )
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------------
# The analysis
# --------------------------------------------------------------------------------------------


def _csv_text(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    return Table([Column(h) for h in header], [list(r) for r in rows]).csv()


def example_indices(n_samples: int, n_examples: int) -> list[int]:
    """``n_examples`` indices evenly spaced over ``0 … n_samples − 1`` (distinct, sorted)."""
    if n_samples <= 0 or n_examples <= 0:
        return []
    return sorted(set(np.linspace(0, n_samples - 1, n_examples).round().astype(int).tolist()))


def analyze(
    module: MFGLitModule,
    datamodule: L.LightningDataModule,
    out_dir: str | Path,
    n_units: int = 100,
    n_examples: int = 4,
    top_units: int = 5,
    max_test_batches: int | None = None,
    device: str = "cpu",
    ckpt_path: str | None = None,
) -> dict[str, Any]:
    """Run the whole analysis on the test split of ``datamodule`` and write every file.

    Everything is computed first; the files are written at the end, each atomically.

    Returns:
        The summary (also written as ``summary.json``).
    """
    net = module.net.eval().to(device)
    out = Path(out_dir)
    datamodule.setup("test")
    dataset = datamodule.dataset("test") if hasattr(datamodule, "dataset") else None
    loader = datamodule.test_dataloader()
    first = dataset[0] if dataset is not None else next(b for b in loader if b is not None)
    intrinsics = first["intrinsics"].reshape(-1, 4)[0].float()
    if tuple(first["flow"].shape[-2:]) != (net.height, net.width):
        raise CheckpointSizeError(
            f"the test inputs are {tuple(first['flow'].shape[-2:])} but the MFG of "
            f"{ckpt_path} takes {net.height}×{net.width}"
        )
    if n_units > net.hidden_units:
        log.info("n_units=%d > %d hidden units: listing all", n_units, net.hidden_units)
    n_listed = min(n_units, net.hidden_units)

    rows = selectivity_rows(net, intrinsics, n_listed)
    units = [r["unit"] for r in rows]
    f_t, f_w = unit_fields(net, units)
    norms = decoder_norms(net)
    rank = torch.empty(net.hidden_units, dtype=torch.long)
    rank[torch.argsort(norms, descending=True, stable=True)] = torch.arange(net.hidden_units)
    stats = population_statistics(net, loader, max_test_batches, device)
    samples = [dataset[i] for i in example_indices(len(dataset), n_examples)] if dataset else []

    labels = [f"#{i} unit {u}" for i, u in enumerate(units)]
    figures = {
        "basis_translational.png": basis_grid_figure(
            f_t, labels, f"translational basis fields of the {n_listed} units of largest norm"
        ),
        "basis_rotational.png": basis_grid_figure(
            f_w, labels, f"rotational basis fields of the {n_listed} units of largest norm"
        ),
        "selectivity_3d.png": selectivity_figure(rows),
        "active_units_histogram.png": active_units_figure(stats),
        "unit_firing.png": firing_figure(stats, norms),
    }
    if samples:
        figures["examples.png"] = examples_figure(net, samples, top_units)
    rates, means = stats.firing_rates, stats.mean_activations
    texts = {
        "basis_selectivity.csv": _csv_text(
            SELECTIVITY_COLUMNS, [[r[c] for c in SELECTIVITY_COLUMNS] for r in rows]
        ),
        "unit_firing.csv": _csv_text(
            ("unit", "norm_rank", "norm", "firing_rate", "mean_activation"),
            [
                [j, int(rank[j]), float(norms[j]), float(rates[j]), float(means[j])]
                for j in range(net.hidden_units)
            ],
        ),
        "active_units_per_input.csv": _csv_text(
            ("sample_id", "active_units"),
            list(zip(stats.sample_ids, stats.active_per_input.tolist(), strict=True)),
        ),
    }
    summary = {
        "ckpt_path": None if ckpt_path is None else str(ckpt_path),
        "model": {
            "hidden_units": net.hidden_units,
            "height": net.height,
            "width": net.width,
            "top_k": module.top_k,
        },
        "intrinsics": dict(zip(("fx", "fy", "cx", "cy"), intrinsics.tolist(), strict=True)),
        "n_units_listed": n_listed,
        "preferred_motion_convention": "camera's own motion, m and rad per frame at activation 1",
        "population": stats.summary(),
        "examples": [str(s.get("sample_id", "")) for s in samples],
        "files": sorted([*texts, *figures, "summary.json"]),
    }
    pngs = {name: figure_png(fig) for name, fig in figures.items()}
    for name, text in texts.items():
        atomic_write_text(out / name, text)
    for name, data in pngs.items():
        atomic_write_bytes(out / name, data)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
