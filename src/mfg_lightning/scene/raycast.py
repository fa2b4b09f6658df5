"""Ray casting against a ground plane and axis-aligned boxes (the slab method), shared by the
per-frame box scene (:mod:`.boxes`) and the persistent worlds' renderer."""

from __future__ import annotations

import numpy as np
import torch

from mfg_lightning.scene.camera import CAMERA_HEIGHT, FAR_PLANE


def reciprocal(r: torch.Tensor) -> torch.Tensor:
    """``1 / r``, components below 1e-12 in magnitude taken as 1e-12 (a ray parallel to a slab
    then gets a huge but finite parameter instead of a division by zero)."""
    return 1.0 / torch.where(r.abs() < 1e-12, torch.full_like(r, 1e-12), r)


def ray_cast(rays: torch.Tensor, boxes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First hit of every ray against a ground plane and axis-aligned boxes (slab method).

    Rays are ``(x, y, 1)`` through normalised image coordinates, so the ray parameter of a hit
    *is* its depth along z. This is the general form for any set of rays; the renderer uses
    :func:`ray_cast_grid`, which gives the same result for the rays of a pixel grid.

    Args:
        rays: ``(N, 3)`` ray directions with z = 1.
        boxes: ``(K, 2, 3)`` min/max corners in camera coordinates (metres).

    Returns:
        ``(depth, hit)``: ``(N,)`` depth in metres (the far plane where nothing is hit) and
        ``(N,)`` index of the surface hit: −2 sky, −1 ground, k ≥ 0 box k.
    """
    n = rays.shape[0]
    depth = torch.full((n,), FAR_PLANE, dtype=rays.dtype)
    hit = torch.full((n,), -2, dtype=torch.long)
    down = rays[:, 1] > 1e-9
    ground = torch.where(
        down, CAMERA_HEIGHT / rays[:, 1].clamp_min(1e-9), torch.full_like(depth, np.inf)
    )
    on_ground = ground < depth
    depth = torch.where(on_ground, ground, depth)
    hit[on_ground] = -1
    if boxes.shape[0]:
        inv = reciprocal(rays)
        # One (N, K) slab interval per axis; the entry and exit are their max and min. Taking
        # them axis by axis (rather than reducing a (N, K, 3) tensor over its short last
        # dimension) is several times faster and gives the same numbers (max/min are exact).
        bounds = boxes.permute(1, 2, 0)  # (2, 3, K): min/max, axis, box
        near, far = slab(inv[:, 0, None], bounds[:, 0])  # (N, K)
        for axis in (1, 2):
            lo, hi = slab(inv[:, axis, None], bounds[:, axis])
            near, far = torch.maximum(near, lo), torch.minimum(far, hi)
        best, idx = first_hit(near, far, dim=1)
        closer = best < depth
        depth = torch.where(closer, best, depth)
        hit = torch.where(closer, idx, hit)
    return depth, hit


def slab(inv: torch.Tensor, bounds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit ray parameters of every box's slab along one axis.

    Args:
        inv: reciprocal ray components along the axis, shaped to broadcast against the bounds.
        bounds: ``(2, ...)`` the boxes' min and max coordinates along the axis.

    Returns:
        ``(near, far)``, the broadcast shape of ``inv`` and one bound.
    """
    t0 = bounds[0] * inv
    t1 = bounds[1] * inv
    return torch.minimum(t0, t1), torch.maximum(t0, t1)


def first_hit(near: torch.Tensor, far: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest box hit in front of the camera from slab entries and exits with the boxes along
    ``dim``: the depth (inf where no box is hit) and the box index (the first box on a tie, as
    ``torch.min`` documents, whichever dimension the boxes are on)."""
    valid = (near <= far) & (near > 0.1)
    near = torch.where(valid, near, torch.full_like(near, np.inf))
    return near.min(dim=dim)


def ray_cast_grid(
    x: torch.Tensor, y: torch.Tensor, boxes: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`ray_cast` for the rays of a pixel grid, exploiting that they are separable.

    The ray through pixel ``(v, u)`` is ``(x_u, y_v, 1)``: its x slab interval depends on the
    column only and its y interval on the row only, so they are computed on ``(K, W)`` and
    ``(K, H)`` and only their combination runs over ``(K, H, W)``, with the boxes on the outer
    dimension so that every op is elementwise over contiguous image planes. The result equals
    ``ray_cast`` on the flattened grid exactly (the same products; max and min are exact;
    tested).

    Args:
        x: ``(W,)`` normalised x coordinate of every column.
        y: ``(H,)`` normalised y coordinate of every row.
        boxes: ``(K, 2, 3)`` min/max corners in camera coordinates (metres).

    Returns:
        ``(depth, hit)``: ``(H, W)`` depth in metres (the far plane where nothing is hit) and
        ``(H, W)`` surface index (−2 sky, −1 ground, k ≥ 0 box k).
    """
    height, width = y.shape[0], x.shape[0]
    # The ground is hit at a depth that depends on the row only.
    ground = torch.where(y > 1e-9, CAMERA_HEIGHT / y.clamp_min(1e-9), torch.full_like(y, np.inf))
    on_ground = (ground < FAR_PLANE)[:, None].expand(height, width)
    depth = torch.where(on_ground, ground[:, None], torch.full_like(ground, FAR_PLANE)[:, None])
    hit = torch.where(on_ground, -1, -2).to(torch.long)
    if boxes.shape[0]:
        bounds = boxes.permute(1, 2, 0)  # (2, 3, K): min/max, axis, box
        near_x, far_x = slab(reciprocal(x), bounds[:, 0, :, None])  # (K, W)
        near_y, far_y = slab(reciprocal(y), bounds[:, 1, :, None])  # (K, H)
        # z = 1 for every ray: the z slab is the box's own z range (times 1/1, as ray_cast).
        near_z, far_z = slab(torch.ones(1, dtype=x.dtype), bounds[:, 2, :, None, None])
        near = torch.maximum(torch.maximum(near_x[:, None, :], near_y[:, :, None]), near_z)
        far = torch.minimum(torch.minimum(far_x[:, None, :], far_y[:, :, None]), far_z)
        best, idx = first_hit(near, far, dim=0)
        closer = best < depth
        depth = torch.where(closer, best, depth)
        hit = torch.where(closer, idx, hit)
    return depth, hit
