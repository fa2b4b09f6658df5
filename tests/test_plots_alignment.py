"""Trajectory figures after an alignment (evaluate's eval.align, predict's predict.align) and of
estimates matched to some frames only (mfg-eval-poses)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mfg_lightning.metrics import align_trajectory
from mfg_lightning.pictures import plots


def _drive(n: int) -> torch.Tensor:
    poses = np.tile(np.eye(4), (n, 1, 1))
    yaw = np.cumsum(np.full(n, 0.02))
    poses[:, :3, :3] = Rotation.from_rotvec(np.stack([0 * yaw, yaw, 0 * yaw], 1)).as_matrix()
    poses[:, 0, 3] = np.cumsum(np.sin(yaw))
    poses[:, 2, 3] = np.cumsum(np.cos(yaw))
    return torch.from_numpy(poses)


def test_figures_are_drawn_aligned_and_say_so(tmp_path: Path, monkeypatch) -> None:
    gt = _drive(60)
    pred = gt.clone()
    pred[:, :3, 3] *= 0.5  # half the scale: a monocular estimate
    drawn: dict[str, dict] = {}
    monkeypatch.setattr(plots, "save_figures", lambda figs, d, seq: drawn.update({seq: figs}) or [])
    plots.write_trajectory_figures({"09": (pred, gt)}, tmp_path, align="sim3")
    figs = drawn["09"]
    assert "sim3-aligned" in figs["trajectory"].axes[0].get_title()
    assert "sim3-aligned" in figs["error"].axes[0].get_title()
    assert "sim3-aligned" in figs["drift"].get_suptitle()
    # The estimate is drawn on the ground truth once aligned.
    line = figs["trajectory"].axes[0].lines[1]
    np.testing.assert_allclose(line.get_xdata(), gt[:, 0, 3].numpy(), atol=1e-9)
    plots.write_trajectory_figures({"09": (pred, gt)}, tmp_path)
    assert "not aligned" in drawn["09"]["trajectory"].axes[0].get_title()


def test_curves_of_a_matched_estimate_measure_distance_on_the_whole_ground_truth() -> None:
    gt = _drive(50)
    frames = torch.tensor([5, 6, 7, 20, 21, 40])
    aligned = align_trajectory(gt[frames], gt[frames], "none")
    curves = plots.curves_from_alignment(aligned, frames=frames, reference=gt)
    steps = (gt[1:, :3, 3] - gt[:-1, :3, 3]).norm(dim=-1)
    dist = torch.cat([torch.zeros(1, dtype=torch.float64), steps.cumsum(0)])
    np.testing.assert_allclose(curves.distance, dist[frames].numpy())
    assert curves.error.shape == (6,) and curves.error.max() == pytest.approx(0.0, abs=1e-12)
