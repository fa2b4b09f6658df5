"""The geometry conventions, proven against independent slow computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mfg_lightning.core import geometry as G

KITTI_QUARTER = torch.tensor([180.0, 180.0, 64.0, 24.0], dtype=torch.float64)


def _random_depth(gen: torch.Generator, h: int = 24, w: int = 32) -> torch.Tensor:
    return 2.0 + 30.0 * torch.rand(1, h, w, generator=gen, dtype=torch.float64)


def _slow_exact_flow(depth: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Per-pixel loop, written from the pinhole model alone: the independent reference."""
    fx, fy, cx, cy = K
    h, w = depth.shape
    flow = np.zeros((2, h, w))
    for r in range(h):
        for c in range(w):
            Z = depth[r, c]
            X = np.array([(c - cx) / fx * Z, (r - cy) / fy * Z, Z])
            # The camera at k+1 sits at t with orientation R in camera-k coordinates.
            Xn = R.T @ (X - t)
            flow[0, r, c] = fx * Xn[0] / Xn[2] + cx - c
            flow[1, r, c] = fy * Xn[1] / Xn[2] + cy - r
    return flow


def test_reprojection_flow_matches_slow_loop() -> None:
    gen = torch.Generator().manual_seed(0)
    depth = _random_depth(gen, 6, 8)
    K = torch.tensor([50.0, 55.0, 3.5, 2.5], dtype=torch.float64)
    R = Rotation.from_rotvec([0.02, -0.05, 0.01]).as_matrix()
    t = np.array([0.1, -0.05, 0.8])
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.from_numpy(R)
    pose[:3, 3] = torch.from_numpy(t)
    fast = G.reprojection_flow(depth, pose[None], K[None])[0].numpy()
    slow = _slow_exact_flow(depth[0].numpy(), R, t, K.numpy())
    np.testing.assert_allclose(fast, slow, atol=1e-9)


@pytest.mark.parametrize(
    "t_dir,w_dir",
    [
        ((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)),  # forward driving
        ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),  # yaw
        ((0.3, -0.2, 1.0), (0.2, -0.5, 0.1)),  # general
    ],
)
def test_motion_field_is_first_order_of_exact_flow(t_dir, w_dir) -> None:
    """For small motions the linear field agrees with exact reprojection, error O(ε²)."""
    gen = torch.Generator().manual_seed(1)
    depth = _random_depth(gen)
    K = KITTI_QUARTER[None]
    t0 = torch.tensor([t_dir], dtype=torch.float64)
    w0 = torch.tensor([w_dir], dtype=torch.float64) * 0.05
    errors, magnitudes = [], []
    for eps in (0.4, 0.2, 0.1, 0.05):
        t, w = eps * t0, eps * w0
        exact = G.reprojection_flow(depth, G.motion_to_pose(t, w), K)
        field = G.motion_field(t, w, 1.0 / depth, K)
        errors.append((exact - field).abs().max().item())
        magnitudes.append(exact.abs().max().item())
    # The field is first order: relative to the flow itself the error vanishes ...
    assert errors[-1] / magnitudes[-1] < 0.05
    # ... and halving the motion divides the error by four (quadratic convergence).
    ratios = [errors[i] / errors[i + 1] for i in range(len(errors) - 1)]
    for r in ratios[1:]:
        assert 3.6 < r < 4.4, ratios


def test_forward_motion_expands_from_the_principal_point() -> None:
    """Sign convention: driving forward (t_z > 0) makes the flow point away from (cx, cy)."""
    K = KITTI_QUARTER[None]
    v_t = G.translational_field(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), K, 48, 128)
    xy = G.normalized_grid(K, 48, 128)
    assert (v_t * xy).sum(dim=1).min() >= 0
    # A positive yaw (rotation about +y, turning right in x-right/y-down/z-forward axes) moves the
    # scene to the left in the image: negative u everywhere.
    v_w = G.rotational_field(torch.tensor([[0.0, 0.01, 0.0]], dtype=torch.float64), K, 48, 128)
    assert (v_w[:, 0] < 0).all()


def test_matrices_agree_with_fields() -> None:
    gen = torch.Generator().manual_seed(2)
    K = torch.tensor([[100.0, 90.0, 20.0, 10.0], [80.0, 80.0, 15.0, 12.0]], dtype=torch.float64)
    t = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    w = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    A, B = G.motion_matrices(K, 20, 30)
    np.testing.assert_allclose(
        torch.einsum("bhwij,bj->bihw", A, t), G.translational_field(t, K, 20, 30), atol=1e-10
    )
    np.testing.assert_allclose(
        torch.einsum("bhwij,bj->bihw", B, w), G.rotational_field(w, K, 20, 30), atol=1e-10
    )


def test_recovery_is_exact_on_exact_fields_and_batched_equals_single() -> None:
    gen = torch.Generator().manual_seed(3)
    K = torch.tensor([[180.0, 170.0, 64.0, 24.0]] * 3 + [[200.0, 200.0, 60.0, 20.0]])
    t = torch.randn(4, 3, generator=gen)
    w = 0.01 * torch.randn(4, 3, generator=gen)
    v_t = G.translational_field(t, K, 48, 128)
    v_w = G.rotational_field(w, K, 48, 128)
    t_hat, w_hat = G.recover_motion(v_t, v_w, K)
    torch.testing.assert_close(t_hat, t, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(w_hat, w, atol=1e-6, rtol=1e-4)
    for i in range(4):
        ti, wi = G.recover_motion(v_t[i : i + 1], v_w[i : i + 1], K[i])
        torch.testing.assert_close(ti, t_hat[i : i + 1])
        torch.testing.assert_close(wi, w_hat[i : i + 1])


def test_field_basis_is_cached_per_grid() -> None:
    K = torch.tensor([150.0, 150.0, 60.0, 20.0])
    assert G.field_basis(K, 40, 120) is G.field_basis(K.clone(), 40, 120)
    assert G.field_basis(K, 40, 120) is not G.field_basis(K, 40, 121)


def test_so3_against_scipy() -> None:
    rng = np.random.default_rng(4)
    rotvecs = rng.normal(size=(64, 3))
    rotvecs = rotvecs / np.linalg.norm(rotvecs, axis=1, keepdims=True)
    rotvecs *= rng.uniform(0, math.pi - 1e-6, size=(64, 1))
    rotvecs[0] = 0.0
    rotvecs[1] = [1e-7, 0, 0]
    rotvecs[2] = [0, math.pi - 1e-5, 0]
    R = G.so3_exp(torch.from_numpy(rotvecs))
    np.testing.assert_allclose(R.numpy(), Rotation.from_rotvec(rotvecs).as_matrix(), atol=1e-12)
    back = G.so3_log(R).numpy()
    np.testing.assert_allclose(back, rotvecs, atol=1e-6)
    angles = G.rotation_angle(R).numpy()
    np.testing.assert_allclose(angles, np.linalg.norm(rotvecs, axis=1), atol=1e-6)


def test_se3_exp_log_roundtrip_and_pose_helpers() -> None:
    gen = torch.Generator().manual_seed(5)
    xi = torch.randn(32, 6, generator=gen, dtype=torch.float64)
    xi[0] = 0
    T = G.se3_exp(xi)
    torch.testing.assert_close(G.se3_log(T), xi, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(
        G.invert_pose(T) @ T, torch.eye(4, dtype=torch.float64).expand(32, 4, 4)
    )
    # Relative pose of consecutive absolute poses, then composing them back.
    traj = G.trajectory_from_motions(T[None, :5])[0]
    torch.testing.assert_close(G.relative_pose(traj[:-1], traj[1:]), T[:5])
    t, w = G.pose_to_motion(T)
    torch.testing.assert_close(G.motion_to_pose(t, w), T)


def test_scale_intrinsics_maps_pixel_centres() -> None:
    K = torch.tensor([718.856, 718.856, 607.1928, 185.2157])
    Ks = G.scale_intrinsics(K, 128 / 1241, 48 / 376)
    # The image's outer edges (-0.5 and W-0.5) map to the new outer edges.
    assert math.isclose(float((-0.5 - K[2]) / K[0]), float((-0.5 - Ks[2]) / Ks[0]), rel_tol=1e-5)
    assert math.isclose(float((1240.5 - K[2]) / K[0]), float((127.5 - Ks[2]) / Ks[0]), rel_tol=1e-5)


def test_bad_intrinsics_shape_is_refused() -> None:
    with pytest.raises(ValueError, match="intrinsics must be"):
        G.normalized_grid(torch.ones(3), 4, 4)
