"""Objects that cross the road, added to a persistent world (the study's object test set).

The movers of a :class:`~mfg_lightning.scene.worlds.World` drive or walk along the road, so a far
one barely moves in the image: small objects are never fast there. :func:`with_crossings` adds
cars and pedestrians that cross the road instead, back and forth between the building lines at
a fixed arc length, each at its own speed and scaled by its own factor; the result is a
:class:`CrossingWorld`, which the renderer reads like any world (its object poses and arc
lengths). Crossing object ``j`` faces the path's right and stands
``lateral[j] + direction[j] · speed[j] · frame`` metres to the right of the path, that offset
reflected back and forth between ``±bounce`` (a triangle wave: continuous, so its motion between
two frames, and the exact flow, are exact).

The settings are ``dataset.world`` keys beside the world's own (:data:`KEYS`), so
``+dataset.world.crossing_per_100m=10`` adds them. This module is separate from
:mod:`~mfg_lightning.scene.worlds` so that a world without crossings, and the cache of its
renders, does not depend on it: a dataset keys its cache on this module's source only when it
has crossings (:mod:`mfg_lightning.data.rendered`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mfg_lightning.scene.furnishing import Boxes, MovingObjects, place_moving, yaw_pose
from mfg_lightning.scene.seeding import seeded_rng
from mfg_lightning.scene.world_config import Range, WorldConfig
from mfg_lightning.scene.worlds import World

__all__ = ["KEYS", "CrossingConfig", "CrossingWorld", "split_world_fields", "with_crossings"]

#: The ``dataset.world`` keys of the crossings, by :class:`CrossingConfig` field.
KEYS = {"crossing_per_100m": "per_100m", "crossing_speed": "speed", "crossing_scale": "scale"}


@dataclass(frozen=True)
class CrossingConfig:
    """Objects crossing the road.

    Attributes:
        per_100m: crossing objects per 100 m of path, half cars and half pedestrians (all
            pedestrians on a road without lanes beside the camera's).
        speed: range of a crossing object's speed (metres per frame).
        scale: range of the factor on its size (a car or a pedestrian at 1).
    """

    per_100m: float = 0.0
    speed: Range = (0.05, 1.5)
    scale: Range = (0.2, 1.2)

    def __post_init__(self) -> None:
        if not self.per_100m >= 0:
            raise ValueError(f"crossing_per_100m must be >= 0, got {self.per_100m}")
        for key, name in (("crossing_speed", "speed"), ("crossing_scale", "scale")):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{key} must be a range 0 < lo <= hi, got {(lo, hi)}")


def split_world_fields(fields: dict[str, Any]) -> tuple[dict[str, Any], CrossingConfig | None]:
    """``dataset.world`` → the world's own fields and the crossings (None: no crossing object)."""
    own = {k: v for k, v in fields.items() if k not in KEYS}
    given = {KEYS[k]: tuple(v) if isinstance(v, list) else v for k, v in fields.items()
             if k in KEYS}  # fmt: skip
    cfg = CrossingConfig(**given)
    return own, (cfg if cfg.per_100m > 0 else None)


@dataclass
class CrossingWorld(World):
    """A :class:`World` whose moving objects from index ``first`` on cross the road (see the
    module docstring), turning back at ``bounce`` metres from the path."""

    first: int = 0
    bounce: float = 0.0

    @property
    def crosses(self) -> np.ndarray:
        """``(M,)`` bool: which moving objects cross the road."""
        return np.arange(len(self.moving)) >= self.first

    def object_lateral(self, frame: int | float) -> np.ndarray:
        """Offset ``(M - first,)`` of every crossing object to the right of the path (metres)."""
        m, b = self.moving, self.bounce
        c = slice(self.first, None)
        u = np.mod(m.lateral[c] + m.direction[c] * m.speed[c] * float(frame) + b, 4 * b)
        return np.where(u < 2 * b, u, 4 * b - u) - b

    def object_arc(self, frame: int | float) -> np.ndarray:
        arc = super().object_arc(frame)
        arc[self.first :] = self.moving.s0[self.first :]
        return arc

    def object_poses(self, frame: int | float) -> torch.Tensor:
        poses = super().object_poses(frame)
        if self.first == len(self.moving):
            return poses
        xyz, heading = self.path_at(self.moving.s0[self.first :])
        right = np.stack([heading[:, 1], -heading[:, 0]], -1)  # (dz, -dx), as World's
        lateral = self.object_lateral(frame)
        x, z = xyz[:, 0] + lateral * right[:, 0], xyz[:, 2] + lateral * right[:, 1]
        y = self.ground(frame).height(torch.from_numpy(x), torch.from_numpy(z))[0].numpy()
        base = self.moving.boxes.base[self.first :]
        yaw = np.arctan2(right[:, 0], right[:, 1])  # facing across the road
        poses[self.first :] = yaw_pose(np.stack([x, y - base, z], -1), yaw)
        return poses


def with_crossings(world: World, cfg: CrossingConfig) -> CrossingWorld:
    """``world`` with ``cfg``'s crossing objects after its own movers (which keep their instance
    ids): cars and pedestrians drawn as the world draws its movers, from a random stream of
    their own (the world's seed and name, ``"crossing"``), each scaled by a factor of
    ``cfg.scale``, at a speed of ``cfg.speed``, from anywhere between the building lines in
    either direction."""
    rng = seeded_rng(world.seed, "world", world.name, "crossing")
    wc: WorldConfig = world.config
    rate = cfg.per_100m / (2 if wc.lanes_per_side else 1)
    # the world's own drawing of cars and pedestrians, at the crossings' density
    drawn = place_moving(
        dataclasses.replace(
            world, config=dataclasses.replace(wc, cars_per_100m=rate, pedestrians_per_100m=rate)
        ),
        rng,
    )
    n = len(drawn)
    scale = rng.uniform(*cfg.scale, n)
    drawn.boxes.half = drawn.boxes.half * scale[:, None]
    drawn.boxes.base = drawn.boxes.base * scale
    m = world.moving
    fields = {f.name: getattr(world, f.name) for f in dataclasses.fields(World)}
    fields["moving"] = MovingObjects(
        Boxes.concat([m.boxes, drawn.boxes]),
        np.concatenate([m.s0, drawn.s0]),
        np.concatenate([m.direction, drawn.direction]),
        np.concatenate([m.speed, rng.uniform(*cfg.speed, n)]),
        np.concatenate([m.lateral, rng.uniform(-wc.building_line, wc.building_line, n)]),
    )
    return CrossingWorld(**fields, first=len(m), bounce=wc.building_line)
