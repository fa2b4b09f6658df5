"""Ground casting of the persistent-world renderer: where every camera ray first meets the
world's height field (:class:`.road.Ground`).

Newton steps from the plane under the camera find most hits; the few rays they miss (folds of
the ground) are marched geometrically and bisected. Rays are given by their world-axis
directions ``d`` of the camera ray ``(x, y, 1)``, so a ray's parameter is its depth along the
camera's z axis (metres).
"""

from __future__ import annotations

import numpy as np
import torch

from mfg_lightning.scene.camera import FAR_PLANE
from mfg_lightning.scene.clipping import CULL_DISTANCE, NEAR
from mfg_lightning.scene.road import Ground

__all__ = ["cast_ground"]


def cast_ground(
    ground: Ground,
    origin: np.ndarray,
    dx: torch.Tensor,
    dy: torch.Tensor,
    dz: torch.Tensor,
    t_box: torch.Tensor,
) -> torch.Tensor:
    """Depth of the first ground hit of every ray (inf where there is none).

    The ray ``o + t d`` (``d`` the world direction of the camera ray ``(x, y, 1)``, so ``t`` is
    the depth) meets the ground where ``f(t) = h(o_xz + t d_xz) − (o_y + t d_y) = 0``. Newton
    steps start from the plane through the ground under the camera (or 60 m for rays above it,
    which can still meet a hill ahead); a ray is done once its step is below 0.05 % of its
    depth, and has no ground hit if it has not converged after eight steps.

    Rays that hit a box at a point above the ground cannot have met the ground before (the
    ground is smooth and boxes stand on it) and are skipped.

    Args:
        ground: the ground of the frame's section.
        origin: ``(3,)`` the camera centre in world coordinates (metres).
        dx, dy, dz: ``(n,)`` float32 world-axis ray directions.
        t_box: ``(n,)`` depth of each ray's box hit (inf: none).

    Returns:
        ``(n,)`` depth in metres (inf: no ground hit).
    """
    ox, oy, oz = (float(v) for v in origin)
    h0, gx0, gz0 = ground.height(torch.tensor([ox]), torch.tensor([oz]))
    below = float(h0[0]) - oy
    depth = torch.full_like(dx, float("inf"))
    # A ray can reach the ground only if it climbs less steeply than the steepest ground.
    horizontal = torch.sqrt(dx * dx + dz * dz)
    candidate = dy > -(ground.max_slope + 0.01) * horizontal
    boxed = torch.isfinite(t_box).nonzero(as_tuple=True)[0]
    if len(boxed):
        tb = t_box.index_select(0, boxed)
        h = ground.height(ox + tb * dx.index_select(0, boxed), oz + tb * dz.index_select(0, boxed))[
            0
        ]
        above = h - oy - tb * dy.index_select(0, boxed) > 0.01
        candidate.index_fill_(0, boxed[above], False)
    active = candidate.nonzero(as_tuple=True)[0]
    x, y, z = dx.index_select(0, active), dy.index_select(0, active), dz.index_select(0, active)
    den = y - float(gx0[0]) * x - float(gz0[0]) * z
    below_plane = active[den > 0.02]
    t = torch.where(den > 0.02, below / den.clamp_min(0.02), torch.full_like(den, 60.0))
    t = t.clamp(NEAR, 2 * FAR_PLANE)
    for _ in range(8):
        h, hx, hz = ground.height(ox + t * x, oz + t * z)
        f = h - oy - t * y
        slope = hx * x + hz * z - y  # df/dt: negative where the ray descends onto the ground
        step = f / torch.where(slope < -1e-4, slope, torch.full_like(slope, -1e-4))
        done = (step.abs() <= 5e-4 * t) & (slope < -1e-4)
        hit = done & (t < FAR_PLANE) & (t > NEAR)
        depth[active[hit]] = t[hit]
        # Rays that climb away from the ground, or pass the far plane above it, never hit.
        lost = (slope >= -1e-4) | ((t >= FAR_PLANE) & (f > 0))
        more = (~done & ~lost).nonzero(as_tuple=True)[0]
        if not len(more):
            break
        active = active.index_select(0, more)
        x, y, z = x.index_select(0, more), y.index_select(0, more), z.index_select(0, more)
        t = (t.index_select(0, more) - step.index_select(0, more)).clamp(NEAR, 2 * FAR_PLANE)
    # Rays that point below the ground under the camera but found no hit (Newton thrown off by
    # a fold of the ground): march out geometrically to the first point below the ground, then
    # bisect.
    missed = below_plane[torch.isinf(depth.index_select(0, below_plane))]
    if len(missed):
        depth.index_copy_(0, missed, _march_ground(ground, origin, dx, dy, dz, missed))
    return depth


def _march_ground(
    ground: Ground,
    origin: np.ndarray,
    dx: torch.Tensor,
    dy: torch.Tensor,
    dz: torch.Tensor,
    rays: torch.Tensor,
) -> torch.Tensor:
    """First ground hit of a few rays by marching (32 steps from 0.5 m to the culling distance,
    geometric) and bisection (10 steps).

    Args:
        ground, origin, dx, dy, dz: as :func:`cast_ground`.
        rays: ``(m,)`` long, the rays to march (indices into ``dx``).

    Returns:
        ``(m,)`` depth in metres, inf where the ray stays above the ground.
    """
    ox, oy, oz = (float(v) for v in origin)
    x, y, z = (d.index_select(0, rays)[:, None] for d in (dx, dy, dz))
    ts = torch.logspace(np.log10(0.5), np.log10(CULL_DISTANCE), 32)[None]
    f = ground.height(ox + ts * x, oz + ts * z)[0] - oy - ts * y  # (m, 32), > 0 above ground
    under = f <= 0
    first = torch.where(under.any(1), under.float().argmax(1), -1)
    found = first > 0
    i = first.clamp_min(1)
    lo = ts[0].index_select(0, i - 1)
    hi = ts[0].index_select(0, i)
    x, y, z = x[:, 0], y[:, 0], z[:, 0]
    for _ in range(10):
        mid = (lo + hi) / 2
        above = ground.height(ox + mid * x, oz + mid * z)[0] - oy - mid * y > 0
        lo, hi = torch.where(above, mid, lo), torch.where(above, hi, mid)
    return torch.where(found, (lo + hi) / 2, torch.full_like(lo, float("inf")))
