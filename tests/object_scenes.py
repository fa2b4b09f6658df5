"""Oracle driving frames for the object-motion tests: a KITTI-like camera, static and moving
boxes ray-cast by a slow reference, exact flow and the oracle fields (batch of 1)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from mfg_lightning.core import geometry

REPO = Path(__file__).resolve().parents[1]
KITTI_K = torch.tensor([718.856, 718.856, 607.1928, 185.2157], dtype=torch.float64)
KITTI_SIZE = (376, 1241)
FAR_PLANE = 655.35
CAMERA_HEIGHT = 1.65
SKY, GROUND = -1, -2

# Axis-aligned boxes (x0, x1, y0, y1, z0, z1) in camera-k coordinates (m; x right, y down,
# z forward; the ground is y = +1.65).
STATIC_BOXES = [
    (-14.0, -8.0, -8.0, CAMERA_HEIGHT, 8.0, 45.0),  # facades on the left
    (7.0, 10.0, -6.0, CAMERA_HEIGHT, 5.0, 18.0),  # a near facade on the right
    (3.0, 4.8, 0.15, CAMERA_HEIGHT, 6.5, 10.5),  # a parked car close by
    (-4.0, -2.2, 0.2, CAMERA_HEIGHT, 25.0, 29.0),  # a parked car ahead
]
# (box, displacement over one frame in m): the paper's claim is about all of these at once.
MOVING = {
    "oncoming car": ((-3.6, -1.8, 0.2, CAMERA_HEIGHT, 12.0, 16.0), (0.0, 0.0, -1.2)),
    "crossing car": ((1.0, 2.8, 0.2, CAMERA_HEIGHT, 22.0, 26.0), (-0.6, 0.0, 0.8)),
    "small distant car": ((-1.0, 0.8, 0.3, CAMERA_HEIGHT, 60.0, 64.0), (0.7, 0.0, 0.3)),
    "slow pedestrian": ((3.0, 3.6, -0.05, CAMERA_HEIGHT, 19.0, 19.5), (-0.1, 0.0, 0.0)),
}


@dataclass
class Frame:
    """A synthetic frame: inputs of the pipeline plus ground truth (batch of 1)."""

    flow: torch.Tensor  # (1, 2, H, W) exact reprojection flow with moving objects
    rigid_flow: torch.Tensor  # (1, 2, H, W) exact flow of the static scene
    v_t: torch.Tensor  # (1, 2, H, W) oracle translational field at unit inverse depth
    v_w: torch.Tensor  # (1, 2, H, W) oracle rotational field
    depth: torch.Tensor  # (1, H, W) metres
    gt_mask: torch.Tensor  # (1, H, W) moving-object pixels
    surface: torch.Tensor  # (1, H, W) SKY, GROUND or the index into the box list
    names: list[str]  # box index → name ("static" for static boxes)


def kitti_intrinsics(height: int, width: int) -> torch.Tensor:
    return geometry.scale_intrinsics(KITTI_K, width / KITTI_SIZE[1], height / KITTI_SIZE[0])


def ray_cast(boxes: list[tuple], K: torch.Tensor, height: int, width: int):
    """Depth and surface index of the first hit of every pixel ray (ground, boxes, far plane).

    A ray through normalised coordinates (x, y) is (x, y, 1)·z, so the slab parameter is depth.
    """
    xy = geometry.normalized_grid(K[None], height, width)[0]
    direction = torch.stack([xy[0], xy[1], torch.ones_like(xy[0])])  # (3, H, W)
    depth = torch.full((height, width), FAR_PLANE, dtype=torch.float64)
    surface = torch.full((height, width), SKY, dtype=torch.long)
    ground = torch.where(xy[1] > 0, CAMERA_HEIGHT / xy[1].clamp_min(1e-12), math.inf)
    hit = ground < depth
    depth, surface = torch.where(hit, ground, depth), torch.where(hit, GROUND, surface)
    safe = torch.where(direction.abs() > 1e-12, direction, torch.full_like(direction, 1e-12))
    for i, box in enumerate(boxes):
        lo = torch.tensor(box[0::2], dtype=torch.float64)[:, None, None] / safe
        hi = torch.tensor(box[1::2], dtype=torch.float64)[:, None, None] / safe
        enter = torch.minimum(lo, hi).amax(0)
        leave = torch.maximum(lo, hi).amin(0)
        hit = (enter <= leave) & (enter > 0) & (enter < depth)
        depth, surface = torch.where(hit, enter, depth), torch.where(hit, i, surface)
    return depth, surface


def make_frame(speed: float, height: int = 96, width: int = 256, yaw: float = 0.01) -> Frame:
    """A KITTI-like driving frame: camera driving forward ``speed`` m/frame with a small yaw."""
    K = kitti_intrinsics(height, width)
    boxes = STATIC_BOXES + [box for box, _ in MOVING.values()]
    names = ["static"] * len(STATIC_BOXES) + list(MOVING)
    depth, surface = ray_cast(boxes, K, height, width)
    t = torch.tensor([[0.05 * speed, 0.0, speed]], dtype=torch.float64)
    w = torch.tensor([[0.0, yaw, 0.0]], dtype=torch.float64)
    pose = geometry.motion_to_pose(t, w)
    displacement = torch.zeros(1, height, width, 3, dtype=torch.float64)
    gt = torch.zeros(1, height, width, dtype=torch.bool)
    for i, (_, motion) in enumerate(MOVING.values(), start=len(STATIC_BOXES)):
        on = surface[None] == i
        displacement[on] = torch.tensor(motion, dtype=torch.float64)
        gt |= on
    flow = geometry.reprojection_flow(depth[None], pose, K[None], point_motion=displacement)
    rigid = geometry.reprojection_flow(depth[None], pose, K[None])
    return Frame(
        flow=flow.float(),
        rigid_flow=rigid.float(),
        v_t=geometry.translational_field(t, K, height, width).float(),
        v_w=geometry.rotational_field(w, K, height, width).float(),
        depth=depth[None].float(),
        gt_mask=gt,
        surface=surface[None],
        names=names,
    )


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum()) / max(float((a | b).sum()), 1.0)
