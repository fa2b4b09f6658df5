"""Whole-trajectory ATE and its alignments: against evo, a slow loop and known transforms.

evo (GPL) is imported by these tests only; the package never imports it.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import SHARED
from mfg_lightning.metrics import TrajectoryATE, align_trajectory, ate_traj, ate_traj_errors
from mfg_lightning.metrics.alignment import umeyama
from mfg_lightning.trajectory.pose_io import read_kitti_poses

KITTI_POSES = SHARED / "data" / "kitti_odometry" / "poses"
# A few hundred poses keep evo's Python loops quick.
NUM_POSES = 400


def _similarity(scale: float, rotvec: list[float], offset: list[float]) -> np.ndarray:
    """A 4×4 similarity ``[s R | t]``."""
    T = np.eye(4)
    T[:3, :3] = scale * Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = offset
    return T


def _apply_similarity(S: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """``S · P_k`` with the scale kept out of the rotation blocks (positions ``s R p + t``)."""
    scale = np.cbrt(np.linalg.det(S[:3, :3]))
    R = S[:3, :3] / scale
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ R.T + S[:3, 3]
    return out


def _drifting_estimate(gt: np.ndarray, seed: int) -> np.ndarray:
    """The true motions composed with small errors, then put into another similarity frame, as a
    monocular method's output would be (unknown scale, its own world frame)."""
    rng = np.random.default_rng(seed)
    motions = np.linalg.inv(gt[:-1]) @ gt[1:]
    noise = np.tile(np.eye(4), (len(motions), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1e-3, (len(motions), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, 0.02, (len(motions), 3))
    poses = [np.eye(4)]
    for m in motions @ noise:
        poses.append(poses[-1] @ m)
    return _apply_similarity(
        _similarity(0.35, [0.2, -0.9, 0.1], [3.0, -1.0, 40.0]), np.stack(poses)
    )


@pytest.fixture(scope="module")
def kitti_pair() -> tuple[np.ndarray, np.ndarray]:
    """Real KITTI 09 ground truth (first poses, exact rotations) and a drifting estimate."""
    if not KITTI_POSES.is_dir():
        pytest.skip(f"{KITTI_POSES} not present")
    gt = read_kitti_poses(KITTI_POSES / "09.txt")[:NUM_POSES]
    # evo would otherwise see the file's 6-digit rotation blocks, which the metrics project
    # onto SO(3); positions (all the ATE uses) are the same either way.
    gt[:, :3, :3] = Rotation.from_matrix(gt[:, :3, :3]).as_matrix()
    return gt, _drifting_estimate(gt, 0)


def _evo_ape(gt: np.ndarray, est: np.ndarray, **kwargs) -> tuple[dict[str, float], float]:
    """evo's APE (translation part) and the scale of its alignment."""
    pytest.importorskip("evo")
    from evo.core.metrics import PoseRelation
    from evo.core.trajectory import PosePath3D
    from evo.main_ape import ape

    result = ape(
        PosePath3D(poses_se3=list(gt)),
        PosePath3D(poses_se3=list(est)),
        PoseRelation.translation_part,
        **kwargs,
    )
    sim3 = result.np_arrays.get("alignment_transformation_sim3")
    scale = 1.0 if sim3 is None else float(np.cbrt(np.linalg.det(sim3[:3, :3])))
    return result.stats, scale


@pytest.mark.parametrize(
    ("align", "evo_kwargs"),
    [
        ("none", {}),
        ("se3", {"align": True}),  # evo_ape -a
        ("sim3", {"align": True, "correct_scale": True}),  # evo_ape -as
        ("se3", {"align": True, "n_to_align": 60}),  # evo_ape -a --n_to_align 60
        ("sim3", {"align": True, "correct_scale": True, "n_to_align": 60}),
    ],
)
def test_agrees_with_evo_on_perturbed_kitti(kitti_pair, align: str, evo_kwargs: dict) -> None:
    gt, est = kitti_pair
    stats, evo_scale = _evo_ape(gt, est, **evo_kwargs)
    ours = ate_traj(
        torch.from_numpy(est), torch.from_numpy(gt), align, evo_kwargs.get("n_to_align")
    )
    assert ours["ate_traj"].item() == pytest.approx(stats["rmse"], abs=1e-6)
    assert ours["ate_traj_mean"].item() == pytest.approx(stats["mean"], abs=1e-6)
    assert ours["ate_traj_std"].item() == pytest.approx(stats["std"], abs=1e-6)
    assert ours["ate_traj_scale"].item() == pytest.approx(evo_scale, abs=1e-6)
    # The test means something: alignment matters here by orders of magnitude.
    if align == "sim3":
        assert ours["ate_traj_scale"].item() == pytest.approx(1 / 0.35, rel=0.05)
        assert (
            ours["ate_traj"].item()
            < 0.02 * ate_traj(torch.from_numpy(est), torch.from_numpy(gt))["ate_traj"].item()
        )


def _scale_loop(gt: np.ndarray, est: np.ndarray, n: int | None) -> tuple[float, list[float]]:
    """kitti-odom-eval's ``--align scale``, pose by pose: both relative to their first frame, the
    least-squares scale Σ g·p / Σ p·p over the first n poses, then position errors."""
    g = [np.linalg.inv(gt[0]) @ gt[k] for k in range(len(gt))]
    p = [np.linalg.inv(est[0]) @ est[k] for k in range(len(est))]
    count = len(gt) if n is None else n
    num = sum(float(g[k][:3, 3] @ p[k][:3, 3]) for k in range(count))
    den = sum(float(p[k][:3, 3] @ p[k][:3, 3]) for k in range(count))
    scale = num / den
    errors = [float(np.linalg.norm(g[k][:3, 3] - scale * p[k][:3, 3])) for k in range(len(gt))]
    return scale, errors


@pytest.mark.parametrize("n_to_align", [None, 50])
def test_scale_mode_matches_a_slow_loop(kitti_pair, n_to_align: int | None) -> None:
    gt, est = kitti_pair
    scale, errors = _scale_loop(gt, est, n_to_align)
    P, Q = torch.from_numpy(est), torch.from_numpy(gt)
    aligned = align_trajectory(P, Q, "scale", n_to_align)
    assert aligned.scale.item() == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(ate_traj_errors(aligned).numpy(), errors, rtol=1e-9, atol=1e-9)
    ours = ate_traj(P, Q, "scale", n_to_align)
    assert ours["ate_traj"].item() == pytest.approx(np.sqrt(np.mean(np.square(errors))), rel=1e-9)
    assert ours["ate_traj_mean"].item() == pytest.approx(np.mean(errors), rel=1e-9)
    assert ours["ate_traj_std"].item() == pytest.approx(np.std(errors), rel=1e-9)


def test_umeyama_recovers_a_known_similarity_exactly() -> None:
    rng = np.random.default_rng(1)
    points = rng.normal(0, 10, (2, 50, 3))
    truth = [
        _similarity(2.5, [0.4, -1.1, 2.0], [1.0, -7.0, 3.0]),
        _similarity(0.01, [-2.9, 0.1, 0.3], [0.0, 100.0, -5.0]),
    ]
    moved = np.stack([p @ S[:3, :3].T + S[:3, 3] for p, S in zip(points, truth, strict=True)])
    R, t, s = umeyama(torch.from_numpy(points), torch.from_numpy(moved))  # batched
    for i, S in enumerate(truth):
        scale = np.cbrt(np.linalg.det(S[:3, :3]))
        assert s[i].item() == pytest.approx(scale, rel=1e-12)
        np.testing.assert_allclose(R[i].numpy(), S[:3, :3] / scale, atol=1e-12)
        np.testing.assert_allclose(t[i].numpy(), S[:3, 3], atol=1e-10)
        assert torch.linalg.det(R[i]).item() == pytest.approx(1.0, abs=1e-12)
    # Without scale: the rotation and translation of a rigid motion, s = 1.
    rigid = _similarity(1.0, [0.4, -1.1, 2.0], [1.0, -7.0, 3.0])
    R, t, s = umeyama(
        torch.from_numpy(points[0]), torch.from_numpy(points[0] @ rigid[:3, :3].T + rigid[:3, 3]),
        with_scale=False,
    )  # fmt: skip
    assert s.item() == 1.0
    np.testing.assert_allclose(R.numpy(), rigid[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t.numpy(), rigid[:3, 3], atol=1e-10)


def test_alignment_undoes_a_known_similarity_of_a_trajectory(kitti_pair) -> None:
    gt, _ = kitti_pair
    S = _similarity(0.2, [1.0, 0.5, -0.3], [10.0, 2.0, -4.0])
    est = _apply_similarity(S, gt)
    P, Q = torch.from_numpy(est), torch.from_numpy(gt)
    for n in (None, 3):  # three poses of a real drive determine the similarity
        aligned = align_trajectory(P, Q, "sim3", n)
        assert aligned.scale.item() == pytest.approx(5.0, rel=1e-10)
        np.testing.assert_allclose(aligned.pred.numpy(), aligned.target.numpy(), atol=1e-9)
    # A rigid motion: se3 undoes it (poses and all), and sim3 finds scale 1.
    rigid = _similarity(1.0, [1.0, 0.5, -0.3], [10.0, 2.0, -4.0])
    est = torch.from_numpy(_apply_similarity(rigid, gt))
    for mode in ("se3", "sim3"):
        aligned = align_trajectory(est, Q, mode)
        np.testing.assert_allclose(aligned.pred.numpy(), gt, atol=1e-9)
        assert aligned.scale.item() == pytest.approx(1.0, abs=1e-12)
    # scale: an estimate that is the truth times a factor, in its own first-frame world.
    scaled = gt.copy()
    scaled[:, :3, 3] *= 0.25
    scaled = _apply_similarity(rigid, scaled)
    aligned = align_trajectory(torch.from_numpy(scaled), Q, "scale")
    assert aligned.scale.item() == pytest.approx(4.0, rel=1e-10)
    assert ate_traj_errors(aligned).max().item() < 1e-9


def test_no_motion_is_finite_with_scale_zero() -> None:
    gt = np.tile(np.eye(4), (20, 1, 1))
    gt[:, 2, 3] = np.arange(20.0)
    still = torch.from_numpy(np.tile(np.eye(4), (20, 1, 1)))
    for mode in ("sim3", "scale"):
        result = ate_traj(still, torch.from_numpy(gt), mode)
        assert result["ate_traj_scale"].item() == 0.0
        assert np.isfinite(result["ate_traj"].item())
    # sim3 then puts every estimated position at the truth's centroid (9.5 m along z).
    expected = np.sqrt(np.mean((np.arange(20.0) - 9.5) ** 2))
    assert ate_traj(still, torch.from_numpy(gt), "sim3")["ate_traj"].item() == pytest.approx(
        expected, rel=1e-12
    )


def test_metric_pools_poses_of_all_sequences(kitti_pair) -> None:
    gt, est = kitti_pair
    pairs = [(est[:250], gt[:250]), (est[250:], gt[250:])]
    errors = torch.cat(
        [
            ate_traj_errors(align_trajectory(torch.from_numpy(e), torch.from_numpy(g), "sim3"))
            for e, g in pairs
        ]
    )
    together, merged, other = (TrajectoryATE(align="sim3") for _ in range(3))
    for e, g in pairs:
        together.update(torch.from_numpy(e), torch.from_numpy(g))
    merged.update(torch.from_numpy(pairs[0][0]), torch.from_numpy(pairs[0][1]))
    other.update(torch.from_numpy(pairs[1][0]), torch.from_numpy(pairs[1][1]))
    merged.merge_state(other)  # the reduction a DDP sync applies
    for metric in (together, merged):
        result = metric.compute()
        assert set(result) == {"ate_traj", "ate_traj_mean", "ate_traj_std"}
        assert result["ate_traj"].item() == pytest.approx(
            errors.square().mean().sqrt().item(), rel=1e-12
        )
        assert result["ate_traj_std"].item() == pytest.approx(np.std(errors.numpy()), rel=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torchmetrics warns about compute before update
        assert np.isnan(TrajectoryATE().compute()["ate_traj"].item())


def test_bad_options_are_refused() -> None:
    poses = torch.eye(4, dtype=torch.float64).expand(5, 4, 4)
    with pytest.raises(ValueError, match="unknown alignment 'umeyama'"):
        ate_traj(poses, poses, "umeyama")
    with pytest.raises(ValueError, match="n_to_align must be a positive"):
        TrajectoryATE(align="se3", n_to_align=0)
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        ate_traj(poses[:4], poses)


def test_a_rotation_needs_three_poses() -> None:
    poses = torch.eye(4, dtype=torch.float64).repeat(10, 1, 1)
    poses[:, 2, 3] = torch.arange(10.0)
    with pytest.raises(ValueError, match="sim3 alignment needs at least 3 poses .* got 2"):
        ate_traj(poses, poses, "sim3", n_to_align=2)
    # scale needs no rotation: the second pose alone (the first is the origin) fixes it.
    assert ate_traj(poses, poses, "scale", n_to_align=2)["ate_traj_scale"].item() == 1.0


def test_scale_7dof_keeps_only_umeyama_s_scale(kitti_pair) -> None:
    """kitti-odom-eval's ``scale_7dof``: both relative to their first frame, Umeyama's Sim(3)
    fitted, only its scale applied to the estimated positions."""
    gt, est = kitti_pair
    est = _apply_similarity(_similarity(0.3, [0.2, 1.0, -0.1], [4.0, -2.0, 9.0]), est)
    P, Q = torch.from_numpy(est), torch.from_numpy(gt)
    g = np.stack([np.linalg.inv(gt[0]) @ x for x in gt])[:, :3, 3]
    p = np.stack([np.linalg.inv(est[0]) @ x for x in est])[:, :3, 3]
    _, _, s = umeyama(torch.from_numpy(p), torch.from_numpy(g))
    aligned = align_trajectory(P, Q, "scale_7dof")
    assert aligned.scale.item() == pytest.approx(s.item(), rel=1e-9)
    assert aligned.scale.item() == pytest.approx(1 / (0.3 * 0.35), rel=0.05)  # kitti_pair: 0.35
    errors = np.linalg.norm(g - s.item() * p, axis=1)
    np.testing.assert_allclose(ate_traj_errors(aligned).numpy(), errors, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(aligned.rotation, torch.eye(3, dtype=torch.float64))
    # The rotation is not undone: sim3 aligns much better than the scale alone.
    sim3 = ate_traj(P, Q, "sim3")["ate_traj"].item()
    assert sim3 < 0.5 * ate_traj(P, Q, "scale_7dof")["ate_traj"].item()
    with pytest.raises(ValueError, match="at least 3 poses"):
        align_trajectory(P, Q, "scale_7dof", n_to_align=2)


def test_align_origin_is_both_trajectories_relative_to_their_first_frame(kitti_pair) -> None:
    """evo's ``--align_origin`` gives the position errors of kitti-odom-eval's first-frame
    expression; it changes nothing for the modes that fit a rigid motion or re-express."""
    gt, est = kitti_pair
    late_gt, late_est = (
        gt[30:],
        _apply_similarity(_similarity(1.0, [0, 0.5, 0], [9, 0, 1]), est)[30:],
    )
    P, Q = torch.from_numpy(late_est), torch.from_numpy(late_gt)
    aligned = align_trajectory(P, Q, "none", align_origin=True)
    torch.testing.assert_close(aligned.pred[0], aligned.target[0])
    g = np.stack([np.linalg.inv(late_gt[0]) @ x for x in late_gt])[:, :3, 3]
    p = np.stack([np.linalg.inv(late_est[0]) @ x for x in late_est])[:, :3, 3]
    np.testing.assert_allclose(
        ate_traj_errors(aligned).numpy(), np.linalg.norm(g - p, axis=1), atol=1e-9
    )
    for mode in ("se3", "sim3", "scale", "scale_7dof"):
        plain = ate_traj_errors(align_trajectory(P, Q, mode))
        origin = ate_traj_errors(align_trajectory(P, Q, mode, align_origin=True))
        torch.testing.assert_close(plain, origin, rtol=1e-9, atol=1e-9)


def test_raw_rotations_differ_only_by_the_rounding_of_the_files(kitti_pair) -> None:
    gt, est = kitti_pair
    rounded = np.round(est, 6)  # a 6-digit file: rotations orthonormal to ~1e-6
    P, Q = torch.from_numpy(rounded), torch.from_numpy(gt)
    for mode in ("none", "sim3", "scale_7dof"):
        projected = align_trajectory(P, Q, mode)
        raw = align_trajectory(P, Q, mode, project=False)
        torch.testing.assert_close(raw.pred, projected.pred, atol=1e-4, rtol=0)
        assert not torch.equal(raw.pred, projected.pred)
        # As written: the rotation blocks are the file's, not projected.
        if mode == "none":
            torch.testing.assert_close(raw.pred, P)
