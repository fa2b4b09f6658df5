"""Surface shading of the persistent-world renderer: the colour of every pixel from what its
ray hit (:class:`RayHits`), before the camera's vignette, exposure and noise.

* **Ground**: asphalt with grain at several scales, tyre-worn lanes, dashed and solid lane
  markings in the road coordinates ``(s, d)`` of the ground's grid, kerb stones, paving slabs,
  grass beyond the building line.
* **Boxes**: one shader per kind. Facades get walls (plaster, brick or concrete panels) with
  windows and shop fronts, car bodies paint, wheels and lights, cabins dark glass between
  pillars, containers corrugated walls, pedestrians legs, torso and head. Their texture
  parameters are the box's ``params`` columns named in :mod:`.box_params`.
* **Sky**: an almost uniform gradient with faint clouds.

Faces are lit by the world's sun (Lambert) and surfaces fade into the horizon's colour from
``FOG_START`` to the culling distance. Colours are float32 RGB on the 0-255 scale, ``(n, 3)``
for ``n`` pixels; footprints are the metres a pixel spans on the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from mfg_lightning.scene import box_params as bp
from mfg_lightning.scene.clipping import CULL_DISTANCE
from mfg_lightning.scene.frame_boxes import CABIN, FrameBoxes
from mfg_lightning.scene.road import Ground
from mfg_lightning.scene.textures import (
    cell_random,
    coverage,
    fade,
    fbm,
    grey_rgb,
    noise,
    noise_table,
    periodic_dist,
)
from mfg_lightning.scene.worlds import CAR, CRATE, FACADE, PARKED_CAR, PEDESTRIAN, World

__all__ = ["FOG_START", "HORIZON", "ZENITH", "RayHits", "haze", "shade_pixels"]

#: Depth (metres) where the distance fog starts.
FOG_START = 40.0
#: Sky colours at the horizon and the zenith (RGB 0-255); the fog fades into the horizon's.
HORIZON = torch.tensor([200.0, 212.0, 226.0])
ZENITH = torch.tensor([92.0, 146.0, 212.0])


@dataclass
class RayHits:
    """What the ray casts found at every pixel (``n`` pixels, flattened row-major).

    Attributes:
        dx, dy, dz: ``(n,)`` float32 world-axis directions of the camera rays ``(x, y, 1)``.
        depth: ``(n,)`` float32 depth of the surface seen (metres; ``FAR_PLANE`` for sky).
        box: ``(n,)`` long index into the frame's boxes of the box seen, -1 elsewhere.
        on_box, on_ground, sky: ``(n,)`` bool, what the pixel sees (exactly one is true).
    """

    dx: Tensor
    dy: Tensor
    dz: Tensor
    depth: Tensor
    box: Tensor
    on_box: Tensor
    on_ground: Tensor
    sky: Tensor


@dataclass
class _BoxSurface:
    """The hits on boxes of one kind, as every box shader reads them (``n`` pixels).

    Attributes:
        table: the world's noise table (:func:`~.textures.noise_table`).
        p: ``(n, 3)`` box-local hit points (metres).
        face: ``(n,)`` the axis of the face hit (0 sides, 1 top or bottom, 2 ends).
        hh: ``(n,)`` height of the hit above the ground (metres).
        fp: ``(n,)`` the pixel footprint on the face (metres).
        half: ``(n, 3)`` the box's half sizes (metres).
        colour, colour2, params: the box's colours ``(n, 3)`` and texture parameters
            ``(n, NUM_PARAMS)`` (see :class:`~.furnishing.Boxes`; columns named in
            :mod:`.box_params`).
    """

    table: Tensor
    p: Tensor
    face: Tensor
    hh: Tensor
    fp: Tensor
    half: Tensor
    colour: Tensor
    colour2: Tensor
    params: Tensor


def haze(rgb: Tensor, t: Tensor) -> Tensor:
    """Distance fog on colours ``rgb`` ``(n, 3)`` at depths ``t`` ``(n,)`` (metres): surfaces
    fade into the horizon's colour from ``FOG_START`` on and are gone at ``CULL_DISTANCE``, so
    nothing visibly appears where culling starts."""
    f = ((t - FOG_START) / (CULL_DISTANCE - FOG_START)).clamp(0, 1)
    return rgb + (f * f * (3 - 2 * f))[:, None] * (HORIZON - rgb)


def shade_pixels(
    world: World,
    ground: Ground,
    boxes: FrameBoxes,
    hits: RayHits,
    origin: np.ndarray,
    fx: float,
) -> Tensor:
    """Colour ``(n, 3)`` of every pixel, sky, ground and boxes each shaded on its own pixels.

    Args:
        world: the world rendered (its textures' seed, layout, sun).
        ground: the ground of the frame's section.
        boxes: the frame's boxes (``hits.box`` indexes them).
        hits: what every pixel's ray hit.
        origin: ``(3,)`` the camera centre in world coordinates (metres).
        fx: the focal length in pixels (sets the pixel footprints).
    """
    dx, dy, dz, depth = hits.dx, hits.dy, hits.dz, hits.depth
    table = noise_table(world.seed, world.name)
    colour = torch.empty(len(dx), 3)
    norm = torch.sqrt(dx * dx + dy * dy + dz * dz)
    fp_lat = depth * norm / fx  # metres per pixel across the ray at the hit
    sun = torch.from_numpy(world.sun).float()
    idx = hits.sky.nonzero(as_tuple=True)[0]
    if len(idx):
        colour.index_copy_(0, idx, _shade_sky(table, *_take(idx, dx, dy, dz)))
    idx = hits.on_ground.nonzero(as_tuple=True)[0]
    if len(idx):
        t, gdx, gdy, gdz, gnorm, gfp = _take(idx, depth, dx, dy, dz, norm, fp_lat)
        gx = float(origin[0]) + t * gdx
        gz = float(origin[2]) + t * gdz
        cos_inc = (gdy / gnorm).abs().clamp_min(0.02)
        light = 0.62 + 0.38 * float(-world.sun[1])
        rgb = _shade_ground(world, ground, table, gx, gz, gfp, gfp / cos_inc)
        colour.index_copy_(0, idx, haze(light * rgb, t))
    idx = hits.on_box.nonzero(as_tuple=True)[0]
    if len(idx):
        hit = _take(idx, hits.box, depth, dx, dy, dz, norm, fp_lat)
        colour.index_copy_(0, idx, haze(_shade_boxes(table, boxes, *hit, sun), hit[1]))
    return colour


def _take(index: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
    """The rows ``index`` (``(n,)`` long) of every tensor, in order: one ``index_select`` along
    dim 0 each (gathering the pixels of one surface; cheaper than boolean masks on CPU)."""
    return tuple(t.index_select(0, index) for t in tensors)


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
        grey = 94.0 + fbm(
            table,
            px,
            pz,
            grain,
            [(7.0, 6.0), (1.6, 5.0), (0.4, 5.0), (0.12, 6.0), (0.035, 9.0), (0.012, 7.0)],
        )
        grey = grey - 6.0 * coverage((periodic_dist(pd, L, 0.0) - 0.8).abs(), 0.5, pfl)
        paint = coverage((pad - (half - 0.15)).abs(), 0.15, pfl)
        if cfg.lanes_per_side > 0:
            dash = coverage(periodic_dist(pd, L, L / 2), 0.12, pfl) * coverage(
                periodic_dist(ps, 9.0, 1.5), 3.0, pf
            )
            paint = torch.maximum(paint, dash * (pad < half - 0.5))
        wear = 1.0 + 0.08 * noise(table, px / 0.7 + 11.0, pz / 0.7)
        grey = grey + paint * (205.0 * wear - grey)
        out.index_copy_(0, idx, grey_rgb(grey, (1.0, 1.0, 1.03)))
    # Kerb stones.
    idx, px, pz, ps, pd, pad, pfl, pf = part((ad >= kerb) & (ad < kerb + 0.2))
    if len(idx):
        grey = 160.0 + fbm(table, px, pz + 300.0, pf, [(0.3, 5.0), (0.05, 5.0)])
        out.index_copy_(0, idx, grey_rgb(grey))
    # Sidewalk: 0.6 m slabs with seams, each slab its own shade.
    idx, px, pz, ps, pd, pad, pfl, pf = part((ad >= kerb + 0.2) & (ad <= line))
    if len(idx):
        grey = 138.0 + 8.0 * cell_random(table, (ps / 0.6).floor(), (pad / 0.6).floor())
        grey = grey + fbm(table, px + 500.0, pz, pf, [(0.5, 4.0), (0.05, 6.0)])
        seam = torch.maximum(
            coverage(periodic_dist(ps, 0.6, 0.0), 0.025, pf),
            coverage(periodic_dist(pad, 0.6, 0.0), 0.025, pf),
        )
        out.index_copy_(0, idx, grey_rgb(grey - 45.0 * seam, (1.0, 0.99, 0.97)))
    # Verge beyond the building line: grass and dirt.
    idx, px, pz, ps, pd, pad, pfl, pf = part(ad > line)
    if len(idx):
        g = fbm(table, px + 900.0, pz, pf, [(3.0, 0.5), (0.6, 0.35), (0.12, 0.25), (0.04, 0.2)])
        out.index_copy_(0, idx, torch.stack([88 + 30 * g, 104 + 34 * g, 58 + 18 * g], -1))
    return out


def _shade_facade(s: _BoxSurface, top: Tensor) -> Tensor:
    """Facade walls with windows, ``(n, 3)`` RGB; ``top`` ``(n,)`` is the facade's height above
    the ground (metres)."""
    table, p, face, hh, fp = s.table, s.p, s.face, s.hh, s.fp
    colour, colour2, params = s.colour, s.colour2, s.params
    floor_h, spacing = params[:, bp.PARAM_FLOOR_HEIGHT], params[:, bp.PARAM_WINDOW_SPACING]
    win_w = params[:, bp.PARAM_WINDOW_WIDTH] * spacing
    win_h = params[:, bp.PARAM_WINDOW_HEIGHT] * floor_h
    style = params[:, bp.PARAM_FACADE_STYLE]
    shop = params[:, bp.PARAM_FACADE_SHOP] < bp.SHOP_FRONT_BELOW
    u = torch.where(face == 0, p[:, 2], p[:, 0]) + params[:, bp.PARAM_FACADE_OFFSET_U]
    v = hh
    v_wall = v + params[:, bp.PARAM_FACADE_OFFSET_V]
    wall = 1.0 + fbm(table, u, v_wall, fp, [(3.0, 0.05), (0.6, 0.05), (0.12, 0.05)])
    brick_rows = periodic_dist(v, 0.075, 0.0)
    brick_cols = periodic_dist(u + 0.125 * ((v / 0.075).floor() % 2), 0.25, 0.0)
    mortar = torch.maximum(coverage(brick_rows, 0.012, fp), coverage(brick_cols, 0.012, fp))
    brick = wall * (1.0 + 0.06 * cell_random(table, (u / 0.25).floor(), (v / 0.075).floor()))
    brick = brick * (1 - 0.35 * mortar) + 0.35 * mortar * 1.25
    panel = torch.maximum(
        coverage(periodic_dist(u, 1.5, 0.0), 0.03, fp),
        coverage(periodic_dist(v, floor_h, 0.0), 0.03, fp),
    )
    concrete = wall * (1.0 - 0.25 * panel)
    tone = torch.where(
        style == bp.STYLE_BRICK, brick, torch.where(style == bp.STYLE_CONCRETE, concrete, wall)
    )
    rgb = colour * tone[:, None]
    # Windows: one per (column, floor); glass of its own shade, a light frame around it.
    col = (u / spacing).floor()
    level = (v / floor_h).floor()
    du = (u - (col + 0.5) * spacing).abs()
    dv = (v - level * floor_h - 0.9 - win_h / 2).abs()
    upper = (level >= 1) & (v < top - 0.9)
    glass_cov = coverage(du, win_w, fp) * coverage(dv, win_h, fp) * upper
    frame_cov = coverage(du, win_w + 0.16, fp) * coverage(dv, win_h + 0.16, fp) * upper
    # Shop fronts: one wide pane per column on the ground floor, from 0.4 m to 2.6 m.
    shop_cov = coverage(du, 0.85 * spacing, fp) * coverage((v - 1.5).abs(), 2.2, fp) * shop
    glass_cov = torch.maximum(glass_cov, shop_cov)
    frame_cov = torch.maximum(frame_cov, shop_cov)
    pane_row = level + 3 * params[:, bp.PARAM_FACADE_OFFSET_U].floor()
    pane = 0.75 + 0.35 * cell_random(table, col, pane_row)
    glass = colour2 * pane[:, None] + 18.0 * (1 - dv / win_h.clamp_min(0.1))[:, None]
    frame = torch.tensor([215.0, 212.0, 205.0])
    rgb = rgb + frame_cov[:, None] * (frame - rgb)
    rgb = rgb + glass_cov[:, None] * (glass - rgb)
    plinth = coverage((v - 0.2).abs(), 0.4, fp)[:, None]
    return rgb * (1 - 0.3 * plinth)


def _shade_car(s: _BoxSurface, front_sign: float) -> Tensor:
    """Car bodies (ground to beltline): nearly uniform paint, wheels, lights, a dark sill."""
    table, p, face, hh, fp, half = s.table, s.p, s.face, s.hh, s.fp, s.half
    colour, params = s.colour, s.params
    along = p[:, 2]
    belt = half[:, 1] * 2 - 0.25  # body height above the ground (0.25 m are buried)
    offset = params[:, bp.PARAM_TEXTURE_OFFSET]
    mottle = fbm(table, p[:, 0] + offset, along + hh, fp, [(0.8, 0.02), (0.2, 0.015)])
    paint = colour * (1.0 + mottle)[:, None]
    paint = paint * (0.8 + 0.2 * (hh / belt).clamp(0, 1))[:, None]
    side = face == 0
    endf = face == 2
    wheel_z = half[:, 2] - 0.8
    wheel = (
        torch.minimum(
            coverage((along.abs() - wheel_z).abs(), 0.62, fp), coverage((hh - 0.3).abs(), 0.6, fp)
        )
        * side
    )
    under = coverage((hh - 0.08).abs(), 0.16, fp)
    lamp_x = coverage((p[:, 0].abs() - (half[:, 0] - 0.25)).abs(), 0.3, fp)
    lamp = lamp_x * coverage((hh - 0.62).abs(), 0.12, fp) * endf
    plate = coverage(p[:, 0].abs(), 0.5, fp) * coverage((hh - 0.42).abs(), 0.12, fp) * endf
    is_front = (p[:, 2] * front_sign) > 0
    lamp_colour = torch.where(
        is_front[:, None], torch.tensor([225.0, 225.0, 205.0]), torch.tensor([170.0, 25.0, 20.0])
    )
    rgb = paint + lamp[:, None] * (lamp_colour - paint)
    rgb = rgb + plate[:, None] * (torch.tensor([225.0, 225.0, 220.0]) - rgb)
    dark = torch.maximum(wheel, under)[:, None]
    return rgb + dark * (torch.tensor([22.0, 22.0, 24.0]) - rgb)


def _shade_cabin(s: _BoxSurface) -> Tensor:
    """Car cabins: dark glass all round between painted pillars, a painted roof."""
    p, face, fp, half = s.p, s.face, s.fp, s.half
    colour, colour2 = s.colour, s.colour2
    pillar_side = torch.maximum(
        coverage(half[:, 2] - p[:, 2].abs(), 0.3, fp), coverage(p[:, 2].abs(), 0.12, fp)
    )
    pillar_end = coverage(half[:, 0] - p[:, 0].abs(), 0.16, fp)
    pillar = torch.where(face == 0, pillar_side, pillar_end)
    rail = coverage(half[:, 1] + p[:, 1], 0.08, fp)  # the roof's edge, just below the roof
    frame = torch.maximum(pillar, rail)
    shine = ((half[:, 1] - p[:, 1]) / (2 * half[:, 1])).clamp(0, 1)  # 0 at the belt, 1 at roof
    glass = colour2 + (25.0 * shine)[:, None]
    rgb = glass + frame[:, None] * (colour - glass)
    return torch.where((face == 1)[:, None], colour, rgb)


def _shade_crate(s: _BoxSurface) -> Tensor:
    """Containers and vans: corrugated, weathered walls, some with a light label."""
    table, p, face, hh, fp = s.table, s.p, s.face, s.hh, s.fp
    colour, params = s.colour, s.params
    u = torch.where(face == 0, p[:, 2], p[:, 0])
    period = params[:, bp.PARAM_CRATE_RIB_PERIOD]
    rib = periodic_dist(u, period, 0.0) / period  # 0 … 0.5
    ribs = 1.0 + 0.12 * (4 * rib - 1) * fade(fp, 1.0) * (fp < period / 2)
    rust = 1.0 + fbm(
        table,
        u + params[:, bp.PARAM_TEXTURE_OFFSET],
        hh,
        fp,
        [(1.5, 0.08), (0.3, 0.06), (0.06, 0.05)],
    )
    rgb = colour * (ribs * rust)[:, None]
    label = (
        coverage(u.abs(), 2.2, fp)
        * coverage((hh - 1.3).abs(), 0.6, fp)
        * (params[:, bp.PARAM_CRATE_LABEL] > 0.5)
        * (face == 0)
    )
    return rgb + label[:, None] * (torch.tensor([235.0, 235.0, 228.0]) - rgb)


def _shade_pedestrian(s: _BoxSurface) -> Tensor:
    """Pedestrians: legs, torso, head."""
    table, p, hh, fp, half = s.table, s.p, s.hh, s.fp, s.half
    colour, colour2, params = s.colour, s.colour2, s.params
    top = half[:, 1] * 2
    cloth = 1.0 + fbm(
        table,
        p[:, 0] + p[:, 2] + params[:, bp.PARAM_TEXTURE_OFFSET],
        hh,
        fp,
        [(0.3, 0.08), (0.08, 0.06)],
    )
    rgb = torch.where((hh < 0.47 * top)[:, None], colour2, colour) * cloth[:, None]
    return torch.where((hh > 0.85 * top)[:, None], params[:, bp.PARAM_PEDESTRIAN_SKIN], rgb)


def _shade_sky(table: Tensor, dx: Tensor, dy: Tensor, dz: Tensor) -> Tensor:
    """Sky colour ``(n, 3)`` for world ray directions: a gradient and faint clouds."""
    norm = torch.sqrt(dx * dx + dy * dy + dz * dz)
    up = (-dy / norm).clamp(0, 1)
    g = torch.sqrt((up / 0.6).clamp(0, 1))
    colour = HORIZON + g[:, None] * (ZENITH - HORIZON)
    # Clouds on a plane 1 km up, seen through the ray: faint, large, smooth.
    k = 1000.0 / (-dy / norm).clamp_min(0.05) / norm
    cloud = noise(table, dx * k / 900.0, dz * k / 900.0) + 0.5 * noise(
        table, dx * k / 300.0 + 50.0, dz * k / 300.0
    )
    cover = ((cloud - 0.3).clamp(0, 1) * (up / 0.2).clamp(0, 1))[:, None] * 0.5
    return colour + cover * (torch.tensor([236.0, 238.0, 242.0]) - colour)


def _shade_boxes(
    table: torch.Tensor,
    boxes: FrameBoxes,
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
        surface = _BoxSurface(
            table,
            *_take(sel, p, face, hh, fp, half),
            *_take(bs, boxes.colour, boxes.colour2, boxes.params),
        )
        if k == FACADE:
            top = boxes.base.index_select(0, bs) + boxes.half.index_select(0, bs)[:, 1]
            out = _shade_facade(surface, top)
            out = torch.where((surface.face == 1)[:, None], torch.tensor([85.0, 82.0, 80.0]), out)
        elif k in (PARKED_CAR, CAR):
            out = _shade_car(surface, 1.0)
        elif k == CABIN:
            out = _shade_cabin(surface)
        elif k == CRATE:
            out = _shade_crate(surface)
        else:
            out = _shade_pedestrian(surface)
        rgb.index_copy_(0, sel, out)
    return rgb * (0.58 + 0.42 * lambert)[:, None]
