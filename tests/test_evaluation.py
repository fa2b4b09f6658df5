"""TrajectoryEvaluator: per-sample predictions → snippet ATE, RPE, drift, whole-trajectory ATE,
per sequence and pooled, through the metric classes."""

from __future__ import annotations

import math

import pytest
import torch

from mfg_lightning.core import geometry
from mfg_lightning.metrics import (
    KittiDrift,
    RelativePoseError,
    SnippetATE,
    TrajectoryATE,
    ate_traj,
    relative_pose_error,
    snippet_ate,
)
from mfg_lightning.metrics.evaluator import TrajectoryEvaluator
from mfg_lightning.trajectory.trajectories import snippets_from_poses


def _trajectory(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    xi = torch.zeros(n - 1, 6, dtype=torch.float64)
    xi[:, 2] = 0.8 + 0.1 * torch.rand(n - 1, generator=gen, dtype=torch.float64)
    xi[:, 4] = 0.02 * torch.randn(n - 1, generator=gen, dtype=torch.float64)
    return geometry.trajectory_from_motions(geometry.se3_exp(xi))


def _records(traj: torch.Tensor, offsets=(1,), noise: float = 0.0, seed: int = 0):
    """(frames, targets, pred, gt) of every (k, k + o) pair of a trajectory."""
    gen = torch.Generator().manual_seed(seed)
    n = traj.shape[0]
    pairs = [(k, k + o) for k in range(n) for o in offsets if 0 <= k + o < n]
    src = torch.tensor([a for a, _ in pairs])
    tgt = torch.tensor([b for _, b in pairs])
    gt = geometry.relative_pose(traj[src], traj[tgt])
    xi = noise * torch.randn(len(pairs), 6, generator=gen, dtype=torch.float64)
    pred = gt @ geometry.se3_exp(xi)
    return src, tgt, pred, gt


def test_perfect_predictions_score_zero() -> None:
    traj = _trajectory(30, 0)
    ev = TrajectoryEvaluator()
    src, tgt, pred, gt = _records(traj)
    ev.update(["s"] * len(src), src, tgt, pred, gt)
    m = ev.compute().metrics
    for key in ("ate", "ate_rmse", "rpe_trans", "s/ate"):
        assert m[key] == pytest.approx(0.0, abs=1e-9), key
    # arccos((trace − 1) / 2) resolves angles to ~1e-8 rad in float64
    assert m["rpe_rot"] == pytest.approx(0.0, abs=1e-7)
    # 30 frames: 29 motions, 26 five-frame snippets; too short for drift (no 100 m segment).
    assert math.isnan(m["drift_t_err"])


def test_matches_the_metrics_on_the_composed_trajectory() -> None:
    """Frame-by-frame snippets and RPE equal the metrics of the composed predicted trajectory."""
    traj = _trajectory(40, 1)
    src, tgt, pred, gt = _records(traj, noise=0.01)
    ev = TrajectoryEvaluator()
    ev.update(["09"] * len(src), src, tgt, pred, gt)
    res = ev.compute()
    pred_traj = geometry.trajectory_from_motions(pred)
    ate = snippet_ate(snippets_from_poses(pred_traj, 5), snippets_from_poses(traj, 5))
    rpe = relative_pose_error(pred_traj, traj)
    assert res.metrics["ate"] == pytest.approx(float(ate["ate"]), rel=1e-9)
    assert res.metrics["09/ate_std"] == pytest.approx(float(ate["ate_std"]), rel=1e-9)
    assert res.metrics["rpe_trans"] == pytest.approx(float(rpe["trans"]), rel=1e-9)
    assert res.metrics["rpe_rot"] == pytest.approx(float(rpe["rot"]), rel=1e-6)
    torch.testing.assert_close(res.sequences["09"].pred, pred_traj)
    assert res.sequences["09"].frames.tolist() == list(range(40))


def test_batches_order_and_duplicates_do_not_change_the_result() -> None:
    trajs = {"09": _trajectory(25, 2), "10": _trajectory(18, 3)}
    whole = TrajectoryEvaluator()
    parts = TrajectoryEvaluator()
    for name, traj in trajs.items():
        src, tgt, pred, gt = _records(traj, noise=0.02, seed=len(name))
        whole.update([name] * len(src), src, tgt, pred, gt)
        perm = torch.randperm(len(src), generator=torch.Generator().manual_seed(4))
        for chunk in perm.split(4):
            parts.update([name] * len(chunk), src[chunk], tgt[chunk], pred[chunk], gt[chunk])
        # a DistributedSampler pads with repeats: seen twice, counted once
        parts.update([name] * 3, src[:3], tgt[:3], pred[:3], gt[:3])
    a, b = whole.compute().metrics, parts.compute().metrics
    assert a.keys() == b.keys()
    for key in a:
        assert a[key] == pytest.approx(b[key], nan_ok=True, rel=1e-12), key
    # Pooled over both sequences' snippets: 21 + 14.
    assert {"09/ate", "10/ate"} <= a.keys()


def test_central_frame_snippets() -> None:
    traj = _trajectory(20, 5)
    ev = TrajectoryEvaluator()
    src, tgt, pred, gt = _records(traj, offsets=(-2, -1, 1, 2))
    ev.update(["s"] * len(src), src, tgt, pred, gt)
    m = ev.compute().metrics
    assert m["ate_central"] == pytest.approx(0.0, abs=1e-9)
    # A constant scale error of the motions from the centre is removed by the ATE alignment.
    scaled = pred.clone()
    scaled[:, :3, 3] *= 1.7
    ev.reset()
    ev.update(["s"] * len(src), src, tgt, scaled, gt)
    assert ev.compute().metrics["ate_central"] == pytest.approx(0.0, abs=1e-9)


def test_gaps_split_sequences_into_runs() -> None:
    traj = _trajectory(30, 6)
    src, tgt, pred, gt = _records(traj)
    keep = src != 12  # one unreadable sample skipped
    ev = TrajectoryEvaluator()
    ev.update(["s"] * int(keep.sum()), src[keep], tgt[keep], pred[keep], gt[keep])
    res = ev.compute()
    assert res.metrics["ate"] == pytest.approx(0.0, abs=1e-9)
    # The longest run (frames 13 … 29) is kept as the sequence's trajectory.
    assert res.sequences["s"].frames.tolist() == list(range(13, 30))


def test_values_are_those_of_the_metric_classes() -> None:
    """Pooled and per-sequence values are the torchmetrics Metrics' own, fed the same whole
    sequences (in sequence order), under one name each: RPE, drift and the whole-trajectory
    ATE included."""
    trajs = {"09": _trajectory(130, 7), "10": _trajectory(60, 8)}
    ev = TrajectoryEvaluator()
    pooled = {
        "rpe": RelativePoseError(),
        "drift": KittiDrift(),
        "ate_traj": TrajectoryATE(),
        "ate": SnippetATE(),
    }
    for name, traj in trajs.items():
        src, tgt, pred, gt = _records(traj, noise=0.01, seed=int(name))
        ev.update([name] * len(src), src, tgt, pred, gt)
        pred_traj = geometry.trajectory_from_motions(pred)
        gt_traj = geometry.trajectory_from_motions(gt)
        for key, metric in pooled.items():
            if key == "ate":
                metric.update(snippets_from_poses(pred_traj, 5), snippets_from_poses(gt_traj, 5))
            else:
                metric.update(pred_traj, gt_traj)
        alone = ate_traj(pred_traj, gt_traj)
        assert ev.compute().metrics[f"{name}/ate_traj"] == pytest.approx(
            float(alone["ate_traj"]), rel=1e-12
        )
    res = ev.compute()
    assert res.samples == 129 + 59
    for metric in pooled.values():
        for key, value in metric.compute().items():
            assert res.metrics[key] == pytest.approx(float(value), rel=1e-9, nan_ok=True), key
    # 130 frames of ~0.85 m: one 100 m segment start every 10 frames, pooled over "09" only.
    assert math.isfinite(res.metrics["drift_t_err"]) and math.isnan(res.metrics["10/drift_t_err"])
    assert res.metrics["drift_t_err"] == res.metrics["09/drift_t_err"]
    # One name per quantity: the published ones only, never the metrics' earlier short names.
    assert not {"t_err", "trans", "kitti_t_err", "drift_t", "rpe_trans_err"} & res.metrics.keys()


def test_an_empty_epoch_reports_no_sample() -> None:
    res = TrajectoryEvaluator().compute()
    assert res.samples == 0 and not res.sequences
    assert math.isnan(res.metrics["ate"]) and math.isnan(res.metrics["ate_traj"])
