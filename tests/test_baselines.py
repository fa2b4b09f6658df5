"""The classical egomotion baselines recover known motions from exact synthetic fields."""

from __future__ import annotations

import math

import pytest
import torch

from mfg_lightning.core import geometry
from mfg_lightning.motion import baselines

# KITTI's camera at a quarter of the model's resolution (fx, fy, cx, cy), pixels.
K = torch.tensor([74.1, 74.1, 62.6, 18.5], dtype=torch.float64)
H, W = 36, 96

MOTIONS = [
    ((0.0, 0.0, 1.2), (0.0, 0.0, 0.0)),  # straight ahead
    ((0.05, -0.01, 0.9), (0.002, 0.03, -0.001)),  # a turn
    ((0.3, 0.05, -0.6), (-0.01, 0.02, 0.015)),  # reversing, sideways, rolling
]


def _depth(seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return 3.0 + 40.0 * torch.rand(1, H, W, generator=gen, dtype=torch.float64)


def _angle(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle between two 3-vectors, radians."""
    cos = (a @ b) / (a.norm() * b.norm())
    return math.acos(max(-1.0, min(1.0, float(cos))))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-6)])
def test_oracle_recovers_the_true_motion_from_the_exact_fields(dtype, tol) -> None:
    t = torch.tensor([m[0] for m in MOTIONS], dtype=torch.float64)
    w = torch.tensor([m[1] for m in MOTIONS], dtype=torch.float64)
    pose = geometry.motion_to_pose(t, w).to(dtype)
    t_hat, w_hat = baselines.oracle_motion(pose, K.to(dtype), H, W)
    assert t_hat.dtype == dtype
    torch.testing.assert_close(t_hat.double(), t, atol=tol * 10, rtol=0)
    torch.testing.assert_close(w_hat.double(), w, atol=tol, rtol=0)


@pytest.mark.parametrize("t_true,w_true", MOTIONS)
def test_continuous_least_squares_recovers_the_motion_of_an_exact_motion_field(
    t_true, w_true
) -> None:
    t = torch.tensor([t_true], dtype=torch.float64)
    w = torch.tensor([w_true], dtype=torch.float64)
    depth = _depth(1)
    flow = geometry.motion_field(t, w, 1.0 / depth, K[None])
    t_hat, w_hat = baselines.continuous_least_squares(flow, K, translation_norm=t.norm(dim=1))
    # The direction (and its sign, from ρ > 0) to the pattern search's resolution.
    assert _angle(t_hat[0], t[0]) < 1e-3
    torch.testing.assert_close(t_hat.norm(dim=1), t.norm(dim=1))
    torch.testing.assert_close(w_hat, w, atol=2e-5, rtol=0)


def test_continuous_least_squares_robust_mode_ignores_outliers() -> None:
    t = torch.tensor([[0.05, -0.01, 0.9]], dtype=torch.float64)
    w = torch.tensor([[0.002, 0.03, -0.001]], dtype=torch.float64)
    flow = geometry.motion_field(t, w, 1.0 / _depth(2), K[None])
    gen = torch.Generator().manual_seed(3)
    outliers = torch.rand(1, H, W, generator=gen) < 0.05
    junk = 30.0 * (torch.rand(1, 2, H, W, generator=gen, dtype=torch.float64) - 0.5)
    corrupted = torch.where(outliers[:, None], junk, flow)
    _, w_ls = baselines.continuous_least_squares(corrupted, K)
    t_rob, w_rob = baselines.continuous_least_squares(corrupted, K, robust=True)
    rob_t, rob_w = _angle(t_rob[0], t[0]), float((w_rob - w).norm())
    # Plain least squares is pulled off by 5 % junk vectors; the reweighted solution is not.
    assert rob_t < 5e-3 and rob_w < 5e-4
    assert float((w_ls - w).norm()) > 5 * rob_w


def test_continuous_least_squares_uses_only_valid_pixels() -> None:
    t = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    w = torch.tensor([[0.0, 0.01, 0.0]], dtype=torch.float64)
    flow = geometry.motion_field(t, w, 1.0 / _depth(4), K[None])
    valid = torch.ones(1, H, W, dtype=torch.bool)
    valid[:, :, : W // 3] = False
    flow[:, :, :, : W // 3] = 1e3  # garbage where the mask says "invalid"
    t_hat, w_hat = baselines.continuous_least_squares(flow, K, valid)
    assert _angle(t_hat[0], t[0]) < 1e-3
    torch.testing.assert_close(w_hat, w, atol=2e-5, rtol=0)
    # Too few valid pixels: no estimate, zeros (not NaN).
    t0, w0 = baselines.continuous_least_squares(flow, K, torch.zeros(1, H, W, dtype=torch.bool))
    assert torch.equal(t0, torch.zeros(1, 3)) and torch.equal(w0, torch.zeros(1, 3))


def _exact_flows() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact reprojection flow of every motion of MOTIONS: ``(flow, t, ω)``."""
    t = torch.tensor([m[0] for m in MOTIONS], dtype=torch.float64)
    w = torch.tensor([m[1] for m in MOTIONS], dtype=torch.float64)
    depth = torch.cat([_depth(10 + i) for i in range(len(MOTIONS))])
    flow = geometry.reprojection_flow(depth, geometry.motion_to_pose(t, w), K.expand(len(t), 4))
    return flow, t, w


@pytest.mark.parametrize("method", ["RANSAC", "USAC_MAGSAC"])
def test_essential_matrix_recovers_the_motion_of_exact_reprojection_flow(method: str) -> None:
    flow, t, w = _exact_flows()
    t_hat, w_hat = baselines.essential_matrix_motion(
        flow, K, translation_norm=t.norm(dim=1), method=method
    )
    for i in range(len(MOTIONS)):
        assert _angle(t_hat[i], t[i]) < 1e-4, i
    torch.testing.assert_close(t_hat.norm(dim=1), t.norm(dim=1))
    torch.testing.assert_close(w_hat, w, atol=1e-5, rtol=0)
    # Deterministic for a fixed seed, and a frame's result does not depend on its batch.
    again = baselines.essential_matrix_motion(
        flow, K, translation_norm=t.norm(dim=1), method=method
    )
    assert torch.equal(again[0], t_hat) and torch.equal(again[1], w_hat)
    alone = baselines.essential_matrix_motion(flow[2:], K, method=method)
    assert torch.equal(alone[1][0], w_hat[2])


def test_essential_matrix_with_ransac_rejects_outliers() -> None:
    flow, t, w = _exact_flows()
    gen = torch.Generator().manual_seed(5)
    outliers = torch.rand(len(MOTIONS), 1, H, W, generator=gen) < 0.03
    junk = 30.0 * (torch.rand(flow.shape, generator=gen, dtype=torch.float64) - 0.5)
    t_hat, w_hat = baselines.essential_matrix_motion(torch.where(outliers, junk, flow), K)
    # RANSAC keeps the unrefined minimal-sample model with most inliers: on dense flow a nearly
    # right model can tie with the exact one, so the bound is loose (a wrong convention or a
    # junk-driven fit would be off by far more).
    for i in range(len(MOTIONS)):
        assert _angle(t_hat[i], t[i]) < 1e-2, i
    torch.testing.assert_close(w_hat, w, atol=1e-3, rtol=0)


@pytest.mark.parametrize("method", ["RANSAC", "USAC_MAGSAC"])
@pytest.mark.parametrize(
    "t_true,w_true,near,far",
    [
        # the first rendered pair of KITTI 10: 0.13 m per frame, turning, a backdrop far away
        ((0.012, 0.0, 0.127), (0.0, 0.0155, 0.0), 300.0, 650.0),
        # slowing down in a street (KITTI 10 near frame 1150): 0.06 m per frame, 5 to 40 m
        ((0.002, 0.0, 0.06), (0.0, 0.0008, 0.0), 5.0, 40.0),
    ],
)
def test_essential_matrix_keeps_the_right_decomposition_when_every_point_is_far(
    method: str, t_true, w_true, near: float, far: float
) -> None:
    # Every point lies beyond 50 baselines, where cv2.recoverPose's default distance limit
    # drops it from the cheirality vote: all four decompositions of E then tie at zero and the
    # first one came back, its rotation turned by π or its translation reversed. The exact flow
    # gives every point's side, so the vote has to count them.
    t = torch.tensor([t_true], dtype=torch.float64)
    w = torch.tensor([w_true], dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    depth = near + (far - near) * torch.rand(1, H, W, generator=gen, dtype=torch.float64)
    assert float(depth.min()) > 50 * float(t.norm())
    pose = geometry.motion_to_pose(t, w)
    flow = geometry.reprojection_flow(depth, pose, K[None])
    t_hat, w_hat = baselines.essential_matrix_motion(flow, K, method=method)
    rotation_error = geometry.rotation_angle(
        geometry.so3_exp(w_hat).transpose(-1, -2) @ pose[:, :3, :3]
    )
    # The parallax is a fraction of the 0.5 px threshold and RANSAC keeps an unrefined
    # minimal-sample model: its rotation is off by about 1e-3 rad and its direction by about
    # 20°. A wrong decomposition is off by π (rotation) or about 180° (direction).
    assert float(rotation_error) < 5e-3
    assert _angle(t_hat[0], t[0]) < math.pi / 4


def test_essential_matrix_of_five_points_keeps_the_solution_with_most_points_in_front() -> None:
    # With exactly five correspondences cv2.findEssentialMat returns every solution of the
    # five-point solver stacked (four here). The first puts two of the points behind a camera
    # and is off by 0.73 rad; only the true motion puts all five in front.
    t = torch.tensor([MOTIONS[2][0]], dtype=torch.float64)
    w = torch.tensor([MOTIONS[2][1]], dtype=torch.float64)
    rows, cols = [21, 34, 15, 15, 26], [72, 92, 36, 55, 2]
    depth = torch.full((1, H, W), 20.0, dtype=torch.float64)
    depth[0, rows, cols] = torch.tensor([31.73, 14.99, 33.69, 17.12, 15.97], dtype=torch.float64)
    valid = torch.zeros(1, H, W, dtype=torch.bool)
    valid[0, rows, cols] = True
    flow = geometry.reprojection_flow(depth, geometry.motion_to_pose(t, w), K[None])
    _, w_hat = baselines.essential_matrix_motion(flow, K, valid, pixel_stride=1)
    torch.testing.assert_close(w_hat, w, atol=1e-6, rtol=0)


def test_essential_matrix_without_motion_or_points_returns_zeros() -> None:
    flow = torch.zeros(1, 2, H, W, dtype=torch.float64)
    t_hat, w_hat = baselines.essential_matrix_motion(flow, K)
    assert torch.isfinite(t_hat).all() and torch.isfinite(w_hat).all()
    t_none, w_none = baselines.essential_matrix_motion(
        flow, K, valid=torch.zeros(1, H, W, dtype=torch.bool)
    )
    assert torch.equal(t_none, torch.zeros(1, 3)) and torch.equal(w_none, torch.zeros(1, 3))


def test_bad_inputs_are_clear_errors() -> None:
    with pytest.raises(ValueError, match="flow must be"):
        baselines.continuous_least_squares(torch.zeros(2, H, W), K)
    with pytest.raises(ValueError, match="intrinsics"):
        baselines.essential_matrix_motion(torch.zeros(1, 2, H, W), torch.ones(3))
    with pytest.raises(ValueError, match="robust estimator"):
        baselines.essential_matrix_motion(torch.zeros(1, 2, H, W), K, method="NOPE")


def test_fibonacci_hemisphere_covers_the_half_sphere_evenly() -> None:
    pts = baselines.fibonacci_hemisphere(400)
    torch.testing.assert_close(pts.norm(dim=1), torch.ones(400, dtype=torch.float64))
    assert bool((pts[:, 2] >= 0).all())
    # Every direction of the half sphere is within about one spacing of a grid point: over 10^5
    # seeded probes the farthest is 1.03 spacings away (the spiral's covering radius), the mean
    # 0.39 spacings.
    gen = torch.Generator().manual_seed(0)
    probe = torch.randn(100_000, 3, dtype=torch.float64, generator=gen)
    probe = torch.nn.functional.normalize(probe, dim=1)
    probe[:, 2] = probe[:, 2].abs()
    nearest = (probe @ pts.T).clamp(-1, 1).acos().min(dim=1).values
    spacing = math.sqrt(2 * math.pi / 400)
    assert float(nearest.max()) < 1.1 * spacing
    assert float(nearest.mean()) < 0.45 * spacing
