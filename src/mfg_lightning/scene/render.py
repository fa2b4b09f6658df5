"""Ray-cast images of persistent worlds, with depth, regions, instances and exact flow.

:func:`render_frame` casts one ray through every pixel centre of a camera at a frame of a
:class:`~mfg_lightning.scene.worlds.World` and shades what it hits:

* **Ground**: the world's height field, intersected by a few Newton steps per ray from the
  plane under the camera. Asphalt with grain at several scales (down to 3 cm), tyre-worn
  lanes, dashed and solid lane markings drawn in the road coordinates ``(s, d)`` of the
  world's grid, a light kerb, paving slabs on the sidewalks, grass beyond.
* **Boxes** (facades, parked cars, containers, moving cars and pedestrians): yaw-aligned boxes
  intersected with the slab method in each box's own frame. Facades get walls (plaster, brick
  or concrete panels) with rows of windows (repeated structure, each pane its own shade) and
  sometimes shop fronts; cars a nearly uniform paint (little texture, as real car bodies) with
  dark glass, wheels and lights; containers corrugated, sometimes labelled walls; pedestrians
  legs, torso and head.
* **Sky**: an almost uniform gradient with faint clouds, at the far plane (655.35 m, as
  Virtual KITTI), for rays that hit nothing closer.

Every texture is a function of the world point hit (world or box coordinates), so it is
anchored to the surface and moves exactly with it from frame to frame. Textures are
prefiltered for the pixel's footprint on the surface (each noise octave and every line fades
as it shrinks below two pixels), so fine grain fades with distance instead of aliasing. Faces
are lit by the world's sun (Lambert), distant surfaces fade a little into the horizon's colour,
the image has a mild vignette, and every frame its own exposure gain (``World.exposure``) and
sensor noise: brightness constancy holds only approximately, as in a real camera.

Work is vectorised over pixels. Boxes are culled to those within ``CULL_DISTANCE`` in front
of the camera, and each is tested only against the 16 × 16 pixel tiles that its projected
outline (clipped at the near plane) overlaps; the nearest hit per pixel is a scatter-min.
All arithmetic is elementwise or exact (min/max, scatter-min) and avoids transcendental
functions on pixel tensors, so a frame is bit-identical in any process and thread count.

:func:`exact_flow` turns a rendered frame into the exact optical flow to any other frame:
the camera's relative pose and, for pixels on a moving object, that object's own rigid motion
between the two frames, through :func:`mfg_lightning.core.geometry.reprojection_flow`.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from mfg_lightning.core import geometry
from mfg_lightning.scene.camera import FAR_PLANE
from mfg_lightning.scene.raycast import reciprocal, slab
from mfg_lightning.scene.seeding import seeded_rng
from mfg_lightning.scene.worlds import CAR, CRATE, FACADE, PARKED_CAR, PEDESTRIAN, Ground, World

__all__ = [
    "CULL_DISTANCE",
    "FAR_FIELD_DEPTH",
    "FAR_PLANE",
    "MAX_SIZE",
    "MIN_SIZE",
    "REGION_FAR",
    "REGION_MOVING",
    "REGION_NAMES",
    "REGION_ROAD",
    "REGION_STRUCTURE",
    "RenderedFrame",
    "check_render_size",
    "exact_flow",
    "render_frame",
]

#: Surface regions of :attr:`RenderedFrame.region`: the ground (road, parking strips,
#: sidewalks, verges), static structure (facades, parked cars and containers), moving objects,
#: and the far field (sky, and every surface deeper than ``FAR_FIELD_DEPTH``).
REGION_ROAD, REGION_STRUCTURE, REGION_MOVING, REGION_FAR = 0, 1, 2, 3
REGION_NAMES = ("road", "structure", "moving", "far")
#: Surfaces beyond this depth (metres) are far field: KITTI's ground-truth flow (from a
#: Velodyne) does not reach much further.
FAR_FIELD_DEPTH = 80.0
#: Boxes further than this from the camera (metres) are not drawn (at most the worlds'
#: ``SECTION_MARGIN``).
CULL_DISTANCE = 200.0
#: Depth (metres) where the distance fog starts.
FOG_START = 40.0
#: Smallest and largest image side (pixels).
MIN_SIZE, MAX_SIZE = 16, 4096
#: Nearest hit along a ray (metres of depth).
NEAR = 0.1
_TILE = 16

_HORIZON = torch.tensor([200.0, 212.0, 226.0])
_ZENITH = torch.tensor([92.0, 146.0, 212.0])
_NOISE_SIZE = 256


@dataclass
class RenderedFrame:
    """One rendered image and what the renderer knows about every pixel.

    Attributes:
        rgb: ``(3, H, W)`` uint8.
        depth: ``(H, W)`` float32 depth along the camera's z axis in metres (``FAR_PLANE`` for
            sky).
        region: ``(H, W)`` uint8 one of ``REGION_ROAD`` … ``REGION_FAR``.
        instance: ``(H, W)`` int32 index of the moving object seen (its row in
            ``World.object_poses``), -1 elsewhere.
        frame: the frame index rendered.
        intrinsics: ``(4,)`` float64 ``(fx, fy, cx, cy)`` in pixels.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    region: torch.Tensor
    instance: torch.Tensor
    frame: int = -1
    intrinsics: torch.Tensor | None = None


def check_render_size(height: int, width: int) -> None:
    """Raise ``ValueError`` naming the size unless both sides are integers in
    ``[MIN_SIZE, MAX_SIZE]`` pixels."""
    ok = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (height, width))
    if not ok or not (MIN_SIZE <= height <= MAX_SIZE and MIN_SIZE <= width <= MAX_SIZE):
        raise ValueError(
            f"render size {height} x {width} (height x width) is not one the scene can take: "
            f"both sides must be whole numbers of pixels from {MIN_SIZE} to {MAX_SIZE}"
        )


def _check_intrinsics(intrinsics: torch.Tensor) -> torch.Tensor:
    K = torch.as_tensor(intrinsics, dtype=torch.float64).reshape(-1)
    if K.shape != (4,) or not bool(torch.isfinite(K).all()) or not bool((K[:2] > 0).all()):
        raise ValueError(
            f"intrinsics must be 4 finite numbers (fx, fy, cx, cy) with fx, fy > 0, "
            f"got {tuple(torch.as_tensor(intrinsics).shape)} {torch.as_tensor(intrinsics).tolist()}"
        )
    return K


def _check_frame(world: World, frame: int) -> int:
    if not 0 <= int(frame) < world.num_frames:
        raise ValueError(
            f"frame {frame} is outside trajectory {world.name!r} "
            f"(frames 0 … {world.num_frames - 1})"
        )
    return int(frame)


# --------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------


def _cast_ground(
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
        dx, dy, dz: ``(n,)`` world-axis ray directions.
        t_box: ``(n,)`` depth of each ray's box hit (inf: none).

    Returns:
        ``(n,)`` depth in metres.
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
    geometric) and bisection (10 steps); inf where the ray stays above the ground."""
    ox, oy, oz = (float(v) for v in origin)
    x, y, z = (d.index_select(0, rays)[:, None] for d in (dx, dy, dz))
    ts = torch.logspace(np.log10(0.5), np.log10(CULL_DISTANCE), 32)[None]
    f = ground.height(ox + ts * x, oz + ts * z)[0] - oy - ts * y  # (n, 48), > 0 above ground
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


@dataclass
class _FrameBoxes:
    """The boxes drawn in one frame, camera-relative (float32 unless stated)."""

    centre: torch.Tensor  # (K, 3) box centre minus camera position, world axes
    cos: torch.Tensor  # (K,) cos yaw
    sin: torch.Tensor  # (K,) sin yaw
    half: torch.Tensor  # (K, 3)
    base: torch.Tensor  # (K,)
    kind: torch.Tensor  # (K,) int64
    colour: torch.Tensor  # (K, 3)
    colour2: torch.Tensor  # (K, 3)
    params: torch.Tensor  # (K, 8)
    instance: torch.Tensor  # (K,) int64, -1 for static boxes


def _frame_boxes(world: World, frame: int, origin: np.ndarray) -> _FrameBoxes:
    """The static boxes of the frame's section and the moving objects on it at ``frame``,
    within ``CULL_DISTANCE`` of the camera."""
    st, mv = world.static, world.moving.boxes
    index, centre = world.static_boxes(frame)
    near = np.linalg.norm(centre - origin, axis=1) - np.linalg.norm(st.half[index], axis=1)
    keep = near < CULL_DISTANCE
    index, centre = index[keep], centre[keep]
    poses = world.object_poses(frame).numpy()
    ground = world.ground(frame)
    arc = world.object_arc(frame)
    near = np.linalg.norm(poses[:, :3, 3] - origin, axis=1) - np.linalg.norm(mv.half, axis=1)
    moving = np.nonzero((near < CULL_DISTANCE) & (arc >= ground.lo) & (arc <= ground.hi))[0]
    poses = poses[moving]

    def cat(a: np.ndarray, b: np.ndarray, dtype=torch.float32) -> torch.Tensor:
        return torch.from_numpy(np.concatenate([a, b])).to(dtype)

    return _split_cars(
        _FrameBoxes(
            centre=torch.from_numpy(np.concatenate([centre, poses[:, :3, 3]]) - origin).float(),
            cos=cat(np.cos(st.yaw[index]), poses[:, 0, 0]),
            sin=cat(np.sin(st.yaw[index]), poses[:, 0, 2]),
            half=cat(st.half[index], mv.half[moving]),
            base=cat(st.base[index], mv.base[moving]),
            kind=cat(st.kind[index], mv.kind[moving], torch.long),
            colour=cat(st.colour[index], mv.colour[moving]),
            colour2=cat(st.colour2[index], mv.colour2[moving]),
            params=cat(st.params[index], mv.params[moving]),
            instance=cat(np.full(len(index), -1), moving, torch.long),
        )
    )


#: Renderer-only kind: the cabin (glasshouse) on top of a car's body.
CABIN = 5
#: A car's beltline (top of the body) as a fraction of its height above the ground, and its
#: cabin's length as a fraction of the car's, set back by ``_CABIN_SHIFT`` of the length.
_BELT, _CABIN_LENGTH, _CABIN_SHIFT = 0.6, 0.55, 0.06


def _split_cars(boxes: _FrameBoxes) -> _FrameBoxes:
    """Each car box becomes a body (ground to beltline) and a narrower, shorter cabin on top,
    both with the car's instance id."""
    car = ((boxes.kind == CAR) | (boxes.kind == PARKED_CAR)).nonzero(as_tuple=True)[0]
    if not len(car):
        return boxes
    half, base = boxes.half[car], boxes.base[car]
    top = base + half[:, 1]  # height of the roof above the ground
    belt_y = base - _BELT * top  # the beltline in the box's own y (down)
    body_half = half.clone()
    body_half[:, 1] = (half[:, 1] - belt_y) / 2
    body_dy = (half[:, 1] + belt_y) / 2
    cabin_half = half.clone()
    cabin_half[:, 0] = 0.88 * half[:, 0]
    cabin_half[:, 1] = (belt_y + half[:, 1]) / 2
    cabin_half[:, 2] = _CABIN_LENGTH * half[:, 2]
    cabin_dy = (belt_y - half[:, 1]) / 2
    cabin_dz = -_CABIN_SHIFT * 2 * half[:, 2]
    c, s = boxes.cos[car], boxes.sin[car]
    body_centre = boxes.centre[car] + torch.stack([0 * c, body_dy, 0 * c], -1)
    cabin_centre = boxes.centre[car] + torch.stack([s * cabin_dz, cabin_dy, c * cabin_dz], -1)
    out = {f: getattr(boxes, f).clone() for f in boxes.__dataclass_fields__}
    out["centre"][car] = body_centre
    out["half"][car] = body_half
    out["base"][car] = base - body_dy
    extra = {f: getattr(boxes, f)[car] for f in boxes.__dataclass_fields__}
    extra.update(
        centre=cabin_centre,
        half=cabin_half,
        base=base - cabin_dy,
        kind=torch.full_like(extra["kind"], CABIN),
    )
    return _FrameBoxes(**{f: torch.cat([out[f], extra[f]]) for f in out})


# The 12 edges of a box whose corners are numbered by the bits (x, y, z) of 0 … 7.
_EDGES = torch.tensor(
    [[a, a | (1 << b)] for a in range(8) for b in range(3) if not a & (1 << b)], dtype=torch.long
)
_CORNER_SIGNS = torch.tensor([[1.0 if c & (1 << i) else -1.0 for i in range(3)] for c in range(8)])


def _screen_rects(
    boxes: _FrameBoxes, R_cw: torch.Tensor, K: torch.Tensor, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel bounding rectangles of the boxes' outlines clipped at the near plane.

    Returns:
        ``(rect, visible)``: ``(K, 4)`` ``u0, u1, v0, v1`` and ``(K,)`` whether any part of the
        box is in front of the near plane and overlaps the image.
    """
    # Corners in world axes relative to the camera, then in camera coordinates.
    local = _CORNER_SIGNS[None] * boxes.half[:, None]  # (K, 8, 3)
    c, s = boxes.cos[:, None], boxes.sin[:, None]
    wx = c * local[..., 0] + s * local[..., 2]
    wz = -s * local[..., 0] + c * local[..., 2]
    world = torch.stack([wx, local[..., 1], wz], -1) + boxes.centre[:, None]
    cam = world @ R_cw.T  # (K, 8, 3)
    a, b = cam[:, _EDGES[:, 0]], cam[:, _EDGES[:, 1]]  # (K, 12, 3)
    za, zb = a[..., 2], b[..., 2]
    cross = (za - NEAR) * (zb - NEAR) < 0
    lam = ((NEAR - za) / torch.where(cross, zb - za, torch.ones_like(za))).clamp(0, 1)
    clip = a + lam[..., None] * (b - a)
    pts = torch.cat([cam, clip], 1)  # (K, 20, 3)
    ok = torch.cat([cam[..., 2] >= NEAR, cross], 1)
    z = pts[..., 2].clamp_min(NEAR)
    u = K[0] * pts[..., 0] / z + K[2]
    v = K[1] * pts[..., 1] / z + K[3]
    inf = torch.full_like(u, float("inf"))
    rect = torch.stack(
        [
            torch.where(ok, u, inf).amin(1),
            torch.where(ok, u, -inf).amax(1),
            torch.where(ok, v, inf).amin(1),
            torch.where(ok, v, -inf).amax(1),
        ],
        -1,
    )
    visible = (
        ok.any(1)
        & (rect[:, 1] >= -1)
        & (rect[:, 0] <= width)
        & (rect[:, 3] >= -1)
        & (rect[:, 2] <= height)
    )
    return rect, visible


def _cast_boxes(
    boxes: _FrameBoxes,
    rect: torch.Tensor,
    rays: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest box hit of every pixel, testing each box only on the tiles its outline overlaps.

    Args:
        rect: ``(K, 4)`` pixel rectangles of the boxes (all visible).
        rays: world-axis ray directions ``(H, W)`` each (camera ray ``(x, y, 1)`` rotated).

    Returns:
        ``(depth, box)``: ``(H, W)`` depth of the nearest box hit (inf: none) and its index in
        ``boxes`` (-1: none).
    """
    T = _TILE
    nth, ntw = -(-height // T), -(-width // T)
    pad = (0, ntw * T - width, 0, nth * T - height)
    tiles = [
        torch.nn.functional.pad(r[None], pad, mode="replicate")[0]
        .view(nth, T, ntw, T)
        .permute(0, 2, 1, 3)
        .reshape(nth * ntw, T * T)
        for r in rays
    ]
    n_pix = nth * ntw * T * T
    best = torch.full((n_pix,), float("inf"))
    winner = torch.full((n_pix,), -1, dtype=torch.long)
    if rect.shape[0] == 0:
        return torch.full((height, width), float("inf")), torch.full((height, width), -1)
    tu0 = ((rect[:, 0] - 1) / T).floor().clamp(0, ntw - 1).long()
    tu1 = ((rect[:, 1] + 1) / T).floor().clamp(0, ntw - 1).long()
    tv0 = ((rect[:, 2] - 1) / T).floor().clamp(0, nth - 1).long()
    tv1 = ((rect[:, 3] + 1) / T).floor().clamp(0, nth - 1).long()
    nu, nv = tu1 - tu0 + 1, tv1 - tv0 + 1
    counts = nu * nv
    box = torch.repeat_interleave(torch.arange(rect.shape[0]), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(int(counts.sum())) - start.index_select(0, box)
    tile = (
        (tv0.index_select(0, box) + local // nu.index_select(0, box)) * ntw
        + tu0.index_select(0, box)
        + local % nu.index_select(0, box)
    )
    ax, ay, az = (t.index_select(0, tile) for t in tiles)  # (P, T²)
    c, s = boxes.cos[box, None], boxes.sin[box, None]
    cen = boxes.centre.index_select(0, box)
    # The camera (origin) and the rays in the box's frame: R^T (0 − centre), R^T d.
    o = (
        -(c[:, 0] * cen[:, 0] - s[:, 0] * cen[:, 2]),
        -cen[:, 1],
        -(s[:, 0] * cen[:, 0] + c[:, 0] * cen[:, 2]),
    )
    d = (c * ax - s * az, ay, s * ax + c * az)
    h = boxes.half.index_select(0, box)
    near = far = None
    for axis in range(3):
        oa = o[axis][:, None]
        ha = h[:, axis, None]
        lo, hi = slab(reciprocal(d[axis]), torch.stack(torch.broadcast_tensors(-ha - oa, ha - oa)))
        near = lo if near is None else torch.maximum(near, lo)
        far = hi if far is None else torch.minimum(far, hi)
    t = torch.where((near <= far) & (near > NEAR), near, torch.full_like(near, float("inf")))
    pix = (tile[:, None] * (T * T) + torch.arange(T * T)).reshape(-1)
    t = t.reshape(-1)
    best.scatter_reduce_(0, pix, t, "amin")
    cand = torch.where(
        (t == best.index_select(0, pix)) & torch.isfinite(t),
        box[:, None].expand(-1, T * T).reshape(-1),
        -1,
    )
    winner.scatter_reduce_(0, pix, cand, "amax")

    def image(x: torch.Tensor) -> torch.Tensor:
        return x.view(nth, ntw, T, T).permute(0, 2, 1, 3).reshape(nth * T, ntw * T)[:height, :width]

    return image(best), image(winner)


# --------------------------------------------------------------------------------------------
# Textures
# --------------------------------------------------------------------------------------------


def _noise_table(world: World) -> torch.Tensor:
    """The world's lattice of random values in [-1, 1] (flat, ``_NOISE_SIZE²``)."""
    return _random_table(world.seed, world.name, "texture")


@functools.lru_cache(maxsize=64)
def _random_table(seed: int, name: str, what: str) -> torch.Tensor:
    """A world's table of random float32 values: uniform in [-1, 1] (``"texture"``,
    ``_NOISE_SIZE²``) or standard normal (``"sensor"``, 2¹⁶). Kept per world (tables are small
    and a trajectory's frames are rendered in bulk)."""
    rng = seeded_rng(seed, "world", name, what)
    if what == "texture":
        values = rng.uniform(-1, 1, _NOISE_SIZE * _NOISE_SIZE)
    else:
        values = rng.standard_normal(1 << 16)
    return torch.from_numpy(values.astype(np.float32))


def _take(index: torch.Tensor, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The rows ``index`` (``(n,)`` long) of every tensor, in order: one ``index_select`` along
    dim 0 each (gathering the pixels of one surface; cheaper than boolean masks on CPU)."""
    return tuple(t.index_select(0, index) for t in tensors)


def _lookup(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``table[index]`` for a 1-D table and an integer index of any shape (``index_select``,
    several times faster than advanced indexing on CPU)."""
    return table.index_select(0, index.reshape(-1)).view(index.shape)


def _sensor_noise(world: World, frame: int, height: int, width: int) -> torch.Tensor:
    """Standard-normal sensor noise ``(3, H, W)`` of one frame.

    Drawn from the world's table of 2¹⁶ normal values through a random affine map of the pixel
    coordinates per frame and channel (odd multipliers, so every row is a permutation of a
    stretch of the table): as good as fresh noise for an optical-flow estimator, and cheaper.
    """
    table = _random_table(world.seed, world.name, "sensor")
    coeff = seeded_rng(world.seed, "world", world.name, "sensor", frame).integers(
        0, 1 << 16, (3, 3)
    )
    u = torch.arange(width)[None]
    v = torch.arange(height)[:, None]
    mask = (1 << 16) - 1
    return torch.stack(
        [
            _lookup(table, (u * (2 * int(a) + 1) + v * (2 * int(b) + 1) * 977 + int(o)) & mask)
            for a, b, o in coeff
        ]
    )


def _noise(table: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Value noise in [-1, 1] at lattice coordinates ``(a, b)`` (smoothstep-interpolated)."""
    n = _NOISE_SIZE
    fa, fb = a.floor(), b.floor()
    ta, tb = a - fa, b - fb
    ta = ta * ta * (3 - 2 * ta)
    tb = tb * tb * (3 - 2 * tb)
    ia, ib = fa.long() & (n - 1), fb.long() & (n - 1)
    ja, jb = (ia + 1) & (n - 1), (ib + 1) & (n - 1)
    v00, v01 = _lookup(table, ib * n + ia), _lookup(table, ib * n + ja)
    v10, v11 = _lookup(table, jb * n + ia), _lookup(table, jb * n + ja)
    top = v00 + (v01 - v00) * ta
    bottom = v10 + (v11 - v10) * ta
    return top + (bottom - top) * tb


def _cell_random(table: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """A random value in [-1, 1] per integer cell ``(i, j)`` (e.g. per window or slab)."""
    n = _NOISE_SIZE
    return _lookup(
        table, ((j.long() * 7 + 3) & (n - 1)) * n + ((i.long() * 13 + j.long()) & (n - 1))
    )


def _fade(footprint: torch.Tensor, wavelength: float) -> torch.Tensor:
    """Weight of a texture component of ``wavelength`` seen through a pixel of ``footprint``
    (both metres): 1 while it spans four pixels or more, 0 below ~1.3."""
    return (1.5 - 2.0 * footprint / wavelength).clamp(0.0, 1.0)


def _fbm(
    table: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    footprint: torch.Tensor,
    octaves: Sequence[tuple[float, float]],
    offset: torch.Tensor | float = 0.0,
) -> torch.Tensor:
    """Sum of noise octaves ``(wavelength m, amplitude)`` at surface coordinates ``(a, b)`` (m),
    each faded by the footprint (and computed only where it has not faded out)."""
    out = torch.zeros_like(a)
    for k, (wavelength, amplitude) in enumerate(octaves):
        weight = _fade(footprint, wavelength)
        shift = 37.0 * k + offset
        if bool((weight > 0).all()):
            value = _noise(table, a / wavelength + shift, b / wavelength + 0.61 * shift)
            out = out + amplitude * weight * value
            continue
        sel = (weight > 0).nonzero(as_tuple=True)[0]
        if not len(sel):
            continue
        if isinstance(shift, torch.Tensor):
            shift = shift.index_select(0, sel)
        value = _noise(
            table,
            a.index_select(0, sel) / wavelength + shift,
            b.index_select(0, sel) / wavelength + 0.61 * shift,
        )
        out.index_add_(0, sel, amplitude * weight.index_select(0, sel) * value)
    return out


def _coverage(dist: torch.Tensor, width: float | torch.Tensor, footprint: torch.Tensor):
    """Fraction of a pixel's footprint (an interval of ``footprint`` metres centred ``dist``
    from a line's centre) covered by the line of ``width`` metres: box-filtered edges."""
    half_fp = footprint * 0.5
    if isinstance(width, torch.Tensor):
        lo = torch.maximum(dist - half_fp, -0.5 * width)
        hi = torch.minimum(dist + half_fp, 0.5 * width)
    else:
        lo = (dist - half_fp).clamp_min(-0.5 * width)
        hi = (dist + half_fp).clamp_max(0.5 * width)
    return (hi - lo).clamp_min_(0.0).div_(footprint.clamp_min(1e-6))


def _periodic_dist(x: torch.Tensor, period: float | torch.Tensor, centre: float | torch.Tensor):
    """Distance from ``x`` to the nearest of ``centre + k · period``."""
    q = (x - centre) / period
    return (q - q.round()).abs() * period


def _grey(v: torch.Tensor, tint: Sequence[float] = (1.0, 1.0, 1.0)) -> torch.Tensor:
    return v[:, None] * torch.tensor(tint, dtype=v.dtype)


def _shade_ground(
    world: World,
    ground: Ground,
    table: torch.Tensor,
    x: torch.Tensor,
    z: torch.Tensor,
    fp_lat: torch.Tensor,
    fp: torch.Tensor,
) -> torch.Tensor:
    """Colour ``(n, 3)`` of ground points at world ``(x, z)`` (``(n,)`` each) seen with
    footprints across and along the ray (metres); each material shaded on its own pixels."""
    cfg = world.config
    s, d, _ = ground.road_coordinates(x, z)
    ad = d.abs()
    half, kerb, line = cfg.road_half_width, cfg.kerb, cfg.building_line
    L = cfg.lane_width
    out = torch.empty(len(x), 3)

    def part(mask: torch.Tensor):
        idx = mask.nonzero(as_tuple=True)[0]
        return (idx, *_take(idx, x, z, s, d, ad, fp_lat, fp))

    # Asphalt: patches, grain down to 3 cm; lanes worn darker by tyres; markings dashed between
    # lanes (3 m on, 6 m off) and solid along the road's edges.
    idx, px, pz, ps, pd, pad, pfl, pf = part(ad < kerb)
    if len(idx):
        # Grain is filtered with the geometric mean of the footprint across and along the ray:
        # a little blur along it at grazing angles, as a real lens and sensor give.
        grain = torch.sqrt(pfl * pf)
        grey = 94.0 + _fbm(
            table,
            px,
            pz,
            grain,
            [(7.0, 6.0), (1.6, 5.0), (0.4, 5.0), (0.12, 6.0), (0.035, 9.0), (0.012, 7.0)],
        )
        grey = grey - 6.0 * _coverage((_periodic_dist(pd, L, 0.0) - 0.8).abs(), 0.5, pfl)
        paint = _coverage((pad - (half - 0.15)).abs(), 0.15, pfl)
        if cfg.lanes_per_side > 0:
            dash = _coverage(_periodic_dist(pd, L, L / 2), 0.12, pfl) * _coverage(
                _periodic_dist(ps, 9.0, 1.5), 3.0, pf
            )
            paint = torch.maximum(paint, dash * (pad < half - 0.5))
        wear = 1.0 + 0.08 * _noise(table, px / 0.7 + 11.0, pz / 0.7)
        grey = grey + paint * (205.0 * wear - grey)
        out.index_copy_(0, idx, _grey(grey, (1.0, 1.0, 1.03)))
    # Kerb stones.
    idx, px, pz, ps, pd, pad, pfl, pf = part((ad >= kerb) & (ad < kerb + 0.2))
    if len(idx):
        grey = 160.0 + _fbm(table, px, pz + 300.0, pf, [(0.3, 5.0), (0.05, 5.0)])
        out.index_copy_(0, idx, _grey(grey))
    # Sidewalk: 0.6 m slabs with seams, each slab its own shade.
    idx, px, pz, ps, pd, pad, pfl, pf = part((ad >= kerb + 0.2) & (ad <= line))
    if len(idx):
        grey = 138.0 + 8.0 * _cell_random(table, (ps / 0.6).floor(), (pad / 0.6).floor())
        grey = grey + _fbm(table, px + 500.0, pz, pf, [(0.5, 4.0), (0.05, 6.0)])
        seam = torch.maximum(
            _coverage(_periodic_dist(ps, 0.6, 0.0), 0.025, pf),
            _coverage(_periodic_dist(pad, 0.6, 0.0), 0.025, pf),
        )
        out.index_copy_(0, idx, _grey(grey - 45.0 * seam, (1.0, 0.99, 0.97)))
    # Verge beyond the building line: grass and dirt.
    idx, px, pz, ps, pd, pad, pfl, pf = part(ad > line)
    if len(idx):
        g = _fbm(table, px + 900.0, pz, pf, [(3.0, 0.5), (0.6, 0.35), (0.12, 0.25), (0.04, 0.2)])
        out.index_copy_(0, idx, torch.stack([88 + 30 * g, 104 + 34 * g, 58 + 18 * g], -1))
    return out


def _shade_facade(
    table: Tensor,
    p: Tensor,
    face: Tensor,
    hh: Tensor,
    fp: Tensor,
    colour: Tensor,
    colour2: Tensor,
    params: Tensor,
    top: Tensor,
) -> Tensor:
    """Facade walls with windows, ``(n, 3)`` RGB.

    The box shaders share their arguments: ``p`` ``(n, 3)`` box-local hit points (metres),
    ``face`` ``(n,)`` the axis of the face hit (0 sides, 1 top or bottom, 2 ends), ``hh`` height
    above the ground, ``fp`` the pixel footprint on the face (metres), ``half`` the box's half
    sizes, ``colour``/``colour2``/``params`` the box's (see :class:`~.worlds.Boxes`); here
    ``top`` is the facade's height above the ground.
    """
    floor_h, spacing = params[:, 0], params[:, 1]
    win_w, win_h = params[:, 2] * spacing, params[:, 3] * floor_h
    style, shop = params[:, 4], params[:, 7] < 0.4
    u = torch.where(face == 0, p[:, 2], p[:, 0]) + params[:, 5]
    v = hh
    wall = 1.0 + _fbm(table, u, v + params[:, 6], fp, [(3.0, 0.05), (0.6, 0.05), (0.12, 0.05)])
    brick_rows = _periodic_dist(v, 0.075, 0.0)
    brick_cols = _periodic_dist(u + 0.125 * ((v / 0.075).floor() % 2), 0.25, 0.0)
    mortar = torch.maximum(_coverage(brick_rows, 0.012, fp), _coverage(brick_cols, 0.012, fp))
    brick = wall * (1.0 + 0.06 * _cell_random(table, (u / 0.25).floor(), (v / 0.075).floor()))
    brick = brick * (1 - 0.35 * mortar) + 0.35 * mortar * 1.25
    panel = torch.maximum(
        _coverage(_periodic_dist(u, 1.5, 0.0), 0.03, fp),
        _coverage(_periodic_dist(v, floor_h, 0.0), 0.03, fp),
    )
    concrete = wall * (1.0 - 0.25 * panel)
    tone = torch.where(style == 1, brick, torch.where(style == 2, concrete, wall))
    rgb = colour * tone[:, None]
    # Windows: one per (column, floor); glass of its own shade, a light frame around it.
    col = (u / spacing).floor()
    level = (v / floor_h).floor()
    du = (u - (col + 0.5) * spacing).abs()
    dv = (v - level * floor_h - 0.9 - win_h / 2).abs()
    upper = (level >= 1) & (v < top - 0.9)
    glass_cov = _coverage(du, win_w, fp) * _coverage(dv, win_h, fp) * upper
    frame_cov = _coverage(du, win_w + 0.16, fp) * _coverage(dv, win_h + 0.16, fp) * upper
    # Shop fronts: one wide pane per column on the ground floor, from 0.4 m to 2.6 m.
    shop_cov = _coverage(du, 0.85 * spacing, fp) * _coverage((v - 1.5).abs(), 2.2, fp) * shop
    glass_cov = torch.maximum(glass_cov, shop_cov)
    frame_cov = torch.maximum(frame_cov, shop_cov)
    pane = 0.75 + 0.35 * _cell_random(table, col, level + 3 * params[:, 5].floor())
    glass = colour2 * pane[:, None] + 18.0 * (1 - dv / win_h.clamp_min(0.1))[:, None]
    frame = torch.tensor([215.0, 212.0, 205.0])
    rgb = rgb + frame_cov[:, None] * (frame - rgb)
    rgb = rgb + glass_cov[:, None] * (glass - rgb)
    plinth = _coverage((v - 0.2).abs(), 0.4, fp)[:, None]
    return rgb * (1 - 0.3 * plinth)


def _shade_car(
    table: Tensor,
    p: Tensor,
    face: Tensor,
    hh: Tensor,
    fp: Tensor,
    half: Tensor,
    colour: Tensor,
    params: Tensor,
    front_sign: float,
) -> Tensor:
    """Car bodies (ground to beltline): nearly uniform paint, wheels, lights, a dark sill."""
    along = p[:, 2]
    belt = half[:, 1] * 2 - 0.25  # body height above the ground (0.25 m are buried)
    paint = (
        colour
        * (1.0 + _fbm(table, p[:, 0] + params[:, 0], along + hh, fp, [(0.8, 0.02), (0.2, 0.015)]))[
            :, None
        ]
    )
    paint = paint * (0.8 + 0.2 * (hh / belt).clamp(0, 1))[:, None]
    side = face == 0
    endf = face == 2
    wheel_z = half[:, 2] - 0.8
    wheel = (
        torch.minimum(
            _coverage((along.abs() - wheel_z).abs(), 0.62, fp), _coverage((hh - 0.3).abs(), 0.6, fp)
        )
        * side
    )
    under = _coverage((hh - 0.08).abs(), 0.16, fp)
    lamp_x = _coverage((p[:, 0].abs() - (half[:, 0] - 0.25)).abs(), 0.3, fp)
    lamp = lamp_x * _coverage((hh - 0.62).abs(), 0.12, fp) * endf
    plate = _coverage(p[:, 0].abs(), 0.5, fp) * _coverage((hh - 0.42).abs(), 0.12, fp) * endf
    is_front = (p[:, 2] * front_sign) > 0
    lamp_colour = torch.where(
        is_front[:, None], torch.tensor([225.0, 225.0, 205.0]), torch.tensor([170.0, 25.0, 20.0])
    )
    rgb = paint + lamp[:, None] * (lamp_colour - paint)
    rgb = rgb + plate[:, None] * (torch.tensor([225.0, 225.0, 220.0]) - rgb)
    dark = torch.maximum(wheel, under)[:, None]
    return rgb + dark * (torch.tensor([22.0, 22.0, 24.0]) - rgb)


def _shade_cabin(
    table: Tensor,
    p: Tensor,
    face: Tensor,
    hh: Tensor,
    fp: Tensor,
    half: Tensor,
    colour: Tensor,
    colour2: Tensor,
) -> Tensor:
    """Car cabins: dark glass all round between painted pillars, a painted roof."""
    pillar_side = torch.maximum(
        _coverage(half[:, 2] - p[:, 2].abs(), 0.3, fp), _coverage(p[:, 2].abs(), 0.12, fp)
    )
    pillar_end = _coverage(half[:, 0] - p[:, 0].abs(), 0.16, fp)
    pillar = torch.where(face == 0, pillar_side, pillar_end)
    rail = _coverage(half[:, 1] + p[:, 1], 0.08, fp)  # the roof's edge, just below the roof
    frame = torch.maximum(pillar, rail)
    shine = ((half[:, 1] - p[:, 1]) / (2 * half[:, 1])).clamp(0, 1)  # 0 at the belt, 1 at roof
    glass = colour2 + (25.0 * shine)[:, None]
    rgb = glass + frame[:, None] * (colour - glass)
    return torch.where((face == 1)[:, None], colour, rgb)


def _shade_crate(
    table: Tensor,
    p: Tensor,
    face: Tensor,
    hh: Tensor,
    fp: Tensor,
    half: Tensor,
    colour: Tensor,
    params: Tensor,
) -> Tensor:
    """Containers and vans: corrugated, weathered walls, some with a light label."""
    u = torch.where(face == 0, p[:, 2], p[:, 0])
    period = params[:, 2]
    rib = _periodic_dist(u, period, 0.0) / period  # 0 … 0.5
    ribs = 1.0 + 0.12 * (4 * rib - 1) * _fade(fp, 1.0) * (fp < period / 2)
    rust = 1.0 + _fbm(table, u + params[:, 0], hh, fp, [(1.5, 0.08), (0.3, 0.06), (0.06, 0.05)])
    rgb = colour * (ribs * rust)[:, None]
    label = (
        _coverage(u.abs(), 2.2, fp)
        * _coverage((hh - 1.3).abs(), 0.6, fp)
        * (params[:, 3] > 0.5)
        * (face == 0)
    )
    return rgb + label[:, None] * (torch.tensor([235.0, 235.0, 228.0]) - rgb)


def _shade_pedestrian(
    table: Tensor,
    p: Tensor,
    hh: Tensor,
    fp: Tensor,
    half: Tensor,
    colour: Tensor,
    colour2: Tensor,
    params: Tensor,
) -> Tensor:
    """Pedestrians: legs, torso, head."""
    top = half[:, 1] * 2
    cloth = 1.0 + _fbm(table, p[:, 0] + p[:, 2] + params[:, 0], hh, fp, [(0.3, 0.08), (0.08, 0.06)])
    rgb = torch.where((hh < 0.47 * top)[:, None], colour2, colour) * cloth[:, None]
    return torch.where((hh > 0.85 * top)[:, None], params[:, 2:5], rgb)


def _shade_sky(table: Tensor, dx: Tensor, dy: Tensor, dz: Tensor) -> Tensor:
    """Sky colour ``(n, 3)`` for world ray directions: a gradient and faint clouds."""
    norm = torch.sqrt(dx * dx + dy * dy + dz * dz)
    up = (-dy / norm).clamp(0, 1)
    g = torch.sqrt((up / 0.6).clamp(0, 1))
    colour = _HORIZON + g[:, None] * (_ZENITH - _HORIZON)
    # Clouds on a plane 1 km up, seen through the ray: faint, large, smooth.
    k = 1000.0 / (-dy / norm).clamp_min(0.05) / norm
    cloud = _noise(table, dx * k / 900.0, dz * k / 900.0) + 0.5 * _noise(
        table, dx * k / 300.0 + 50.0, dz * k / 300.0
    )
    cover = ((cloud - 0.3).clamp(0, 1) * (up / 0.2).clamp(0, 1))[:, None] * 0.5
    return colour + cover * (torch.tensor([236.0, 238.0, 242.0]) - colour)


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def render_frame(
    world: World, frame: int, intrinsics: torch.Tensor, height: int, width: int
) -> RenderedFrame:
    """Render one frame of a world (see the module docstring).

    Args:
        world: the persistent world.
        frame: frame index into ``world.poses``.
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)`` in pixels at ``height × width``
            (:func:`mfg_lightning.data.camera.kitti_like_intrinsics` is the default camera).
        height, width: image size in pixels (``MIN_SIZE`` … ``MAX_SIZE`` each).

    Returns:
        The :class:`RenderedFrame`; a pure function of ``(world, frame, intrinsics, size)``.

    Raises:
        ValueError: a size the scene cannot take, bad intrinsics or a frame out of range.
    """
    check_render_size(height, width)
    K = _check_intrinsics(intrinsics)
    frame = _check_frame(world, frame)
    T = world.poses[frame]
    R = T[:3, :3].float()
    origin = T[:3, 3].numpy()
    xy = geometry.normalized_grid(K[None], height, width)[0].float()
    x, y = xy[0], xy[1]
    # World-axis ray directions R · (x, y, 1), written out so the order of operations is fixed.
    rays = tuple(x * R[i, 0] + y * R[i, 1] + R[i, 2] for i in range(3))
    boxes = _frame_boxes(world, frame, origin)
    rect, visible = _screen_rects(boxes, R.T, K.float(), height, width)
    keep = visible.nonzero(as_tuple=True)[0]
    boxes = _FrameBoxes(*(getattr(boxes, f)[keep] for f in boxes.__dataclass_fields__))
    t_box, box = _cast_boxes(boxes, rect[keep], rays, height, width)
    dx, dy, dz = (r.reshape(-1) for r in rays)
    t_box, box = t_box.reshape(-1), box.reshape(-1)
    ground = world.ground(frame)
    t_ground = _cast_ground(ground, origin, dx, dy, dz, t_box)

    on_box = (t_box < t_ground) & (t_box < FAR_PLANE)
    on_ground = ~on_box & (t_ground < FAR_PLANE)
    sky = ~on_box & ~on_ground
    depth = torch.where(on_box, t_box, torch.where(on_ground, t_ground, FAR_PLANE))
    box = torch.where(on_box, box, -1)

    table = _noise_table(world)
    colour = torch.empty(height * width, 3)
    norm = torch.sqrt(dx * dx + dy * dy + dz * dz)
    fp_lat = depth * norm / float(K[0])  # metres per pixel across the ray at the hit
    sun = torch.from_numpy(world.sun).float()

    def haze(rgb: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Distance fog: surfaces fade into the horizon's colour from ``FOG_START`` on and are
        gone at ``CULL_DISTANCE``, so nothing visibly appears where culling starts."""
        f = ((t - FOG_START) / (CULL_DISTANCE - FOG_START)).clamp(0, 1)
        return rgb + (f * f * (3 - 2 * f))[:, None] * (_HORIZON - rgb)

    idx = sky.nonzero(as_tuple=True)[0]
    if len(idx):
        colour.index_copy_(0, idx, _shade_sky(table, *_take(idx, dx, dy, dz)))
    idx = on_ground.nonzero(as_tuple=True)[0]
    if len(idx):
        t, gdx, gdy, gdz, gnorm, gfp = _take(idx, depth, dx, dy, dz, norm, fp_lat)
        gx = float(origin[0]) + t * gdx
        gz = float(origin[2]) + t * gdz
        cos_inc = (gdy / gnorm).abs().clamp_min(0.02)
        light = 0.62 + 0.38 * float(-world.sun[1])
        rgb = _shade_ground(world, ground, table, gx, gz, gfp, gfp / cos_inc)
        colour.index_copy_(0, idx, haze(light * rgb, t))
    idx = on_box.nonzero(as_tuple=True)[0]
    if len(idx):
        hit = _take(idx, box, depth, dx, dy, dz, norm, fp_lat)
        colour.index_copy_(0, idx, haze(_shade_boxes(table, boxes, *hit, sun), hit[1]))

    # Camera: vignette, this frame's exposure, sensor noise, 8 bits.
    u = (torch.arange(width, dtype=torch.float32) - (width - 1) / 2) / (width / 2)
    v = (torch.arange(height, dtype=torch.float32) - (height - 1) / 2) / (height / 2)
    vignette = 1.0 - 0.09 * (u[None] ** 2 + v[:, None] ** 2)
    gain = float(world.exposure[frame])
    noise = _sensor_noise(world, frame, height, width)
    image = (
        colour.T.reshape(3, height, width) * (gain * vignette) + world.config.sensor_noise * noise
    )
    rgb = image.round_().clamp_(0, 255).to(torch.uint8)

    # A frame may see no box at all (an open stretch of road): nothing to look up then.
    obj = boxes.instance[box.clamp_min(0)] if len(boxes.instance) else torch.full_like(box, -1)
    is_moving = on_box & (obj >= 0)
    region = torch.where(
        on_ground,
        REGION_ROAD,
        torch.where(is_moving, REGION_MOVING, torch.where(on_box, REGION_STRUCTURE, REGION_FAR)),
    )
    region = torch.where(depth > FAR_FIELD_DEPTH, REGION_FAR, region).to(torch.uint8)
    instance = torch.where(is_moving, obj, -1).to(torch.int32)
    return RenderedFrame(
        rgb=rgb.contiguous(),
        depth=depth.view(height, width),
        region=region.view(height, width),
        instance=instance.view(height, width),
        frame=frame,
        intrinsics=K,
    )


def _shade_boxes(
    table: torch.Tensor,
    boxes: _FrameBoxes,
    b: torch.Tensor,
    t: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    dz: torch.Tensor,
    norm: torch.Tensor,
    fp_lat: torch.Tensor,
    sun: torch.Tensor,
) -> torch.Tensor:
    """Colour ``(n, 3)`` of box hits: box ``b`` at depth ``t`` along rays ``d`` (``(n,)`` each)."""
    c, s, cen, half = _take(b, boxes.cos, boxes.sin, boxes.centre, boxes.half)
    wx, wy, wz = t * dx - cen[:, 0], t * dy - cen[:, 1], t * dz - cen[:, 2]
    px, py, pz = c * wx - s * wz, wy, s * wx + c * wz  # box-local hit point
    p = torch.stack([px, py, pz], -1)
    # The face hit: the axis along which the point is furthest out relative to the half size.
    rx, ry, rz = px.abs() / half[:, 0], py.abs() / half[:, 1], pz.abs() / half[:, 2]
    on_x = (rx >= ry) & (rx >= rz)
    on_y = ~on_x & (ry >= rz)
    on_z = ~on_x & ~on_y
    face = torch.where(on_x, 0, torch.where(on_y, 1, 2))
    zero = torch.zeros_like(px)
    lx, ly, lz = (torch.where(m, q.sign(), zero) for m, q in ((on_x, px), (on_y, py), (on_z, pz)))
    # World normal: R · n with R = [[c, 0, s], [0, 1, 0], [-s, 0, c]].
    nx = c * lx + s * lz
    nz = -s * lx + c * lz
    ny = ly
    lambert = (nx * sun[0] + ny * sun[1] + nz * sun[2]).clamp_min(0)
    cos_inc = ((nx * dx + ny * dy + nz * dz) / norm).abs().clamp_min(0.02)
    fp = fp_lat / cos_inc
    hh = boxes.base.index_select(0, b) - p[:, 1]
    kind = boxes.kind.index_select(0, b)
    rgb = torch.empty(len(b), 3)
    for k in (FACADE, PARKED_CAR, CRATE, CAR, PEDESTRIAN, CABIN):
        sel = (kind == k).nonzero(as_tuple=True)[0]
        if not len(sel):
            continue
        bs = b.index_select(0, sel)
        kp, kface, khh, kfp, khalf = _take(sel, p, face, hh, fp, half)
        colour, colour2, params = _take(bs, boxes.colour, boxes.colour2, boxes.params)
        args = (table, kp, kface, khh, kfp)
        if k == FACADE:
            top = boxes.base.index_select(0, bs) + boxes.half.index_select(0, bs)[:, 1]
            out = _shade_facade(*args, colour, colour2, params, top)
            out = torch.where((kface == 1)[:, None], torch.tensor([85.0, 82.0, 80.0]), out)
        elif k in (PARKED_CAR, CAR):
            out = _shade_car(*args, khalf, colour, params, 1.0)
        elif k == CABIN:
            out = _shade_cabin(*args, khalf, colour, colour2)
        elif k == CRATE:
            out = _shade_crate(*args, khalf, colour, params)
        else:
            out = _shade_pedestrian(table, kp, khh, kfp, khalf, colour, colour2, params)
        rgb.index_copy_(0, sel, out)
    return rgb * (0.58 + 0.42 * lambert)[:, None]


# --------------------------------------------------------------------------------------------
# Exact flow
# --------------------------------------------------------------------------------------------


def exact_flow(
    world: World,
    src: int,
    tgt: int,
    intrinsics: torch.Tensor,
    height: int,
    width: int,
    source: RenderedFrame | None = None,
    target: RenderedFrame | None = None,
) -> dict[str, torch.Tensor]:
    """The exact optical flow from frame ``src`` to frame ``tgt`` (any offset).

    Every pixel of the source frame is back-projected with its rendered depth; points on a
    moving object move rigidly with it (its pose at ``tgt`` times the inverse of its pose at
    ``src``); everything is re-projected into the target camera
    (:func:`mfg_lightning.core.geometry.reprojection_flow`).

    Args:
        world, intrinsics, height, width: as :func:`render_frame`.
        src, tgt: frame indices.
        source: the rendered source frame, reused instead of rendering it again.
        target: the rendered target frame; when given, adds ``"visible"``.

    Returns:
        ``"flow"``: ``(2, H, W)`` float32 pixels; ``"flow_valid"``: ``(H, W)`` bool, finite
        flow of a point in front of the target camera; ``"object_mask"``: ``(H, W)`` bool,
        valid pixels on moving objects; ``"object_flow"``: ``(2, H, W)`` float32, the part of
        the flow due to the objects' own motion (zero elsewhere); ``"depth"``: ``(H, W)``
        float32 source depth (metres). With ``target``: ``"visible"``, ``(H, W)`` bool, the
        point lands inside the target image and is not occluded there (its depth in the target
        camera is at most 2 % + 5 cm behind the target's rendered depth at the nearest pixel).
    """
    check_render_size(height, width)
    K = _check_intrinsics(intrinsics)
    src, tgt = _check_frame(world, src), _check_frame(world, tgt)
    if source is None:
        source = render_frame(world, src, K, height, width)
    elif source.frame != src or tuple(source.depth.shape) != (height, width):
        raise ValueError(
            f"exact_flow: the source frame given is frame {source.frame} at "
            f"{tuple(source.depth.shape)}, not frame {src} at {(height, width)}"
        )
    T_src, T_tgt = world.poses[src], world.poses[tgt]
    rel = geometry.relative_pose(T_src, T_tgt)
    depth = source.depth.double()[None]
    inst = source.instance.long()
    moving = inst >= 0
    motion = torch.zeros(1, height, width, 3, dtype=torch.float64)
    if bool(moving.any()):
        # M = T_cam,world(src) · T_world,obj(tgt) · T_obj,world(src) · T_world,cam(src): the
        # object's rigid motion written in the source camera's coordinates.
        ids, local = torch.unique(inst[moving], return_inverse=True)
        P_src, P_tgt = world.object_poses(src)[ids], world.object_poses(tgt)[ids]
        M = geometry.invert_pose(T_src) @ P_tgt @ geometry.invert_pose(P_src) @ T_src
        points = geometry.backproject(depth, K[None])[0][moving]  # (n, 3)
        moved = torch.einsum("nij,nj->ni", M[local, :3, :3], points) + M[local, :3, 3]
        motion[0][moving] = moved - points
        rigid, flow = geometry.reprojection_flow(
            depth.expand(2, -1, -1),
            rel[None].expand(2, -1, -1),
            K[None].expand(2, -1),
            torch.cat([torch.zeros_like(motion), motion]),
        )
    else:
        rigid = flow = geometry.reprojection_flow(depth, rel[None], K[None])[0]
    # Depth of every point in the target camera: behind it, the flow means nothing.
    X = geometry.backproject(depth, K[None])[0] + motion[0]
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
        "depth": source.depth,
    }
    if target is not None:
        grid_u = torch.arange(width, dtype=torch.float64)[None]
        grid_v = torch.arange(height, dtype=torch.float64)[:, None]
        u = (grid_u + flow[0]).round()
        v = (grid_v + flow[1]).round()
        inside = valid & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
        ui = u.clamp(0, width - 1).long()
        vi = v.clamp(0, height - 1).long()
        there = target.depth.double()[vi, ui]
        out["visible"] = inside & (z_tgt <= there * 1.02 + 0.05)
    return out
