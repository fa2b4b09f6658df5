"""The furniture of a persistent world (:class:`~mfg_lightning.scene.worlds.World`): its static
boxes (facades, parked cars, crates) and its moving objects (cars, pedestrians), placed at road
coordinates along the path with their sizes, colours and texture parameters.

Every function draws from the random generator it is given in a fixed order: a world is a pure
function of its seed (:mod:`mfg_lightning.scene.seeding`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Protocol, TypeVar

import numpy as np
import torch

from mfg_lightning.scene.box_params import (
    NUM_PARAMS,
    PARAM_CRATE_LABEL,
    PARAM_CRATE_RIB_PERIOD,
    PARAM_FACADE_OFFSET_U,
    PARAM_FACADE_OFFSET_V,
    PARAM_FACADE_SHOP,
    PARAM_FACADE_STYLE,
    PARAM_FLOOR_HEIGHT,
    PARAM_PEDESTRIAN_SKIN,
    PARAM_SPARE_OFFSET,
    PARAM_TEXTURE_OFFSET,
    PARAM_WINDOW_HEIGHT,
    PARAM_WINDOW_SPACING,
    PARAM_WINDOW_WIDTH,
)
from mfg_lightning.scene.world_config import WorldConfig


class Street(Protocol):
    """The path boxes are placed along (:class:`~mfg_lightning.scene.worlds.World` is one)."""

    config: WorldConfig
    path_s: np.ndarray  # (P,) arc length of the resampled centreline (metres)

    def path_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centreline point ``(n, 3)`` and unit heading ``(n, 2)`` at arc lengths ``(n,)``."""
        ...


#: Box kinds. Facades, parked cars and crates are static; cars and pedestrians move.
FACADE, PARKED_CAR, CRATE, CAR, PEDESTRIAN = 0, 1, 2, 3, 4
KIND_NAMES = ("facade", "parked car", "crate", "car", "pedestrian")

# Full sizes (x width, y height, z length) in metres.
_CAR_SIZE = (1.8, 1.5, 4.2)
_PEDESTRIAN_SIZE = (0.55, 1.75, 0.35)
_CRATE_SIZES = ((2.4, 2.6, 6.0), (2.0, 2.2, 5.0), (1.9, 1.9, 2.5))

# Colour palettes (RGB, 0-255) before lighting.
_WALLS = np.array(
    [[196, 178, 150], [170, 160, 150], [205, 195, 175], [150, 85, 60],
     [120, 120, 125], [215, 205, 190], [180, 140, 100], [160, 170, 160]],
    dtype=np.float64,
)  # fmt: skip
_CAR_PAINT = np.array(
    [[200, 200, 205], [30, 30, 35], [120, 125, 130], [150, 30, 30],
     [25, 50, 110], [230, 230, 230], [70, 90, 60], [180, 150, 60]],
    dtype=np.float64,
)  # fmt: skip
_CRATE_PAINT = np.array(
    [[170, 60, 40], [40, 90, 150], [60, 120, 70], [210, 140, 40], [200, 200, 190]],
    dtype=np.float64,
)
_CLOTHES = np.array(
    [[40, 40, 50], [60, 70, 110], [150, 40, 40], [200, 190, 170], [90, 90, 90], [40, 100, 60]],
    dtype=np.float64,
)
_SKIN = np.array([[225, 190, 160], [190, 140, 110], [120, 85, 60]], dtype=np.float64)


def yaw_pose(centre: np.ndarray, yaw: np.ndarray) -> torch.Tensor:
    """Poses ``T_world_obj`` of boxes turned by ``yaw`` about the world's vertical (y) axis.

    The object's z axis (its heading) is ``(sin yaw, 0, cos yaw)``, its x axis (its right)
    ``(cos yaw, 0, -sin yaw)``, its y axis the world's y (down).

    Args:
        centre: ``(M, 3)`` box centres in world coordinates (metres).
        yaw: ``(M,)`` headings in radians.

    Returns:
        ``(M, 4, 4)`` float64.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros((len(yaw), 4, 4))
    T[:, 0, 0], T[:, 0, 2] = c, s
    T[:, 1, 1] = 1.0
    T[:, 2, 0], T[:, 2, 2] = -s, c
    T[:, :3, 3] = centre
    T[:, 3, 3] = 1.0
    return torch.from_numpy(T)


class Rows:
    """A dataclass of arrays of one length, a row per box or object: its first field gives the
    length, and every field (arrays, or other :class:`Rows`) is joined or selected alike."""

    def __len__(self) -> int:
        return len(getattr(self, fields(self)[0].name))

    @classmethod
    def concat(cls: type[R], parts: list[R]) -> R:
        """The parts' rows one after the other, in order."""
        return cls(*(_joined([getattr(p, f.name) for p in parts]) for f in fields(cls)))

    def select(self: R, keep: np.ndarray) -> R:
        """The rows ``keep`` (indices or a boolean mask) picks."""
        return type(self)(*(getattr(self, f.name)[keep] for f in fields(self)))


R = TypeVar("R", bound=Rows)


def _joined(values: list) -> Any:
    return type(values[0]).concat(values) if isinstance(values[0], Rows) else np.concatenate(values)


@dataclass
class Boxes(Rows):
    """A set of yaw-aligned boxes (arrays of one length ``M``).

    Attributes:
        centre: ``(M, 3)`` float64 world coordinates of the box centres (static boxes; moving
            objects get theirs from :meth:`World.object_poses`).
        yaw: ``(M,)`` float64 heading (radians, see :func:`yaw_pose`).
        half: ``(M, 3)`` float64 half sizes along the box's own x, y, z (metres).
        base: ``(M,)`` float64 the box's own y coordinate of the ground level (positive: the
            bottom ``half_y - base`` metres are buried).
        kind: ``(M,)`` int64 one of ``FACADE`` … ``PEDESTRIAN``.
        colour, colour2: ``(M, 3)`` float64 main and secondary colour (wall and glass, paint
            and glass, clothes), RGB 0-255.
        params: ``(M, NUM_PARAMS)`` float64 kind-specific texture parameters, the columns named
            in :mod:`.box_params`.
    """

    centre: np.ndarray
    yaw: np.ndarray
    half: np.ndarray
    base: np.ndarray
    kind: np.ndarray
    colour: np.ndarray
    colour2: np.ndarray
    params: np.ndarray


@dataclass
class MovingObjects(Rows):
    """Cars and pedestrians moving along the road (arrays of one length ``M``).

    Object ``j`` is at arc length ``s0[j] + direction[j] · speed[j] · frame`` (wrapped into the
    path's extended range), ``lateral[j]`` metres to the right of the path, facing along the path
    (``direction = +1``) or against it (``-1``).

    Attributes:
        boxes: appearance and size (:class:`Boxes`; ``centre`` and ``yaw`` unused, zero).
        s0, direction, speed, lateral: ``(M,)`` float64 (metres, ±1, metres per frame, metres).
    """

    boxes: Boxes
    s0: np.ndarray
    direction: np.ndarray
    speed: np.ndarray
    lateral: np.ndarray


@dataclass
class Placed(Rows):
    """Candidate static boxes, placed at road coordinates before any section picks its own
    (``n`` boxes)."""

    boxes: Boxes
    s: np.ndarray  # (n,) arc length each box was placed at (metres)
    clearance: np.ndarray  # (n,) distance it must keep from every pass of the path (metres)
    footprint_x: np.ndarray  # (n, 9) world x of its footprint points (metres)
    footprint_z: np.ndarray  # (n, 9) world z of its footprint points (metres)


def footprints(world: Street, s: np.ndarray, lateral: np.ndarray, half: np.ndarray):
    """Centres, yaws and 9 footprint points ``(n, 9)`` of boxes at road coordinates; point 0
    is the centre of the face towards the road."""
    xyz, heading = world.path_at(s)
    yaw = np.arctan2(heading[:, 0], heading[:, 1])
    right = np.stack([heading[:, 1], -heading[:, 0]], -1)
    cx = xyz[:, 0] + lateral * right[:, 0]
    cz = xyz[:, 2] + lateral * right[:, 1]
    side = -np.sign(lateral)  # towards the road
    a = np.array([1, -1, -1, 1, 1, 0, 0, -1, 0], dtype=np.float64)  # across
    b = np.array([0, -1, 1, -1, 1, -1, 1, 0, 0], dtype=np.float64)  # along
    a = a[None] * half[:, 0:1] * side[:, None]
    b = b[None] * half[:, 2:3]
    px = cx[:, None] + a * right[:, 0:1] + b * heading[:, 0:1]
    pz = cz[:, None] + a * right[:, 1:2] + b * heading[:, 1:2]
    return cx, cz, yaw, px, pz


def boxes_at(
    world: Street,
    s: np.ndarray,
    lateral: np.ndarray,
    size: np.ndarray,
    bury: float,
    kind: int,
    colour: np.ndarray,
    colour2: np.ndarray,
    params: np.ndarray,
    clearance: float,
) -> Placed:
    """Candidate boxes at road coordinates ``(s, lateral)`` (``(n,)`` metres each; their
    centre y is set per section), with their footprints.

    Args:
        size: ``(n, 3)`` full sizes (metres).
        bury: how deep the bottom sits below the ground (metres), so slopes leave no gap.
        kind: the boxes' kind (``FACADE`` … ``PEDESTRIAN``).
        colour, colour2, params: ``(n, 3)``, ``(n, 3)``, ``(n, NUM_PARAMS)``, as
            :class:`Boxes`.
        clearance: the distance (metres) the footprints must keep from every pass.
    """
    half = size / 2
    cx, cz, yaw, px, pz = footprints(world, s, lateral, half)
    boxes = Boxes(
        centre=np.stack([cx, np.zeros_like(cx), cz], -1),
        yaw=yaw,
        half=half,
        base=half[:, 1] - bury,
        kind=np.full(len(s), kind, dtype=np.int64),
        colour=colour,
        colour2=colour2,
        params=params,
    )
    return Placed(boxes, s, np.full(len(s), clearance), px, pz)


def place_static(world: Street, rng: np.random.Generator) -> Placed:
    """Every candidate static box: on each side of the path its facades, then its parked
    boxes (the order of the random draws, which the worlds depend on)."""
    parts: list[Placed] = []
    for side in (-1.0, 1.0):
        for placed in (_place_facades(world, rng, side), _place_parked(world, rng, side)):
            if placed is not None:
                parts.append(placed)
    if not parts:
        return Placed(empty_boxes(), np.zeros(0), np.zeros(0), *(np.zeros((0, 9)),) * 2)
    return Placed.concat(parts)


def _place_facades(world: Street, rng: np.random.Generator, side: float) -> Placed | None:
    """Facades on one side (``side`` -1 left, +1 right): a sequence of blocks and gaps
    along the path, set back behind the building line (None: no block)."""
    cfg = world.config
    s_lo, s_hi = float(world.path_s[0]), float(world.path_s[-1])
    s_list, length, depth, setback = [], [], [], []
    s = s_lo + rng.uniform(0, 10)
    while s < s_hi:
        if rng.random() < cfg.facade_coverage:
            n = rng.uniform(*cfg.facade_length)
            s_list.append(s + n / 2)
            length.append(n)
            depth.append(rng.uniform(*cfg.facade_depth))
            setback.append(rng.uniform(*cfg.facade_setback))
            s += n + rng.choice([0.0, rng.uniform(0.5, 4.0)])
        else:
            s += rng.uniform(6.0, 25.0)
    k = len(s_list)
    if not k:
        return None
    depth_a = np.asarray(depth)
    lateral = side * (cfg.building_line + np.asarray(setback) + depth_a / 2)
    height = rng.uniform(*cfg.facade_height, k)
    size = np.stack([depth_a, height + 1.5, np.asarray(length)], -1)
    wall = _WALLS[rng.integers(0, len(_WALLS), k)] * rng.uniform(0.85, 1.1, (k, 1))
    glass = np.stack([rng.uniform(35, 70, k)] * 3, -1) + rng.uniform(-5, 10, (k, 3))
    # Drawn column by column, in this order.
    params = np.zeros((k, NUM_PARAMS))
    params[:, PARAM_FLOOR_HEIGHT] = rng.uniform(2.9, 3.6, k)
    params[:, PARAM_WINDOW_SPACING] = rng.uniform(2.2, 3.6, k)
    params[:, PARAM_WINDOW_WIDTH] = rng.uniform(0.45, 0.7, k)
    params[:, PARAM_WINDOW_HEIGHT] = rng.uniform(0.4, 0.6, k)
    params[:, PARAM_FACADE_STYLE] = rng.integers(0, 3, k)
    params[:, PARAM_FACADE_OFFSET_U] = rng.uniform(0, 1000, k)
    params[:, PARAM_FACADE_OFFSET_V] = rng.uniform(0, 1000, k)
    params[:, PARAM_FACADE_SHOP] = rng.uniform(0.0, 1.0, k)
    return boxes_at(
        world,
        np.asarray(s_list),
        lateral,
        size,
        1.5,
        FACADE,
        wall,
        glass,
        params,
        cfg.building_line - 0.3,
    )


def _place_parked(world: Street, rng: np.random.Generator, side: float) -> Placed | None:
    """Parked cars and crates in the parking strip on one side (``side`` -1 left, +1
    right), at least 5.5 m between centres (None: no parking, ``parked_per_100m`` 0)."""
    cfg = world.config
    s_lo, s_hi = float(world.path_s[0]), float(world.path_s[-1])
    rate = cfg.parked_per_100m / 100.0
    if not rate > 0:
        return None
    mean_gap = max(1.0 / rate - 5.5, 0.1)
    n_max = int((s_hi - s_lo) * rate * 1.5) + 2
    pos = s_lo + np.cumsum(5.5 + rng.exponential(mean_gap, n_max))
    pos = pos[pos < s_hi]
    k = len(pos)
    crate = rng.random(k) < cfg.crate_fraction
    which = rng.integers(0, len(_CRATE_SIZES), k)
    size = np.where(
        crate[:, None], np.asarray(_CRATE_SIZES)[which], np.asarray(_CAR_SIZE)
    ) * rng.uniform(0.92, 1.08, (k, 1))
    lateral = side * (cfg.road_half_width + cfg.parking_width / 2) + rng.normal(0, 0.1, k)
    paint = np.where(
        crate[:, None],
        _CRATE_PAINT[rng.integers(0, len(_CRATE_PAINT), k)],
        _CAR_PAINT[rng.integers(0, len(_CAR_PAINT), k)],
    ) * rng.uniform(0.9, 1.05, (k, 1))
    glass = np.stack([rng.uniform(25, 45, k)] * 3, -1)
    # Drawn column by column, in this order; the other columns stay zero.
    params = np.zeros((k, NUM_PARAMS))
    params[:, PARAM_TEXTURE_OFFSET] = rng.uniform(0, 1000, k)
    params[:, PARAM_SPARE_OFFSET] = rng.uniform(0, 1000, k)
    params[:, PARAM_CRATE_RIB_PERIOD] = rng.uniform(0.25, 0.4, k)
    params[:, PARAM_CRATE_LABEL] = rng.integers(0, 2, k)
    # Parked cars stand either way round.
    flip = rng.random(k) < 0.3
    placed = boxes_at(
        world,
        pos,
        lateral,
        size,
        0.25,
        PARKED_CAR,
        paint,
        glass,
        params,
        cfg.road_half_width + 0.1,
    )
    placed.boxes.kind = np.where(crate, CRATE, PARKED_CAR)
    placed.boxes.yaw = placed.boxes.yaw + np.pi * flip
    return placed


def place_moving(world: Street, rng: np.random.Generator) -> MovingObjects:
    """Cars in the lanes beside the camera's and pedestrians on the sidewalks, each at its own
    constant speed along the road."""
    cfg = world.config
    s_lo, s_hi = float(world.path_s[0]) + 20.0, float(world.path_s[-1]) - 20.0
    span = s_hi - s_lo
    n_car = rng.poisson(cfg.cars_per_100m * span / 100.0) if cfg.lanes_per_side else 0
    n_ped = rng.poisson(cfg.pedestrians_per_100m * span / 100.0)
    # Cars: lanes 1 … lanes_per_side on either side; oncoming on the left.
    lane = rng.integers(1, max(cfg.lanes_per_side, 1) + 1, n_car)
    left = rng.random(n_car) < 0.5
    car_lateral = np.where(left, -1.0, 1.0) * lane * cfg.lane_width + rng.normal(0, 0.15, n_car)
    car_dir = np.where(left, -1.0, 1.0)
    car_speed = rng.uniform(*cfg.car_speed, n_car)
    car_size = np.asarray(_CAR_SIZE) * rng.uniform(0.92, 1.08, (n_car, 1))
    car_paint = _CAR_PAINT[rng.integers(0, len(_CAR_PAINT), n_car)]
    car_glass = np.stack([rng.uniform(25, 45, n_car)] * 3, -1)
    # Pedestrians: on either sidewalk, walking either way.
    ped_side = np.where(rng.random(n_ped) < 0.5, -1.0, 1.0)
    ped_lateral = ped_side * (
        cfg.kerb + rng.uniform(0.5, max(cfg.sidewalk_width - 0.5, 0.6), n_ped)
    )
    ped_dir = np.where(rng.random(n_ped) < 0.5, -1.0, 1.0)
    ped_speed = rng.uniform(*cfg.pedestrian_speed, n_ped)
    ped_size = np.asarray(_PEDESTRIAN_SIZE) * rng.uniform(0.9, 1.1, (n_ped, 1))
    ped_top = _CLOTHES[rng.integers(0, len(_CLOTHES), n_ped)]
    ped_legs = _CLOTHES[rng.integers(0, len(_CLOTHES), n_ped)] * 0.7
    skin = _SKIN[rng.integers(0, len(_SKIN), n_ped)]
    n = n_car + n_ped
    params = np.zeros((n, NUM_PARAMS))
    params[:, [PARAM_TEXTURE_OFFSET, PARAM_SPARE_OFFSET]] = rng.uniform(0, 1000, (n, 2))
    params[n_car:, PARAM_PEDESTRIAN_SKIN] = skin
    size = np.concatenate([car_size, ped_size]).reshape(n, 3)
    bury = np.concatenate([np.full(n_car, 0.25), np.full(n_ped, 0.05)])
    boxes = Boxes(
        centre=np.zeros((n, 3)),
        yaw=np.zeros(n),
        half=size / 2,
        base=size[:, 1] / 2 - bury,
        kind=np.concatenate([np.full(n_car, CAR), np.full(n_ped, PEDESTRIAN)]).astype(np.int64),
        colour=np.concatenate([car_paint, ped_top]).reshape(n, 3),
        colour2=np.concatenate([car_glass, ped_legs]).reshape(n, 3),
        params=params,
    )
    return MovingObjects(
        boxes=boxes,
        s0=rng.uniform(s_lo, s_hi, n),
        direction=np.concatenate([car_dir, ped_dir]),
        speed=np.concatenate([car_speed, ped_speed]),
        lateral=np.concatenate([car_lateral, ped_lateral]),
    )


def empty_boxes() -> Boxes:
    """No boxes."""
    return Boxes(
        centre=np.zeros((0, 3)),
        yaw=np.zeros(0),
        half=np.zeros((0, 3)),
        base=np.zeros(0),
        kind=np.zeros(0, dtype=np.int64),
        colour=np.zeros((0, 3)),
        colour2=np.zeros((0, 3)),
        params=np.zeros((0, NUM_PARAMS)),
    )
