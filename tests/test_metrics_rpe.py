"""RPE (Sturm et al. 2012) cross-checked against evo, on random and real KITTI trajectories."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from evo.core import metrics as evo_metrics
from evo.core.trajectory import PosePath3D
from scipy.spatial.transform import Rotation

from conftest import KITTI_POSES, NO_KITTI_POSES
from mfg_lightning.metrics import RelativePoseError, relative_pose_error, relative_pose_errors
from mfg_lightning.trajectory.pose_io import read_kitti_poses


def _random_trajectory(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.4, (n, 3))).as_matrix()
    poses[:, :3, 3] = np.cumsum(rng.normal(0, 1.0, (n, 3)), axis=0)
    return poses


def _perturb(poses: np.ndarray, seed: int, rot_sigma: float, trans_sigma: float) -> np.ndarray:
    """Right-multiply every pose by a random small motion (noise in the camera frame)."""
    rng = np.random.default_rng(seed)
    noise = np.tile(np.eye(4), (len(poses), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, rot_sigma, (len(poses), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, trans_sigma, (len(poses), 3))
    return poses @ noise


def _evo_rpe(gt: np.ndarray, est: np.ndarray, delta: int) -> tuple[np.ndarray, np.ndarray]:
    """evo's per-pair translational (m) and rotational (rad) RPE.

    evo's default "consecutive pairs" step the first frame by Δ; the protocol (and Sturm et al.)
    use every first frame, which is evo's ``all_pairs`` for Δ > 1. For Δ = 1 both are the same and
    the default is used, as ``evo_rpe --delta 1 --delta_unit f``.
    """
    data = (PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est)))
    errors = []
    for relation in (
        evo_metrics.PoseRelation.translation_part,
        evo_metrics.PoseRelation.rotation_angle_rad,
    ):
        metric = evo_metrics.RPE(
            relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=delta > 1
        )
        metric.process_data(data)
        errors.append(np.asarray(metric.error))
    return errors[0], errors[1]


def _assert_matches_evo(gt: np.ndarray, est: np.ndarray, delta: int) -> None:
    trans, rot = relative_pose_errors(torch.from_numpy(est), torch.from_numpy(gt), delta)
    evo_trans, evo_rot = _evo_rpe(gt, est, delta)
    np.testing.assert_allclose(trans.numpy(), evo_trans, atol=1e-6, rtol=0)
    np.testing.assert_allclose(rot.numpy(), evo_rot, atol=1e-6, rtol=0)
    summary = relative_pose_error(torch.from_numpy(est), torch.from_numpy(gt), delta)
    for name, values in (("rpe_trans", evo_trans), ("rpe_rot", evo_rot)):
        # evo's statistics: mean, np.std (population) and RMSE.
        assert summary[name].item() == pytest.approx(values.mean(), abs=1e-6)
        assert summary[f"{name}_std"].item() == pytest.approx(values.std(), abs=1e-6)
        assert summary[f"{name}_rmse"].item() == pytest.approx(
            math.sqrt(np.mean(values**2)), abs=1e-6
        )


@pytest.mark.parametrize("delta", [1, 3])
def test_matches_evo_on_random_trajectories(delta: int) -> None:
    gt = _random_trajectory(200, 0)
    est = _perturb(gt, 1, rot_sigma=0.05, trans_sigma=0.2)
    _assert_matches_evo(gt, est, delta)


@pytest.mark.parametrize("rot_sigma,trans_sigma", [(0.0, 0.0), (1e-3, 0.02), (1e-2, 0.1)])
def test_matches_evo_on_perturbed_kitti_09(rot_sigma: float, trans_sigma: float) -> None:
    if not KITTI_POSES.is_dir():
        pytest.skip(NO_KITTI_POSES)
    gt = read_kitti_poses(KITTI_POSES / "09.txt")
    est = _perturb(gt, 2, rot_sigma, trans_sigma)
    _assert_matches_evo(gt, est, 1)


def test_identical_kitti_trajectories_have_no_rotation_floor() -> None:
    """The 6-digit rotations of pose files must not turn into ~5e-4 rad of error."""
    if not KITTI_POSES.is_dir():
        pytest.skip(NO_KITTI_POSES)
    gt = torch.from_numpy(read_kitti_poses(KITTI_POSES / "09.txt"))
    trans, rot = relative_pose_errors(gt, gt)
    # arccos resolves angles only down to sqrt(2 · 2.2e-16) ≈ 2e-8 rad in float64.
    assert trans.max().item() < 1e-9 and rot.max().item() < 1e-7


def test_metric_over_sequences_in_any_split_or_merged() -> None:
    gts = [_random_trajectory(n, s) for n, s in ((50, 3), (31, 4), (2, 5))]
    ests = [_perturb(g, 10 + i, 0.02, 0.1) for i, g in enumerate(gts)]
    t = [torch.from_numpy(x) for x in gts]
    e = [torch.from_numpy(x) for x in ests]
    pairs = [relative_pose_errors(ei, ti) for ei, ti in zip(e, t, strict=True)]
    trans = torch.cat([p[0] for p in pairs])
    rot = torch.cat([p[1] for p in pairs])

    sequential = RelativePoseError()
    for ei, ti in zip(e, t, strict=True):
        sequential.update(ei, ti)
    # One long sequence fed in chunks that overlap by Δ frames gives the same pairs.
    chunked = RelativePoseError()
    chunked.update(e[0][:20], t[0][:20])
    chunked.update(e[0][19:], t[0][19:])
    chunked.update(e[1], t[1])
    chunked.update(e[2], t[2])
    merged, other = RelativePoseError(), RelativePoseError()
    merged.update(e[0], t[0])
    other.update(e[1], t[1])
    other.update(e[2], t[2])
    merged.merge_state(other)  # the reductions a DDP sync applies

    expected = {
        "rpe_trans": trans.mean(),
        "rpe_trans_std": trans.std(correction=0),
        "rpe_trans_rmse": trans.square().mean().sqrt(),
        "rpe_rot": rot.mean(),
        "rpe_rot_std": rot.std(correction=0),
        "rpe_rot_rmse": rot.square().mean().sqrt(),
    }
    for metric in (sequential, chunked, merged):
        result = metric.compute()
        assert set(result) == set(expected)
        for key, value in expected.items():
            assert result[key].item() == pytest.approx(value.item(), rel=1e-12)


def test_short_sequences_and_bad_inputs() -> None:
    one = torch.eye(4, dtype=torch.float64)[None]
    assert all(math.isnan(v.item()) for v in relative_pose_error(one, one).values())
    with pytest.raises(ValueError, match="delta"):
        RelativePoseError(delta=0)
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        relative_pose_errors(torch.eye(4).repeat(3, 1, 1), torch.eye(4).repeat(4, 1, 1))
    metric = RelativePoseError()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torchmetrics warns about compute before update
        assert all(math.isnan(v.item()) for v in metric.compute().values())


def test_published_names_and_the_earlier_ones() -> None:
    """One name per quantity (``rpe_trans``, as logged and in the README); code written against
    the names before them (``"trans"``) still reads the same values."""
    gt = torch.from_numpy(_random_trajectory(20, 7))
    est = torch.from_numpy(_perturb(gt.numpy(), 8, 0.02, 0.1))
    metric = RelativePoseError()
    metric.update(est, gt)
    for result in (relative_pose_error(est, gt), metric.compute()):
        assert tuple(result) == RelativePoseError.names
        for part in ("trans", "rot"):
            for stat in ("", "_std", "_rmse"):
                assert f"{part}{stat}" in result
                assert result[f"{part}{stat}"] is result[f"rpe_{part}{stat}"]
        assert result.get("trans") is result["rpe_trans"] and result.get("ate") is None
        with pytest.raises(KeyError):
            result["t_err"]  # a name of another metric
