"""KITTI drift (Geiger et al. 2012): known values and a loop written from the devkit's algorithm."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import SHARED
from mfg_lightning.metrics import (
    KittiDrift,
    kitti_drift,
    kitti_drift_by_length,
    kitti_drift_from_segments,
    kitti_segment_errors,
)
from mfg_lightning.trajectory.pose_io import read_kitti_poses

KITTI_POSES = SHARED / "data" / "kitti_odometry" / "poses"
LENGTHS = (100, 200, 300, 400, 500, 600, 700, 800)


def _straight_line(n: int, step: float = 1.0) -> np.ndarray:
    """n frames ``step`` metres apart along z, no rotation."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = step * np.arange(n)
    return poses


def _from_motions(motions: np.ndarray) -> np.ndarray:
    poses = [np.eye(4)]
    for m in motions:
        poses.append(poses[-1] @ m)
    return np.stack(poses)


def _drive(n: int, seed: int) -> np.ndarray:
    """A car-like trajectory: about 1 m per frame forward with smooth turns, exact rotations."""
    rng = np.random.default_rng(seed)
    motions = np.tile(np.eye(4), (n - 1, 1, 1))
    yaw = 0.02 * np.sin(np.arange(n - 1) / 40.0) + rng.normal(0, 0.002, n - 1)
    rotvec = np.stack([rng.normal(0, 1e-3, n - 1), yaw, rng.normal(0, 1e-3, n - 1)], axis=1)
    motions[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    motions[:, :3, 3] = np.stack(
        [rng.normal(0, 0.02, n - 1), rng.normal(0, 0.01, n - 1), 1.0 + rng.normal(0, 0.05, n - 1)],
        axis=1,
    )
    return _from_motions(motions)


def _perturbed_estimate(gt: np.ndarray, seed: int) -> np.ndarray:
    """Compose the true motions with small errors: an estimate that drifts."""
    rng = np.random.default_rng(seed)
    motions = np.linalg.inv(gt[:-1]) @ gt[1:]
    noise = np.tile(np.eye(4), (len(motions), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 2e-3, (len(motions), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, 0.03, (len(motions), 3))
    return gt[0] @ _from_motions(motions @ noise)


def _devkit_loop(gt: np.ndarray, est: np.ndarray) -> tuple[list[float], list[float]]:
    """calcSequenceErrors of the KITTI odometry devkit, transcribed as plain loops."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[i - 1][:3, 3] - gt[i][:3, 3])))
    t_errs, r_errs = [], []
    for first in range(0, len(gt), 10):
        for length in LENGTHS:
            last = next((i for i in range(first, len(dist)) if dist[i] > dist[first] + length), -1)
            if last == -1:
                continue
            delta_gt = np.linalg.inv(gt[first]) @ gt[last]
            delta_est = np.linalg.inv(est[first]) @ est[last]
            error = np.linalg.inv(delta_est) @ delta_gt
            cos = 0.5 * (np.trace(error[:3, :3]) - 1.0)
            r_errs.append(math.acos(max(min(cos, 1.0), -1.0)) / length)
            t_errs.append(float(np.linalg.norm(error[:3, 3])) / length)
    return t_errs, r_errs


def _drift(est: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    return {
        k: v.item() for k, v in kitti_drift(torch.from_numpy(est), torch.from_numpy(gt)).items()
    }


def test_identical_trajectories_have_no_drift() -> None:
    gt = _drive(900, 0)
    result = _drift(gt, gt)
    assert result["drift_t_err"] == pytest.approx(0.0, abs=1e-9)
    # arccos resolves angles only down to ~2e-8 rad in float64: ~1e-6 deg/100 m at 100 m.
    assert result["drift_r_err"] == pytest.approx(0.0, abs=1e-5)


def test_constant_scale_error_of_a_single_segment() -> None:
    # 102 frames 1 m apart: the only complete segment is 100 m from frame 0. Its last frame is the
    # first with dist > 100, frame 101, so the true displacement is 101 m and a 0.9 scale misses
    # 10.1 m of it: t_err = 10.1 / 100 = 10.1 %.
    gt = _straight_line(102)
    est = _straight_line(102, step=0.9)
    _, _, lengths = kitti_segment_errors(torch.from_numpy(est), torch.from_numpy(gt))
    assert lengths.tolist() == [100.0]
    result = _drift(est, gt)
    assert result["drift_t_err"] == pytest.approx(10.1, abs=1e-9)
    assert result["drift_r_err"] == pytest.approx(0.0, abs=1e-5)


def test_constant_scale_error_over_many_segments() -> None:
    n, scale = 1000, 1.2
    gt = _straight_line(n)
    est = _straight_line(n, step=scale)
    # Segment (first f, length L) ends at frame f + L + 1 and exists while that is < n; each one
    # has error |1 − s| (L + 1) / L.
    per_segment = [
        abs(1 - scale) * (length + 1) / length
        for first in range(0, n, 10)
        for length in LENGTHS
        if first + length + 1 < n
    ]
    assert _drift(est, gt)["drift_t_err"] == pytest.approx(100 * np.mean(per_segment), rel=1e-12)


def test_constant_rotation_rate_error() -> None:
    # The estimate turns by α about y every frame while the truth goes straight: over the single
    # 100 m segment (101 frames) the rotation error is 101 α, i.e. 101 α / 100 rad per metre.
    alpha = 1e-3
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec([0.0, alpha, 0.0]).as_matrix()
    motion[2, 3] = 1.0
    est = _from_motions(np.tile(motion, (101, 1, 1)))
    expected = 101 * alpha / 100 * (180 / math.pi) * 100
    assert _drift(est, _straight_line(102))["drift_r_err"] == pytest.approx(expected, rel=1e-9)


def test_matches_the_devkit_loop_on_a_drifting_estimate() -> None:
    gt = _drive(700, 1)
    est = _perturbed_estimate(gt, 2)
    t_loop, r_loop = _devkit_loop(gt, est)
    t_err, r_err, _ = kitti_segment_errors(torch.from_numpy(est), torch.from_numpy(gt))
    assert len(t_loop) == t_err.numel() > 100
    np.testing.assert_allclose(t_err.numpy(), t_loop, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r_err.numpy(), r_loop, rtol=1e-6, atol=1e-10)
    result = _drift(est, gt)
    assert result["drift_t_err"] == pytest.approx(100 * np.mean(t_loop), rel=1e-9)
    assert result["drift_r_err"] == pytest.approx(np.mean(r_loop) * 180 / math.pi * 100, rel=1e-6)


def test_matches_the_devkit_loop_on_kitti_09() -> None:
    if not KITTI_POSES.is_dir():
        pytest.skip(f"{KITTI_POSES} not present")
    raw = read_kitti_poses(KITTI_POSES / "09.txt")
    gt = raw.copy()
    # The loop uses exact rotations (scipy's own projection of the 6-digit file's blocks).
    gt[:, :3, :3] = Rotation.from_matrix(raw[:, :3, :3]).as_matrix()
    est = _perturbed_estimate(gt, 3)
    t_loop, r_loop = _devkit_loop(gt, est)
    t_err, r_err, _ = kitti_segment_errors(torch.from_numpy(est), torch.from_numpy(raw))
    np.testing.assert_allclose(t_err.numpy(), t_loop, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(r_err.numpy(), r_loop, rtol=1e-5, atol=1e-9)


def test_metric_pools_segments_of_all_sequences() -> None:
    gts = [_drive(400, 4), _drive(250, 5)]
    ests = [_perturbed_estimate(g, 6 + i) for i, g in enumerate(gts)]
    per_sequence = [
        kitti_segment_errors(torch.from_numpy(e), torch.from_numpy(g))
        for e, g in zip(ests, gts, strict=True)
    ]
    t_all = torch.cat([s[0] for s in per_sequence])
    r_all = torch.cat([s[1] for s in per_sequence])
    expected = {
        "drift_t_err": 100 * t_all.mean().item(),
        "drift_r_err": r_all.mean().item() * 18000 / math.pi,
    }

    together = KittiDrift()
    for e, g in zip(ests, gts, strict=True):
        together.update(torch.from_numpy(e), torch.from_numpy(g))
    merged, other = KittiDrift(), KittiDrift()
    merged.update(torch.from_numpy(ests[0]), torch.from_numpy(gts[0]))
    other.update(torch.from_numpy(ests[1]), torch.from_numpy(gts[1]))
    merged.merge_state(other)  # the reductions a DDP sync applies
    for metric in (together, merged):
        result = metric.compute()
        assert set(result) == {"drift_t_err", "drift_r_err"}
        for key, value in expected.items():
            assert result[key].item() == pytest.approx(value, rel=1e-12)


def test_paths_shorter_than_100_m_have_undefined_drift() -> None:
    gt = _straight_line(100)  # 99 m
    assert all(math.isnan(v) for v in _drift(gt, gt).values())
    metric = KittiDrift()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torchmetrics warns about compute before update
        assert all(math.isnan(v.item()) for v in metric.compute().values())


def _in_another_similarity_frame(poses: np.ndarray, scale: float) -> np.ndarray:
    """``poses`` scaled and moved into another world frame, as a monocular method's output."""
    R = Rotation.from_rotvec([0.3, -1.2, 0.2]).as_matrix()
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ R.T + np.array([5.0, -2.0, 30.0])
    return out


def _scale_aligned_loop(gt: np.ndarray, est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """kitti-odom-eval's ``--align scale`` pose by pose: both relative to their first frame,
    estimated positions times Σ g·p / Σ p·p."""
    g = np.stack([np.linalg.inv(gt[0]) @ gt[k] for k in range(len(gt))])
    p = np.stack([np.linalg.inv(est[0]) @ est[k] for k in range(len(est))])
    num = sum(float(g[k][:3, 3] @ p[k][:3, 3]) for k in range(len(g)))
    den = sum(float(p[k][:3, 3] @ p[k][:3, 3]) for k in range(len(p)))
    for k in range(len(p)):
        p[k][:3, 3] *= num / den
    return g, p


def test_aligned_drift_matches_the_devkit_loop() -> None:
    gt = _drive(700, 1)
    est = _in_another_similarity_frame(_perturbed_estimate(gt, 2), 0.4)
    P, Q = torch.from_numpy(est), torch.from_numpy(gt)
    # sim3: evo's Umeyama alignment (an independent implementation), then the devkit's loop.
    pytest.importorskip("evo")
    from evo.core.trajectory import PosePath3D

    evo_est = PosePath3D(poses_se3=list(est))
    evo_est.align(PosePath3D(poses_se3=list(gt)), correct_scale=True)
    expected = {
        "sim3": (gt, np.stack(evo_est.poses_se3)),
        "scale": _scale_aligned_loop(gt, est),
    }
    for mode, (loop_gt, loop_est) in expected.items():
        t_loop, r_loop = _devkit_loop(loop_gt, loop_est)
        t_err, r_err, _ = kitti_segment_errors(P, Q, align=mode)
        assert len(t_loop) == t_err.numel() > 100
        np.testing.assert_allclose(t_err.numpy(), t_loop, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(r_err.numpy(), r_loop, rtol=1e-6, atol=1e-10)
        metric = KittiDrift(align=mode)
        metric.update(P, Q)
        assert metric.compute()["drift_t_err"].item() == pytest.approx(
            100 * np.mean(t_loop), rel=1e-8
        )
    # Unaligned, the 0.4 scale dominates; a rigid alignment changes no segment.
    assert (
        _drift(est, gt)["drift_t_err"] > 50 > kitti_drift(P, Q, align="sim3")["drift_t_err"].item()
    )
    for key, value in kitti_drift(P, Q, align="se3").items():
        assert value.item() == pytest.approx(_drift(est, gt)[key], rel=1e-9)


def test_drift_by_length_is_the_mean_of_each_length() -> None:
    gt = _drive(900, 3)
    est = _perturbed_estimate(gt, 4)
    t_loop, r_loop = _devkit_loop(gt, est)
    t_err, r_err, length = kitti_segment_errors(torch.from_numpy(est), torch.from_numpy(gt))
    by_length = kitti_drift_by_length(t_err, r_err, length)
    assert list(by_length) == [100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0]
    lengths = length.tolist()
    for value, result in by_length.items():
        t = [e for e, s in zip(t_loop, lengths, strict=True) if s == value]
        r = [e for e, s in zip(r_loop, lengths, strict=True) if s == value]
        assert int(result["count"]) == len(t) > 0
        assert result["drift_t_err"].item() == pytest.approx(100 * np.mean(t), rel=1e-9)
        assert result["drift_r_err"].item() == pytest.approx(np.mean(r) * 18000 / math.pi, rel=1e-6)


def test_published_names_and_the_earlier_ones() -> None:
    """``drift_t_err`` / ``drift_r_err`` (the names logged and defined in docs/protocols.md) from
    every drift function; the names before them (``"t_err"``) still read the same values."""
    gt = _drive(300, 8)
    P, Q = torch.from_numpy(_perturbed_estimate(gt, 9)), torch.from_numpy(gt)
    metric = KittiDrift()
    metric.update(P, Q)
    by_length = kitti_drift_by_length(*kitti_segment_errors(P, Q))
    for result in (kitti_drift(P, Q), metric.compute(), *by_length.values()):
        assert {"drift_t_err", "drift_r_err"} <= set(result) and "t_err" not in set(result)
        assert result["t_err"] is result["drift_t_err"] and result["r_err"] is result["drift_r_err"]
    assert tuple(metric.compute()) == KittiDrift.names
    # The per-segment helper keeps the devkit's short names (mfg-eval-poses prefixes them).
    assert kitti_drift_from_segments(*kitti_segment_errors(P, Q)[:2]).keys() == {"t_err", "r_err"}


def test_a_late_start_with_holes_is_scored_on_its_segments_as_kitti_odom_eval() -> None:
    """kitti-odom-eval's ``calc_sequence_errors`` on a result that has some frames only: the
    segments are those of the whole ground truth (first frames 0, 10, … of its path), kept when
    the result has a pose at both ends."""
    gt = _drive(700, 5)
    est = _perturbed_estimate(gt, 6)
    frames = np.r_[3:250, 262:600, 640:700]
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    have = set(frames.tolist())
    t_loop, r_loop = [], []
    for first in range(0, len(gt), 10):
        for length in LENGTHS:
            last = next((i for i in range(first, len(dist)) if dist[i] > dist[first] + length), -1)
            if last == -1 or first not in have or last not in have:
                continue
            error = np.linalg.inv(np.linalg.inv(est[first]) @ est[last]) @ (
                np.linalg.inv(gt[first]) @ gt[last]
            )
            cos = 0.5 * (np.trace(error[:3, :3]) - 1.0)
            r_loop.append(math.acos(max(min(cos, 1.0), -1.0)) / length)
            t_loop.append(float(np.linalg.norm(error[:3, 3])) / length)
    F = torch.from_numpy(frames)
    t_err, r_err, _ = kitti_segment_errors(
        torch.from_numpy(est[frames]), torch.from_numpy(gt[frames]), frames=F,
        reference=torch.from_numpy(gt), project=False,
    )  # fmt: skip
    assert len(t_loop) == t_err.numel() > 50
    np.testing.assert_allclose(t_err.numpy(), t_loop, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r_err.numpy(), r_loop, rtol=1e-6, atol=1e-10)
    # Every frame matched is the plain computation.
    everything = torch.arange(len(gt))
    P, Q = torch.from_numpy(est), torch.from_numpy(gt)
    for a, b in zip(
        kitti_segment_errors(P, Q, frames=everything, reference=Q), kitti_segment_errors(P, Q),
        strict=True,
    ):  # fmt: skip
        torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="whole ground truth"):
        kitti_segment_errors(P, Q, frames=everything)
