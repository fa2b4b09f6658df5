"""The exact optical flow between two frames of a persistent world, from the source frame's
rendered depth and moving-object instances.

Every source pixel is back-projected with its depth; points on a moving object move rigidly
with it (its pose at the target frame times the inverse of its pose at the source frame);
everything is re-projected into the target camera
(:func:`mfg_lightning.core.geometry.reprojection_flow`). :func:`.render.exact_flow` is the
public entry point (it renders the source frame when it is not given).
"""

from __future__ import annotations

import torch
from torch import Tensor

from mfg_lightning.core import geometry
from mfg_lightning.scene.clipping import NEAR
from mfg_lightning.scene.worlds import World

__all__ = ["flow_from_depth"]


def flow_from_depth(
    world: World,
    src: int,
    tgt: int,
    K: Tensor,
    depth: Tensor,
    instance: Tensor,
    target_depth: Tensor | None = None,
) -> dict[str, Tensor]:
    """The exact optical flow from frame ``src`` to frame ``tgt`` of a rendered source frame.

    Args:
        world: the persistent world.
        src, tgt: frame indices (checked by the caller).
        K: ``(4,)`` float64 ``(fx, fy, cx, cy)`` pixels.
        depth: ``(H, W)`` float32 source depth (metres, the rendered frame's).
        instance: ``(H, W)`` int32 moving-object instance of every source pixel (-1: none).
        target_depth: ``(H, W)`` float32 rendered depth of the target frame; when given, adds
            ``"visible"``.

    Returns:
        As :func:`.render.exact_flow`: ``"flow"``, ``"flow_valid"``, ``"object_mask"``,
        ``"object_flow"``, ``"depth"`` (``depth`` itself), and with ``target_depth``
        ``"visible"``.
    """
    height, width = depth.shape
    T_src, T_tgt = world.poses[src], world.poses[tgt]
    rel = geometry.relative_pose(T_src, T_tgt)
    depth64 = depth.double()[None]
    inst = instance.long()
    moving = inst >= 0
    motion = torch.zeros(1, height, width, 3, dtype=torch.float64)
    if bool(moving.any()):
        motion[0][moving] = _object_motion(world, src, tgt, K, depth64, inst, moving)
        # The rigid flow and the flow with the objects' motion in one batched call (the same
        # numbers as two calls, bit for bit).
        rigid, flow = geometry.reprojection_flow(
            depth64.expand(2, -1, -1),
            rel[None].expand(2, -1, -1),
            K[None].expand(2, -1),
            torch.cat([torch.zeros_like(motion), motion]),
        )
    else:
        rigid = flow = geometry.reprojection_flow(depth64, rel[None], K[None])[0]
    # Depth of every point in the target camera: behind it, the flow means nothing.
    X = geometry.backproject(depth64, K[None])[0] + motion[0]
    to_tgt = geometry.invert_pose(rel)  # camera-src points → camera-tgt points
    z_tgt = X @ to_tgt[2, :3] + to_tgt[2, 3]
    limit = 2.0 * max(height, width)
    valid = torch.isfinite(flow).all(0) & (flow.abs().amax(0) < limit) & (z_tgt > NEAR)
    object_mask = moving & valid
    object_flow = torch.where(object_mask[None], flow - rigid, torch.zeros_like(flow))
    out = {
        "flow": flow.float(),
        "flow_valid": valid,
        "object_mask": object_mask,
        "object_flow": object_flow.float(),
        "depth": depth,
    }
    if target_depth is not None:
        out["visible"] = _visible(flow, valid, z_tgt, target_depth)
    return out


def _object_motion(
    world: World,
    src: int,
    tgt: int,
    K: Tensor,
    depth: Tensor,
    inst: Tensor,
    moving: Tensor,
) -> Tensor:
    """Displacement ``(n, 3)`` (metres, source camera coordinates) of the ``n`` source pixels
    on moving objects (``moving``, ``(H, W)`` bool; ``inst`` ``(H, W)`` long their instances;
    ``depth`` ``(1, H, W)`` float64 metres) from ``src`` to ``tgt``."""
    # M = T_cam,world(src) · T_world,obj(tgt) · T_obj,world(src) · T_world,cam(src): the
    # object's rigid motion written in the source camera's coordinates.
    T_src = world.poses[src]
    ids, local = torch.unique(inst[moving], return_inverse=True)
    P_src, P_tgt = world.object_poses(src)[ids], world.object_poses(tgt)[ids]
    M = geometry.invert_pose(T_src) @ P_tgt @ geometry.invert_pose(P_src) @ T_src
    points = geometry.backproject(depth, K[None])[0][moving]  # (n, 3)
    moved = torch.einsum("nij,nj->ni", M[local, :3, :3], points) + M[local, :3, 3]
    return moved - points


def _visible(flow: Tensor, valid: Tensor, z_tgt: Tensor, target_depth: Tensor) -> Tensor:
    """Whether each source point lands inside the target image and is not occluded there: its
    depth in the target camera (``z_tgt``, ``(H, W)`` metres) is at most 2 % + 5 cm behind the
    target's rendered depth at the nearest pixel (``flow`` ``(2, H, W)`` float64 pixels;
    ``valid`` ``(H, W)`` bool). ``(H, W)`` bool."""
    height, width = valid.shape
    grid_u = torch.arange(width, dtype=torch.float64)[None]
    grid_v = torch.arange(height, dtype=torch.float64)[:, None]
    u = (grid_u + flow[0]).round()
    v = (grid_v + flow[1]).round()
    inside = valid & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    ui = u.clamp(0, width - 1).long()
    vi = v.clamp(0, height - 1).long()
    there = target_depth.double()[vi, ui]
    return inside & (z_tgt <= there * 1.02 + 0.05)
