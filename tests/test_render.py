"""Rendered frames of persistent worlds: deterministic, consistent across frames, exact flow."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from mfg_lightning.core import geometry
from mfg_lightning.pictures.rendered_frames import frame_panels, picture_grid
from mfg_lightning.scene import camera, seeding
from mfg_lightning.scene.render import (
    FAR_PLANE,
    REGION_FAR,
    REGION_MOVING,
    REGION_NAMES,
    REGION_ROAD,
    REGION_STRUCTURE,
    exact_flow,
    render_frame,
)
from mfg_lightning.scene.worlds import World
from mfg_lightning.trajectory.pose_io import read_kitti_poses
from street_worlds import rendered_frames, street_world

H, W = 96, 256


@pytest.fixture(scope="module")
def world() -> World:
    return street_world(120)


@pytest.fixture(scope="module")
def K() -> torch.Tensor:
    return camera.kitti_like_intrinsics(H, W)


@pytest.fixture(scope="module")
def frames(world, K) -> dict[int, object]:
    return rendered_frames(world, K, (60, 61, 62), H, W)


def _frame_with_moving_object(world: World, K: torch.Tensor) -> int:
    """The first frame (of every third) with a moving object over 30 pixels at 48 × 128."""
    for k in range(0, world.num_frames - 2, 3):
        if int((render_frame(world, k, K, 48, 128).instance >= 0).sum()) > 30:
            return k
    raise AssertionError("no moving object in view anywhere")


def test_frames_are_deterministic_and_depend_on_the_seed(world, K, frames):
    a = frames[60]
    torch.set_num_threads(2)
    try:
        b = render_frame(world, 60, K, H, W)
    finally:
        torch.set_num_threads(1)
    for field in ("rgb", "depth", "region", "instance"):
        assert torch.equal(getattr(a, field), getattr(b, field)), field
    other = World.generate(world.poses, seed=6, name="r")
    c = render_frame(other, 60, K, H, W)
    assert (a.rgb.float() - c.rgb.float()).abs().mean() > 10


def test_a_frame_has_the_parts_of_a_street(frames):
    f = frames[60]
    assert f.rgb.shape == (3, H, W) and f.rgb.dtype == torch.uint8
    assert f.depth.dtype == torch.float32 and f.instance.dtype == torch.int32
    assert len(REGION_NAMES) == 4
    # Sky at the top (far plane), road at the bottom, structure on the sides.
    assert (f.region[0] == REGION_FAR).float().mean() > 0.2
    assert torch.all(f.depth[f.region == REGION_FAR] > 40)
    assert (f.depth == FAR_PLANE).any()
    assert (f.region[-1] == REGION_ROAD).float().mean() > 0.8
    assert (f.region == REGION_STRUCTURE).float().mean() > 0.1
    bottom = f.depth[-1][f.region[-1] == REGION_ROAD]
    assert 2.0 < float(bottom.median()) < 8.0
    # Textured: the road near the camera has grain; the sky is smooth.
    grey = f.rgb.float().mean(0)
    road = grey[-12:, W // 3 : 2 * W // 3]
    assert float((road[:, 1:] - road[:, :-1]).abs().mean()) > 1.5
    assert torch.equal(f.instance >= 0, f.region == REGION_MOVING) or bool(
        (f.depth[(f.instance >= 0) & (f.region != REGION_MOVING)] > 80).all()
    )


def test_static_points_project_where_the_exact_flow_says(world, K, frames):
    src, tgt = frames[60], frames[62]
    flow = exact_flow(world, 60, 62, K, H, W, source=src, target=tgt)
    static = (src.instance < 0) & (src.region != REGION_FAR) & flow["flow_valid"]
    # The same static points, back-projected into the world and projected into the target
    # camera with the geometry module, land where the exact flow says.
    pts = geometry.backproject(src.depth.double()[None], K[None])[0]
    world_pts = pts @ world.poses[60][:3, :3].T + world.poses[60][:3, 3]
    to_tgt = geometry.invert_pose(world.poses[62])
    in_tgt = world_pts @ to_tgt[:3, :3].T + to_tgt[:3, 3]
    uv = geometry.project(in_tgt[None], K[None])[0]
    grid = torch.stack(torch.meshgrid(torch.arange(W), torch.arange(H), indexing="xy"), -1)
    expected = (uv - grid).permute(2, 0, 1)
    assert torch.allclose(flow["flow"].double()[:, static], expected[:, static], atol=1e-3)
    # ... and equals the reprojection flow of the rendered depth under the relative pose.
    rel = geometry.relative_pose(world.poses[60], world.poses[62])
    rigid = geometry.reprojection_flow(src.depth.double()[None], rel[None], K[None])[0]
    assert torch.allclose(flow["flow"][:, static], rigid[:, static].float())
    # The world persists: where the target camera sees those points, it renders their depth.
    seen = static & flow["visible"]
    assert seen.float().mean() > 0.5
    u = (grid[..., 0] + flow["flow"][0]).round().long().clamp(0, W - 1)
    v = (grid[..., 1] + flow["flow"][1]).round().long().clamp(0, H - 1)
    z = in_tgt[..., 2].float()
    rel_err = ((tgt.depth[v, u] - z).abs() / z)[seen]
    assert float(rel_err.median()) < 0.01


def test_warping_the_next_frame_back_reproduces_this_one(world, K, frames):
    for tgt in (61, 62):
        src = frames[60]
        flow = exact_flow(world, 60, tgt, K, H, W, source=src, target=frames[tgt])
        grid = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).astype(np.float32)
        maps = grid + flow["flow"].permute(1, 2, 0).numpy()
        image = frames[tgt].rgb.permute(1, 2, 0).numpy().astype(np.float32)
        warped = cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)
        gain = world.exposure[tgt] / world.exposure[60]
        # Compare where the point is seen in both frames, static, textured and near (not in the
        # distance fog), and away from depth edges (where bilinear sampling mixes surfaces).
        depth = src.depth.numpy()
        edge = cv2.dilate(
            (np.abs(cv2.Laplacian(np.log(depth), cv2.CV_32F)) > 0.05).astype(np.uint8),
            np.ones((3, 3)),
        )
        grey = src.rgb.float().mean(0).numpy()
        textured = (
            np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)) > 20
        )
        use = (
            flow["visible"].numpy()
            & (src.instance < 0).numpy()
            & (src.region != REGION_FAR).numpy()
            & (depth < 30)
            & ~edge.astype(bool)
            & textured
        )
        assert use.mean() > 0.05
        err = np.abs(warped / gain - src.rgb.permute(1, 2, 0).numpy())[use]
        assert np.median(err) < 3.0, (tgt, np.median(err))
        # Without the flow the frames differ: the comparison is not trivially satisfied.
        still = np.abs(image / gain - src.rgb.permute(1, 2, 0).numpy())[use]
        assert np.median(still) > 2 * np.median(err)


def test_moving_objects_move_by_their_own_motion(world):
    K2 = camera.kitti_like_intrinsics(48, 128)
    k = _frame_with_moving_object(world, K2)
    src = render_frame(world, k, K2, 48, 128)
    flow = exact_flow(world, k, k + 2, K2, 48, 128, source=src)
    mask = flow["object_mask"]
    assert mask.sum() > 10 and torch.equal(mask, (src.instance >= 0) & flow["flow_valid"])
    # Independently: each object point, carried by its object's pose change, projected.
    pts = geometry.backproject(src.depth.double()[None], K2[None])[0]
    world_pts = pts @ world.poses[k][:3, :3].T + world.poses[k][:3, 3]
    inst = src.instance.long().clamp_min(0)
    P0, P1 = world.object_poses(k)[inst], world.object_poses(k + 2)[inst]
    moved = torch.einsum("hwij,hwj->hwi", (P1 @ geometry.invert_pose(P0))[..., :3, :3], world_pts)
    moved = moved + (P1 @ geometry.invert_pose(P0))[..., :3, 3]
    to_tgt = geometry.invert_pose(world.poses[k + 2])
    uv = geometry.project((moved @ to_tgt[:3, :3].T + to_tgt[:3, 3])[None], K2[None])[0]
    grid = torch.stack(torch.meshgrid(torch.arange(128), torch.arange(48), indexing="xy"), -1)
    expected = (uv - grid).permute(2, 0, 1)
    assert torch.allclose(flow["flow"].double()[:, mask], expected[:, mask], atol=1e-3)
    # The objects' own share of the flow is what is left after the camera's.
    rel = geometry.relative_pose(world.poses[k], world.poses[k + 2])
    rigid = geometry.reprojection_flow(src.depth.double()[None], rel[None], K2[None])[0]
    assert torch.allclose(
        flow["object_flow"][:, mask], (flow["flow"] - rigid.float())[:, mask], atol=1e-4
    )
    assert float(flow["object_flow"][:, mask].norm(dim=0).median()) > 0.05
    assert torch.all(flow["object_flow"][:, ~mask] == 0)


def test_driving_a_real_kitti_trajectory_keeps_the_road_under_the_camera(shared_poses):
    poses = torch.from_numpy(read_kitti_poses(shared_poses / "00.txt"))[:400]
    world = World.generate(poses, seed=0, name="00")
    h, w = 48, 128
    K = camera.kitti_like_intrinsics(h, w)
    for k in range(0, len(poses), 16):
        f = render_frame(world, k, K, h, w)
        # Ground under the camera (a car in the next lane may cover part of the bottom row).
        bottom = f.region[-1, w // 4 : 3 * w // 4] == REGION_ROAD
        assert bottom.float().mean() > 0.75 and f.region[-1, w // 2] == REGION_ROAD, k
        assert 2.5 < float(f.depth[-1, w // 4 : 3 * w // 4][bottom].median()) < 10.0, k
        assert (f.region[: h // 4] == REGION_FAR).float().mean() > 0.05, k


def test_any_size_renders_and_impossible_sizes_are_refused(world):
    f = render_frame(world, 10, camera.kitti_like_intrinsics(20, 60), 20, 60)
    assert f.rgb.shape == (3, 20, 60)
    K = camera.kitti_like_intrinsics(H, W)
    for h, w in ((8, 64), (64, 10), (0, 0), (64, 5000), (64.5, 128)):
        with pytest.raises(ValueError, match=f"render size {h} x {w}"):
            render_frame(world, 10, K, h, w)
        with pytest.raises(ValueError, match=f"render size {h} x {w}"):
            exact_flow(world, 10, 11, K, h, w)
    with pytest.raises(ValueError, match="frame 120 is outside trajectory 'r'"):
        render_frame(world, 120, K, H, W)
    with pytest.raises(ValueError, match="intrinsics"):
        render_frame(world, 0, torch.tensor([1.0, 2.0, 3.0]), H, W)


def test_the_picture_grid_takes_extra_panels(frames, world, K):
    flow = exact_flow(world, 60, 61, K, H, W, source=frames[60])
    extra = [("estimated flow", np.zeros((H, W, 3), np.uint8))]
    columns = [frame_panels(frames[60], flow, extra), frame_panels(frames[61], None, extra)[:5]]
    columns[1].insert(1, ("no flow", np.zeros((H, W, 3), np.uint8)))
    image = picture_grid(columns, headers=["a", "b"])
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[0] > 5 * H
    assert [t for t, _ in columns[0]][-1] == "estimated flow"
    with pytest.raises(ValueError, match="same, non-zero number of panels"):
        picture_grid([columns[0], columns[1][:2]])


def test_a_frame_that_sees_no_box_renders_road_and_sky():
    """An open stretch of road (no facade, parked box or mover in view) renders, and its exact
    flow is defined: KITTI 09's world has such frames."""
    from mfg_lightning.scene.worlds import WorldConfig

    poses = camera.procedural_trajectory(seeding.seeded_rng(5, "trajectory", "r"), 12)
    empty = WorldConfig(
        facade_coverage=0.0, parked_per_100m=0.0, cars_per_100m=0.0, pedestrians_per_100m=0.0
    )
    world = World.generate(poses, seed=5, name="open", config=empty)
    K = camera.kitti_like_intrinsics(48, 128)
    f = render_frame(world, 3, K, 48, 128)
    assert (f.instance == -1).all()
    assert set(f.region.unique().tolist()) <= {REGION_ROAD, REGION_FAR}
    flow = exact_flow(world, 3, 4, K, 48, 128)
    assert flow["flow_valid"].any() and torch.isfinite(flow["flow"][:, flow["flow_valid"]]).all()
