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

This module is the renderer's public face and the camera (rays, vignette, exposure, sensor
noise); the stages live beside it: :mod:`.frame_boxes` (the frame's boxes, their screen
rectangles and tiled ray casting), :mod:`.ground_casting` (the height field), :mod:`.shading`
(surface colours, sky, fog), :mod:`.textures` (noise and prefiltered lines) and
:mod:`.optical_flow` (the exact flow); :mod:`.clipping` holds the depth range they share.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from mfg_lightning.core import geometry
from mfg_lightning.scene.camera import FAR_PLANE
from mfg_lightning.scene.clipping import CULL_DISTANCE, NEAR
from mfg_lightning.scene.frame_boxes import FrameBoxes, cast_boxes, frame_boxes, screen_rects
from mfg_lightning.scene.ground_casting import cast_ground
from mfg_lightning.scene.optical_flow import flow_from_depth
from mfg_lightning.scene.seeding import seeded_rng
from mfg_lightning.scene.shading import FOG_START, RayHits, shade_pixels
from mfg_lightning.scene.textures import lookup, random_table
from mfg_lightning.scene.worlds import Ground, World

__all__ = [
    "CULL_DISTANCE",
    "FAR_FIELD_DEPTH",
    "FAR_PLANE",
    "FOG_START",
    "MAX_SIZE",
    "MIN_SIZE",
    "NEAR",
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
#: Smallest and largest image side (pixels).
MIN_SIZE, MAX_SIZE = 16, 4096


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
    """``intrinsics`` as ``(4,)`` float64 ``(fx, fy, cx, cy)`` pixels; ``ValueError`` unless
    they are 4 finite numbers with positive focal lengths."""
    K = torch.as_tensor(intrinsics, dtype=torch.float64).reshape(-1)
    if K.shape != (4,) or not bool(torch.isfinite(K).all()) or not bool((K[:2] > 0).all()):
        raise ValueError(
            f"intrinsics must be 4 finite numbers (fx, fy, cx, cy) with fx, fy > 0, "
            f"got {tuple(torch.as_tensor(intrinsics).shape)} {torch.as_tensor(intrinsics).tolist()}"
        )
    return K


def _check_frame(world: World, frame: int) -> int:
    """``frame`` as an int; ``ValueError`` unless it is a frame of ``world``'s trajectory."""
    if not 0 <= int(frame) < world.num_frames:
        raise ValueError(
            f"frame {frame} is outside trajectory {world.name!r} "
            f"(frames 0 … {world.num_frames - 1})"
        )
    return int(frame)


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
            (:func:`mfg_lightning.scene.camera.kitti_like_intrinsics` is the default camera).
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
    rays = _camera_rays(K, R, height, width)
    ground = world.ground(frame)
    boxes, hits = _cast_rays(world, frame, ground, origin, R, K, rays)
    colour = shade_pixels(world, ground, boxes, hits, origin, float(K[0]))
    rgb = _camera_response(world, frame, colour, height, width)
    region, instance = _regions(boxes, hits)
    return RenderedFrame(
        rgb=rgb.contiguous(),
        depth=hits.depth.view(height, width),
        region=region.view(height, width),
        instance=instance.view(height, width),
        frame=frame,
        intrinsics=K,
    )


def _camera_rays(K: Tensor, R: Tensor, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """World-axis directions ``R · (x, y, 1)`` of the rays through every pixel centre.

    Args:
        K: ``(4,)`` float64 ``(fx, fy, cx, cy)`` pixels.
        R: ``(3, 3)`` float32 camera-to-world rotation.

    Returns:
        ``(dx, dy, dz)``, ``(H, W)`` float32 each; the ray's parameter is depth along z.
    """
    xy = geometry.normalized_grid(K[None], height, width)[0].float()
    x, y = xy[0], xy[1]
    # Written out so the order of operations is fixed.
    return tuple(x * R[i, 0] + y * R[i, 1] + R[i, 2] for i in range(3))


def _cast_rays(
    world: World,
    frame: int,
    ground: Ground,
    origin: np.ndarray,
    R: Tensor,
    K: Tensor,
    rays: tuple[Tensor, Tensor, Tensor],
) -> tuple[FrameBoxes, RayHits]:
    """Cast every ray against the frame's boxes, then the ground: the nearest surface wins.

    Args:
        world, frame: what is rendered.
        ground: the frame's ground (``world.ground(frame)``).
        origin: ``(3,)`` the camera centre in world coordinates (metres).
        R, K: as :func:`_camera_rays`.
        rays: ``(H, W)`` world-axis ray directions (:func:`_camera_rays`).

    Returns:
        ``(boxes, hits)``: the boxes on screen (``hits.box`` indexes them) and what every
        pixel's ray hit (flattened row-major).
    """
    height, width = rays[0].shape
    boxes = frame_boxes(world, frame, origin)
    rect, visible = screen_rects(boxes, R.T, K.float(), height, width)
    keep = visible.nonzero(as_tuple=True)[0]
    boxes = boxes.select(keep)
    t_box, box = cast_boxes(boxes, rect[keep], rays, height, width)
    dx, dy, dz = (r.reshape(-1) for r in rays)
    t_box, box = t_box.reshape(-1), box.reshape(-1)
    # Rays that hit a box above the ground skip the ground (see cast_ground).
    t_ground = cast_ground(ground, origin, dx, dy, dz, t_box)
    on_box = (t_box < t_ground) & (t_box < FAR_PLANE)
    on_ground = ~on_box & (t_ground < FAR_PLANE)
    sky = ~on_box & ~on_ground
    depth = torch.where(on_box, t_box, torch.where(on_ground, t_ground, FAR_PLANE))
    box = torch.where(on_box, box, -1)
    return boxes, RayHits(dx, dy, dz, depth, box, on_box, on_ground, sky)


def _camera_response(world: World, frame: int, colour: Tensor, height: int, width: int) -> Tensor:
    """The camera's image of the surface colours ``colour`` (``(H·W, 3)`` RGB 0-255):
    vignette, this frame's exposure gain, sensor noise, 8 bits. ``(3, H, W)`` uint8."""
    u = (torch.arange(width, dtype=torch.float32) - (width - 1) / 2) / (width / 2)
    v = (torch.arange(height, dtype=torch.float32) - (height - 1) / 2) / (height / 2)
    vignette = 1.0 - 0.09 * (u[None] ** 2 + v[:, None] ** 2)
    gain = float(world.exposure[frame])
    noise = _sensor_noise(world, frame, height, width)
    image = (
        colour.T.reshape(3, height, width) * (gain * vignette) + world.config.sensor_noise * noise
    )
    return image.round_().clamp_(0, 255).to(torch.uint8)


def _sensor_noise(world: World, frame: int, height: int, width: int) -> Tensor:
    """Standard-normal sensor noise ``(3, H, W)`` of one frame.

    Drawn from the world's table of 2¹⁶ normal values through a random affine map of the pixel
    coordinates per frame and channel (odd multipliers, so every row is a permutation of a
    stretch of the table): as good as fresh noise for an optical-flow estimator, and cheaper.
    """
    table = random_table(world.seed, world.name, "sensor")
    coeff = seeded_rng(world.seed, "world", world.name, "sensor", frame).integers(
        0, 1 << 16, (3, 3)
    )
    u = torch.arange(width)[None]
    v = torch.arange(height)[:, None]
    mask = (1 << 16) - 1
    return torch.stack(
        [
            lookup(table, (u * (2 * int(a) + 1) + v * (2 * int(b) + 1) * 977 + int(o)) & mask)
            for a, b, o in coeff
        ]
    )


def _regions(boxes: FrameBoxes, hits: RayHits) -> tuple[Tensor, Tensor]:
    """The region ``(n,)`` uint8 and moving-object instance ``(n,)`` int32 (-1: none) of every
    pixel."""
    box = hits.box
    # A frame may see no box at all (an open stretch of road): nothing to look up then.
    obj = boxes.instance[box.clamp_min(0)] if len(boxes.instance) else torch.full_like(box, -1)
    is_moving = hits.on_box & (obj >= 0)
    region = torch.where(
        hits.on_ground,
        REGION_ROAD,
        torch.where(
            is_moving, REGION_MOVING, torch.where(hits.on_box, REGION_STRUCTURE, REGION_FAR)
        ),
    )
    region = torch.where(hits.depth > FAR_FIELD_DEPTH, REGION_FAR, region).to(torch.uint8)
    instance = torch.where(is_moving, obj, -1).to(torch.int32)
    return region, instance


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
    (:func:`mfg_lightning.core.geometry.reprojection_flow`; see :mod:`.optical_flow`).

    Args:
        world, intrinsics, height, width: as :func:`render_frame`.
        src, tgt: frame indices.
        source: the rendered source frame, reused instead of rendering it again.
        target: the rendered target frame; when given, adds ``"occluded"`` and ``"visible"``.

    Returns:
        ``"flow"``: ``(2, H, W)`` float32 pixels; ``"flow_valid"``: ``(H, W)`` bool, finite
        flow of a point in front of the target camera; ``"out_of_frame"``: ``(H, W)`` bool,
        valid pixels whose flow lands outside the target image; ``"object_mask"``: ``(H, W)``
        bool, valid pixels on moving objects; ``"object_flow"``: ``(2, H, W)`` float32, the
        part of the flow due to the objects' own motion (zero elsewhere); ``"depth"``:
        ``(H, W)`` float32 source depth (metres). With ``target``: ``"occluded"``, ``(H, W)``
        bool, valid pixels landing inside the target image whose point is more than
        :data:`~.optical_flow.OCCLUSION_TOLERANCE` (2 %) behind the largest depth the target
        frame sees at the four pixel centres around where it lands; ``"visible"``, valid
        pixels neither out of frame nor occluded (:func:`.optical_flow.visibility`). The flow
        is the same for all: marking a pixel changes nothing of its flow.

    Raises:
        ValueError: as :func:`render_frame`, or a ``source`` of another frame or size.
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
    target_depth = None if target is None else target.depth
    return flow_from_depth(world, src, tgt, K, source.depth, source.instance, target_depth)
