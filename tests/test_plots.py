"""Trajectory figures: what they show, in metres, one colour per method in every figure."""

from __future__ import annotations

import numpy as np
import torch
from matplotlib.colors import to_hex

from mfg_lightning.pictures.plots import figure_png, figure_rgb, sequence_figures, trajectory_curves


def _circle(n: int, radius: float) -> torch.Tensor:
    """Camera-to-world poses driving round a circle in the x–z plane (about 1 m per frame)."""
    angle = torch.arange(n, dtype=torch.float64) / radius
    poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    poses[:, 0, 3] = radius * (1 - torch.cos(angle))
    poses[:, 2, 3] = radius * torch.sin(angle)
    c, s = torch.cos(angle), torch.sin(angle)
    poses[:, 0, 0], poses[:, 0, 2], poses[:, 2, 0], poses[:, 2, 2] = c, s, -s, c
    return poses


def test_figures_of_two_methods() -> None:
    gt = _circle(400, 80.0)
    scaled = gt.clone()
    scaled[:, :3, 3] *= 0.5
    curves = {
        "half scale": trajectory_curves(scaled, gt, "sim3"),
        "unaligned": trajectory_curves(scaled, gt, "none"),
    }
    assert abs(curves["half scale"].scale - 2.0) < 1e-9
    assert curves["half scale"].error.max() < 1e-9 < curves["unaligned"].error.max()
    assert set(curves["unaligned"].drift) == {100.0, 200.0, 300.0}  # a 399 m path
    figures = sequence_figures("07", curves, "sim3")
    assert set(figures) == {"trajectory", "drift", "error"}
    colours = {}
    for kind, fig in figures.items():
        for ax in fig.axes:
            assert "(m" in ax.get_xlabel() and ax.get_ylabel()
        ax = fig.axes[-1] if kind == "drift" else fig.axes[0]
        legend = ax.get_legend()
        handles = dict(zip([t.get_text() for t in legend.get_texts()], legend.legend_handles,
                           strict=True))  # fmt: skip
        for name in curves:
            colours.setdefault(name, set()).add(to_hex(handles[name].get_color()))
    assert figures["trajectory"].axes[0].get_xlabel() == "x (m)"
    assert figures["trajectory"].axes[0].get_ylabel() == "z (m)"
    # One colour per method, the same in every figure, and different methods differ.
    assert all(len(c) == 1 for c in colours.values())
    assert len({next(iter(c)) for c in colours.values()}) == len(curves)
    png = figure_png(figures["trajectory"])
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    rgb = figure_rgb(figures["drift"])
    assert rgb.dtype == np.uint8 and rgb.shape == (432, 1080, 3)
