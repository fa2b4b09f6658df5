"""The camera rig of the synthetic scenes: KITTI's left colour camera (intrinsics, 1.65 m above
the ground), the far plane (655.35 m, as Virtual KITTI) and procedural driving trajectories."""

from __future__ import annotations

import numpy as np
import torch

from mfg_lightning.core import geometry

#: KITTI odometry sequences 00–02 at full resolution (formats.md): fx, fy, cx, cy, width, height.
KITTI_INTRINSICS = (718.856, 718.856, 607.1928, 185.2157, 1241, 376)


FAR_PLANE = 655.35


CAMERA_HEIGHT = 1.65


def kitti_like_intrinsics(height: int, width: int) -> torch.Tensor:
    """KITTI's left colour camera intrinsics scaled to ``height × width``. ``(4,)`` pixels."""
    fx, fy, cx, cy, w0, h0 = KITTI_INTRINSICS
    return geometry.scale_intrinsics(
        torch.tensor([fx, fy, cx, cy], dtype=torch.float64), width / w0, height / h0
    )


def procedural_trajectory(rng: np.random.Generator, length: int) -> torch.Tensor:
    """A continuous driving trajectory from a smooth random driving model.

    Speed, yaw rate, pitch, roll and vertical bumps follow AR(1) processes, so consecutive
    motions are correlated as in real driving (stops, turns, straight stretches).

    Returns:
        ``(length, 4, 4)`` float64 camera-to-world poses ``T_world_cam``, starting at identity.
    """
    speed = rng.uniform(0.2, 1.4)
    yaw = pitch = roll = bump = 0.0
    motions = np.zeros((length - 1, 6))
    for k in range(length - 1):
        speed = float(np.clip(0.98 * speed + 0.02 * 0.8 + rng.normal(0, 0.04), 0.0, 1.6))
        yaw = 0.92 * yaw + rng.normal(0, 0.006)
        pitch = 0.7 * pitch + rng.normal(0, 0.0015)
        roll = 0.7 * roll + rng.normal(0, 0.001)
        bump = 0.6 * bump + rng.normal(0, 0.004)
        # The car moves along the chord of its turn: a little sideways when it yaws.
        motions[k] = [speed * np.sin(yaw / 2), bump, speed * np.cos(yaw / 2), pitch, yaw, roll]
    rel = geometry.motion_to_pose(
        torch.from_numpy(motions[:, :3]), torch.from_numpy(motions[:, 3:])
    )
    return geometry.trajectory_from_motions(rel)
