"""Persistent worlds: reproducible, furnished clear of the road, ground under the camera."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mfg_lightning.scene import camera, seeding
from mfg_lightning.scene.crossing import CrossingConfig, split_world_fields, with_crossings
from mfg_lightning.scene.worlds import (
    CAR,
    FACADE,
    PEDESTRIAN,
    SECTION,
    World,
    WorldConfig,
)
from mfg_lightning.trajectory.pose_io import read_kitti_poses


@pytest.fixture(scope="module")
def poses() -> torch.Tensor:
    return camera.procedural_trajectory(seeding.seeded_rng(3, "trajectory", "w"), 300)


@pytest.fixture(scope="module")
def world(poses) -> World:
    return World.generate(poses, seed=3, name="w")


def _same_boxes(a: World, b: World) -> bool:
    return all(
        np.array_equal(getattr(a.static, f), getattr(b.static, f))
        for f in ("centre", "yaw", "half", "kind", "colour", "params")
    )


def test_a_world_is_a_function_of_seed_and_name(poses, world):
    again = World.generate(poses.clone(), seed=3, name="w")
    assert _same_boxes(world, again)
    assert torch.equal(world.object_poses(17), again.object_poses(17))
    assert np.array_equal(world.exposure, again.exposure)
    assert np.array_equal(world.static_boxes(120)[1], again.static_boxes(120)[1])
    for other in (World.generate(poses, 4, "w"), World.generate(poses, 3, "x")):
        assert not _same_boxes(world, other)
        assert not np.array_equal(world.exposure, other.exposure)


def test_the_world_holds_every_kind_of_thing(world):
    kinds = set(world.static.kind.tolist())
    assert FACADE in kinds and len(kinds) >= 2
    assert {CAR, PEDESTRIAN} <= set(world.moving.boxes.kind.tolist())
    # About 0.8 of each side's length lined with facades of 8–30 m.
    length = world.path_s[-1] - world.path_s[0]
    assert 0.5 * length / 30 < (world.static.kind == FACADE).sum() < 2 * 2 * length / 8


def test_moving_objects_follow_continuous_paths_at_their_own_speed(world):
    a, b, half = world.object_poses(40), world.object_poses(41), world.object_poses(40.5)
    # Every object advances along the road at its own speed (arc length of the centreline).
    advance = world.object_arc(41) - world.object_arc(40)
    np.testing.assert_allclose(advance, world.moving.direction * world.moving.speed, atol=1e-9)
    step = (b[:, :3, 3] - a[:, :3, 3])[:, [0, 2]].norm(dim=1).numpy()
    lateral = np.abs(world.moving.lateral)
    assert np.all(np.abs(step - world.moving.speed) <= 0.1 * lateral * world.moving.speed + 1e-3)
    mid = (a[:, :3, 3] + b[:, :3, 3]) / 2
    assert (half[:, :3, 3] - mid)[:, [0, 2]].norm(dim=1).max() < 0.02
    # Headings turn smoothly; cars drive both ways.
    assert (a[:, :3, 2] * b[:, :3, 2]).sum(1).min() > 0.99
    cars = world.moving.boxes.kind == CAR
    assert set(world.moving.direction[cars].tolist()) == {-1.0, 1.0}


def test_crossing_objects_cross_the_road_and_leave_the_others_as_they_were(poses, world):
    """with_crossings adds objects that move across the road, back and forth between the
    building lines at their own speed, facing across it; the other objects do not change."""
    crossed = with_crossings(world, CrossingConfig(per_100m=8.0))
    n, m = len(world.moving), crossed.moving
    assert len(m) > n and not crossed.crosses[:n].any() and crossed.crosses[n:].all()
    assert torch.equal(crossed.object_poses(40)[:n], world.object_poses(40))
    assert np.array_equal(crossed.object_arc(40)[:n], world.object_arc(40))
    assert torch.equal(world.object_poses(40), World.generate(poses, 3, "w").object_poses(40))
    frames = np.arange(0.0, 120.0)
    lateral = np.stack([crossed.object_lateral(f) for f in frames])
    # within the building lines, moving at their speed except across a turn
    assert np.abs(lateral).max() <= world.config.building_line + 1e-9
    step = np.abs(np.diff(lateral, axis=0))
    assert (step > 0.999 * m.speed[n:]).mean() > 0.9 and np.all(step <= m.speed[n:] + 1e-9)
    # the same arc length at every frame; facing across the road, horizontally
    assert np.array_equal(crossed.object_arc(0)[n:], crossed.object_arc(99)[n:])
    a, b = crossed.object_poses(40)[n:], crossed.object_poses(41)[n:]
    move = (b[:, :3, 3] - a[:, :3, 3])[:, [0, 2]]
    across = move / move.norm(dim=1, keepdim=True)
    assert (across * a[:, :3, 2][:, [0, 2]]).sum(1).abs().min() > 0.98
    # a size factor of crossing_scale (0.2-1.2) on a car's or a pedestrian's
    assert m.boxes.half[n:, 1].min() < m.boxes.half[:n, 1].min()


def test_crossings_are_dataset_world_keys_checked_like_the_worlds_own() -> None:
    own, crossing = split_world_fields({"lanes_per_side": 2, "crossing_per_100m": 4,
                                        "crossing_speed": [0.1, 1.0]})  # fmt: skip
    assert own == {"lanes_per_side": 2} and crossing == CrossingConfig(4, (0.1, 1.0))
    assert split_world_fields({"lanes_per_side": 2})[1] is None
    with pytest.raises(ValueError, match=r"crossing_scale must be a range 0 < lo <= hi"):
        split_world_fields({"crossing_per_100m": 4, "crossing_scale": [0.0, 1.0]})


def test_objects_stand_on_the_ground(world):
    frame = 150
    ground = world.ground(frame)
    poses = world.object_poses(frame)
    m = world.moving
    centre = poses[:, :3, 3]
    gy = ground.height(centre[:, 0], centre[:, 2])[0].numpy()
    np.testing.assert_allclose(centre[:, 1].numpy() + m.boxes.base, gy, atol=1e-6)
    index, centre = world.static_boxes(frame)
    gy = ground.height(torch.from_numpy(centre[:, 0]), torch.from_numpy(centre[:, 2]))[0]
    np.testing.assert_allclose(centre[:, 1] + world.static.base[index], gy.numpy(), atol=1e-6)


def test_static_boxes_keep_clear_of_the_road(world):
    cfg = world.config
    for frame in (0, 150, 299):
        ground = world.ground(frame)
        index, centre = world.static_boxes(frame)
        half = world.static.half[index]
        yaw = world.static.yaw[index]
        # The four footprint corners of every box, in world x, z.
        corners = []
        for sa, sb in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            ax, az = sa * half[:, 0], sb * half[:, 2]
            corners.append(
                np.stack(
                    [
                        centre[:, 0] + np.cos(yaw) * ax + np.sin(yaw) * az,
                        centre[:, 2] - np.sin(yaw) * ax + np.cos(yaw) * az,
                    ],
                    -1,
                )
            )
        xz = torch.from_numpy(np.concatenate(corners))
        _, _, dist = ground.road_coordinates(xz[:, 0], xz[:, 1])
        assert float(dist.min()) > cfg.road_half_width
        facades = np.tile(world.static.kind[index] == FACADE, 4)
        assert float(dist[torch.from_numpy(facades)].min()) > cfg.building_line - 0.5


def test_the_ground_is_under_the_camera_of_a_procedural_drive(poses, world):
    pos = poses[:, :3, 3]
    heights = [
        float(world.ground_height(pos[k : k + 1, 0], pos[k : k + 1, 2], k)[0][0] - pos[k, 1])
        for k in range(0, len(poses), 10)
    ]
    np.testing.assert_allclose(heights, camera.CAMERA_HEIGHT, atol=0.08)


def test_the_ground_follows_a_real_kitti_trajectory(shared_poses):
    poses = torch.from_numpy(read_kitti_poses(shared_poses / "00.txt"))[:500]
    world = World.generate(poses, seed=0, name="00")
    pos = poses[:, :3, 3]
    frames = range(0, len(poses), 10)
    heights = np.array(
        [
            float(world.ground_height(pos[k : k + 1, 0], pos[k : k + 1, 2], k)[0][0] - pos[k, 1])
            for k in frames
        ]
    )
    # Hills and pitch are followed; the ground is not a plane (KITTI 00 climbs 10 m here).
    assert np.abs(heights - camera.CAMERA_HEIGHT).max() < 0.25
    assert np.ptp(pos[:, 1].numpy()) > 5
    assert world.num_sections == int(np.ceil(world.frame_s.max() / SECTION))


def test_bad_poses_and_settings_are_refused():
    with pytest.raises(ValueError, match=r"\(N, 4, 4\).*\(5, 3, 4\)"):
        World.generate(torch.zeros(5, 3, 4), 0, "x")
    bad = torch.eye(4).repeat(3, 1, 1)
    bad[1, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="'x' has non-finite poses"):
        World.generate(bad, 0, "x")
    with pytest.raises(ValueError, match="lane_width"):
        WorldConfig(lane_width=0.0)
    with pytest.raises(ValueError, match="car_speed"):
        WorldConfig(car_speed=(2.0, 1.0))


def test_a_standing_car_gets_a_straight_road():
    world = World.generate(torch.eye(4, dtype=torch.float64).repeat(4, 1, 1), 1, "still")
    heading = world.path_dir
    assert np.allclose(heading, heading[0]) and np.allclose(heading[0], [0.0, 1.0])
    y, _, _ = world.ground_height(torch.tensor([0.0]), torch.tensor([0.0]))
    assert float(y[0]) == pytest.approx(camera.CAMERA_HEIGHT, abs=1e-3)


def test_sections_agree_around_the_camera_where_they_switch(poses, world):
    switches = [k for k in range(1, len(poses)) if world.section_of(k) != world.section_of(k - 1)]
    assert switches
    for k in switches:
        before, after = world.ground(k - 1), world.ground(k)
        assert before is not after
        c = poses[k, :3, 3].float()
        xs = c[0] + torch.linspace(-20, 20, 41).repeat_interleave(41)
        zs = c[2] + torch.linspace(-20, 20, 41).repeat(41)
        assert float((before.height(xs, zs)[0] - after.height(xs, zs)[0]).abs().max()) < 0.01
        pairs = zip(before.road_coordinates(xs, zs), after.road_coordinates(xs, zs), strict=True)
        for a, b in pairs:
            assert torch.allclose(a, b, atol=1e-3)
