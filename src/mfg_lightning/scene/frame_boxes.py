"""The boxes one frame of a persistent world draws, and their ray casting.

:func:`frame_boxes` gathers the static boxes of the frame's section and the moving objects on
it, culled to ``CULL_DISTANCE``, camera-relative, with every car split into a body and a cabin.
:func:`screen_rects` bounds each box's outline on the screen (clipped at the near plane), and
:func:`cast_boxes` tests each box only against the ``TILE × TILE`` pixel tiles its rectangle
overlaps (slab method in the box's own frame), the nearest hit per pixel by a scatter-min.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from mfg_lightning.scene.clipping import CULL_DISTANCE, NEAR
from mfg_lightning.scene.raycast import reciprocal, slab
from mfg_lightning.scene.worlds import CAR, PARKED_CAR, World

__all__ = ["CABIN", "TILE", "FrameBoxes", "cast_boxes", "frame_boxes", "screen_rects"]

#: Renderer-only kind (after the worlds' ``FACADE`` … ``PEDESTRIAN``): the cabin (glasshouse)
#: on top of a car's body.
CABIN = 5
#: Side of the square pixel tiles boxes are tested on (pixels).
TILE = 16
#: A car's beltline (top of the body) as a fraction of its height above the ground, and its
#: cabin's length as a fraction of the car's, set back by ``_CABIN_SHIFT`` of the length.
_BELT, _CABIN_LENGTH, _CABIN_SHIFT = 0.6, 0.55, 0.06


@dataclass
class FrameBoxes:
    """The boxes drawn in one frame, camera-relative (``K`` boxes; float32 unless stated)."""

    centre: torch.Tensor  # (K, 3) box centre minus camera position, world axes (metres)
    cos: torch.Tensor  # (K,) cos yaw
    sin: torch.Tensor  # (K,) sin yaw
    half: torch.Tensor  # (K, 3) half sizes along the box's x, y, z (metres)
    base: torch.Tensor  # (K,) the box's own y of the ground level (metres)
    kind: torch.Tensor  # (K,) int64, FACADE … PEDESTRIAN or CABIN
    colour: torch.Tensor  # (K, 3) RGB 0-255
    colour2: torch.Tensor  # (K, 3) RGB 0-255
    params: torch.Tensor  # (K, NUM_PARAMS), columns named in box_params
    instance: torch.Tensor  # (K,) int64, -1 for static boxes

    def select(self, keep: torch.Tensor) -> FrameBoxes:
        """The boxes ``keep`` (``(k,)`` long indices), in that order."""
        return FrameBoxes(*(getattr(self, f.name)[keep] for f in fields(self)))


def frame_boxes(world: World, frame: int, origin: np.ndarray) -> FrameBoxes:
    """The static boxes of the frame's section and the moving objects on it at ``frame``,
    within ``CULL_DISTANCE`` of the camera centre ``origin`` (``(3,)`` world metres)."""
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
        FrameBoxes(
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


def _split_cars(boxes: FrameBoxes) -> FrameBoxes:
    """Each car box becomes a body (ground to beltline) and a narrower, shorter cabin on top,
    both with the car's instance id (cabins appended after all other boxes)."""
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
    names = [f.name for f in fields(boxes)]
    out = {f: getattr(boxes, f).clone() for f in names}
    out["centre"][car] = body_centre
    out["half"][car] = body_half
    out["base"][car] = base - body_dy
    extra = {f: getattr(boxes, f)[car] for f in names}
    extra.update(
        centre=cabin_centre,
        half=cabin_half,
        base=base - cabin_dy,
        kind=torch.full_like(extra["kind"], CABIN),
    )
    return FrameBoxes(**{f: torch.cat([out[f], extra[f]]) for f in out})


# The 12 edges of a box whose corners are numbered by the bits (x, y, z) of 0 … 7.
_EDGES = torch.tensor(
    [[a, a | (1 << b)] for a in range(8) for b in range(3) if not a & (1 << b)], dtype=torch.long
)
_CORNER_SIGNS = torch.tensor([[1.0 if c & (1 << i) else -1.0 for i in range(3)] for c in range(8)])


def screen_rects(
    boxes: FrameBoxes, R_cw: torch.Tensor, K: torch.Tensor, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel bounding rectangles of the boxes' outlines clipped at the near plane.

    Args:
        boxes: the frame's boxes.
        R_cw: ``(3, 3)`` float32 rotation from world to camera axes.
        K: ``(4,)`` float32 ``(fx, fy, cx, cy)`` pixels.
        height, width: image size (pixels).

    Returns:
        ``(rect, visible)``: ``(K, 4)`` ``u0, u1, v0, v1`` (pixels) and ``(K,)`` whether any
        part of the box is in front of the near plane and overlaps the image.
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


def _box_tiles(rect: torch.Tensor, nth: int, ntw: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every (box, tile) pair to test: the tiles each box's rectangle (grown by a pixel)
    overlaps.

    Args:
        rect: ``(K, 4)`` pixel rectangles ``u0, u1, v0, v1``.
        nth, ntw: the number of tile rows and columns.

    Returns:
        ``(box, tile)``: ``(P,)`` long each, the box and the tile (row-major) of every pair,
        grouped by box.
    """
    tu0 = ((rect[:, 0] - 1) / TILE).floor().clamp(0, ntw - 1).long()
    tu1 = ((rect[:, 1] + 1) / TILE).floor().clamp(0, ntw - 1).long()
    tv0 = ((rect[:, 2] - 1) / TILE).floor().clamp(0, nth - 1).long()
    tv1 = ((rect[:, 3] + 1) / TILE).floor().clamp(0, nth - 1).long()
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
    return box, tile


def _slab_depths(
    boxes: FrameBoxes, box: torch.Tensor, ax: torch.Tensor, ay: torch.Tensor, az: torch.Tensor
) -> torch.Tensor:
    """Depth of the entry of rays into boxes (slab method in each box's own frame).

    Args:
        boxes: the frame's boxes.
        box: ``(P,)`` long, the box each row of rays is tested against.
        ax, ay, az: ``(P, T)`` world-axis ray directions (``T`` rays per row).

    Returns:
        ``(P, T)`` depth in metres of the hit (inf: the ray misses the box or enters it closer
        than ``NEAR``).
    """
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
    return torch.where((near <= far) & (near > NEAR), near, torch.full_like(near, float("inf")))


def cast_boxes(
    boxes: FrameBoxes,
    rect: torch.Tensor,
    rays: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest box hit of every pixel, testing each box only on the tiles its outline overlaps.

    Args:
        boxes: the frame's boxes, all visible.
        rect: ``(K, 4)`` pixel rectangles of the boxes (:func:`screen_rects`).
        rays: world-axis ray directions ``(H, W)`` each (camera ray ``(x, y, 1)`` rotated).
        height, width: image size (pixels).

    Returns:
        ``(depth, box)``: ``(H, W)`` depth of the nearest box hit (metres, inf: none) and its
        index in ``boxes`` (-1: none; the highest index on a tie).
    """
    T = TILE
    nth, ntw = -(-height // T), -(-width // T)
    pad = (0, ntw * T - width, 0, nth * T - height)
    # The rays of every tile as one row of T² (the image padded to whole tiles).
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
    box, tile = _box_tiles(rect, nth, ntw)
    t = _slab_depths(boxes, box, *(r.index_select(0, tile) for r in tiles))  # (P, T²)
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
