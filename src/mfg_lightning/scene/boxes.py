"""The per-frame box scene of ``flow=exact``: facades, parked and moving boxes drawn anew for
every frame in front of the camera, ray-cast, with the exact flow of one camera motion."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from mfg_lightning.core import geometry
from mfg_lightning.scene.camera import CAMERA_HEIGHT
from mfg_lightning.scene.raycast import ray_cast_grid

# Surface classes, for the RGB rendering and for telling moving pixels apart.
SKY, GROUND, BUILDING, PARKED, MOVING = 0, 1, 2, 3, 4


_COLOURS = np.array(
    [[135, 190, 235], [110, 110, 110], [170, 130, 100], [60, 90, 170], [210, 50, 40]],
    dtype=np.float32,
)


@dataclass(frozen=True)
class SceneConfig:
    """Ranges of the procedural scene (metres, metres per frame at 10 Hz).

    Attributes:
        buildings_per_side: maximum number of facade boxes on each side of the road.
        building_distance: lateral distance range of the facades from the camera.
        parked_boxes: maximum number of static car-sized boxes.
        moving_objects: maximum number of independently moving objects.
        object_speed: maximum speed of moving cars; pedestrians move at up to a tenth of it.
        pedestrian_fraction: probability that a moving object is a pedestrian.
    """

    buildings_per_side: int = 4
    building_distance: tuple[float, float] = (5.0, 15.0)
    parked_boxes: int = 6
    moving_objects: int = 4
    object_speed: float = 1.5
    pedestrian_fraction: float = 0.25


def sample_boxes(
    rng: np.random.Generator, cfg: SceneConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of one scene in camera coordinates (x right, y down, z forward).

    Returns:
        ``(boxes, kinds, motion)``: ``(K, 2, 3)`` min and max corners, ``(K,)`` surface class,
        ``(K, 3)`` displacement of each box over one frame (zero for static ones).
    """
    h = CAMERA_HEIGHT
    boxes, kinds, motion = [], [], []
    for side in (-1.0, 1.0):
        z = rng.uniform(-5.0, 10.0)
        for _ in range(rng.integers(0, cfg.buildings_per_side + 1)):
            length = rng.uniform(8.0, 40.0)
            near = rng.uniform(*cfg.building_distance)
            depth = rng.uniform(6.0, 15.0)
            top = h - rng.uniform(4.0, 20.0)
            x0, x1 = sorted((side * near, side * (near + depth)))
            boxes.append([[x0, top, z], [x1, h, z + length]])
            kinds.append(BUILDING)
            motion.append([0.0, 0.0, 0.0])
            z += length + rng.uniform(0.0, 12.0)
    for _ in range(rng.integers(0, cfg.parked_boxes + 1)):
        side = rng.choice([-1.0, 1.0])
        x = side * rng.uniform(2.5, 5.0)
        z = rng.uniform(4.0, 60.0)
        boxes.append([[x - 0.9, h - 1.5, z], [x + 0.9, h, z + 4.2]])
        kinds.append(PARKED)
        motion.append([0.0, 0.0, 0.0])
    for _ in range(rng.integers(0, cfg.moving_objects + 1)):
        if rng.random() < cfg.pedestrian_fraction:
            size = np.array([0.6, 1.75, 0.6])
            speed = rng.uniform(0.02, 0.15) * cfg.object_speed
            heading = rng.uniform(0, 2 * np.pi)
            d = [speed * np.cos(heading), 0.0, speed * np.sin(heading)]
            x, z = rng.uniform(-7.0, 7.0), rng.uniform(5.0, 40.0)
        else:
            size = np.array([1.8, 1.5, 4.2])
            # Oncoming or same-direction traffic, occasionally crossing.
            if rng.random() < 0.2:
                d = [rng.choice([-1, 1]) * rng.uniform(0.2, 1.0) * cfg.object_speed, 0.0, 0.0]
            else:
                d = [rng.normal(0, 0.05), 0.0, rng.uniform(-1.0, 1.0) * cfg.object_speed]
            x, z = rng.uniform(-7.0, 7.0), rng.uniform(6.0, 70.0)
        lo = np.array([x - size[0] / 2, h - size[1], z])
        boxes.append([lo, lo + size])
        kinds.append(MOVING)
        motion.append(d)
    if not boxes:
        return np.zeros((0, 2, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    return (
        np.asarray(boxes, dtype=np.float64),
        np.asarray(kinds),
        np.asarray(motion, dtype=np.float64),
    )


def render_sample(
    rel_pose: torch.Tensor,
    intrinsics: torch.Tensor,
    height: int,
    width: int,
    rng: np.random.Generator,
    scene: SceneConfig,
    noise_std: float,
    outlier_fraction: float,
) -> dict[str, torch.Tensor]:
    """Draw a scene, ray-cast it and compute the exact flow for one camera motion.

    Args:
        rel_pose: ``(4, 4)`` float64 ``T_src,tgt``.
        intrinsics: ``(4,)`` float64 pixels at ``height × width``.
        noise_std: standard deviation of the Gaussian flow noise, pixels.
        outlier_fraction: fraction of pixels whose flow is replaced by a uniform random vector.

    Returns:
        The tensor fields of a sample (float32, bool, uint8) — see :mod:`..sample`.
    """
    boxes, kinds, motion = sample_boxes(rng, scene)
    K = intrinsics[None]
    xy = geometry.normalized_grid(K, height, width)[0]
    depth, hit = ray_cast_grid(xy[0, 0], xy[1, :, 0], torch.from_numpy(boxes))
    depth = depth[None]
    # Per-surface lookup tables indexed by ``surface``: box k at row k, then one row for the
    # ground and one for the sky. One gather per table replaces boolean-mask indexing.
    n_box = boxes.shape[0]
    surface = torch.where(hit >= 0, hit, n_box + (hit == -2).long())  # (H, W)
    box_motion = torch.from_numpy(motion)
    displacement = torch.cat([box_motion, box_motion.new_zeros(2, 3)])[surface]  # (H, W, 3)
    moving = torch.cat([box_motion.norm(dim=-1) > 0, torch.zeros(2, dtype=torch.bool)])
    object_mask = moving[surface]
    if bool(object_mask.any()):
        # The rigid flow and the flow with the objects' displacement in one batched call (the
        # same numbers as two calls, bit for bit; the reprojection is the costliest step left).
        rigid, flow = geometry.reprojection_flow(
            depth.expand(2, -1, -1),
            rel_pose[None].expand(2, -1, -1),
            K.expand(2, -1),
            torch.stack([torch.zeros_like(displacement), displacement]),
        )
    else:
        # Nothing moves in view: the displacement is zero everywhere and the flow is the rigid one.
        rigid = flow = geometry.reprojection_flow(depth, rel_pose[None], K)[0]
    object_flow = torch.where(object_mask[None], flow - rigid, torch.zeros_like(flow))

    # Points that end up behind the target camera have no meaningful flow.
    limit = 2.0 * max(height, width)
    valid = torch.isfinite(flow).all(0) & (flow.abs().amax(0) < limit)
    noisy = flow + noise_std * torch.from_numpy(rng.standard_normal(flow.shape))
    if outlier_fraction > 0:
        outliers = torch.from_numpy(rng.random((height, width)) < outlier_fraction)
        random_flow = torch.from_numpy(
            rng.uniform(-1, 1, flow.shape)
        ) * flow.abs().amax().clamp_min(1.0)
        noisy = torch.where(outliers[None], random_flow, noisy)
    noisy = torch.where(valid[None], noisy, torch.zeros_like(noisy))

    kind = torch.cat([torch.from_numpy(kinds).long(), torch.tensor([GROUND, SKY])])[surface]
    shade = (1.0 - 0.6 * (depth[0].clamp(max=80.0) / 80.0)).numpy()[..., None]
    shade[kind.numpy() == SKY] = 1.0
    rgb = (_COLOURS[kind.numpy()] * shade).clip(0, 255).astype(np.uint8)
    return {
        "flow": noisy.float(),
        "flow_valid": valid,
        "depth": depth[0].float(),
        "object_mask": object_mask & valid,
        "object_flow": object_flow.float(),
        "rgb": torch.from_numpy(rgb).permute(2, 0, 1).contiguous(),
    }
