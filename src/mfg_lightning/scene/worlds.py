"""Persistent synthetic worlds: one street scene per trajectory, seen by every frame.

A :class:`World` is generated once from a trajectory's camera poses, a seed and the trajectory's
name, and is a pure function of them (the same inputs give the same world in any process). It
holds:

* **The road.** Its centreline is the camera path itself (the camera drives in the middle of its
  lane), smoothed and resampled by arc length, and extended 250 m straight beyond both ends so
  that the first and last frames look down a road too. The ground is a height field over the
  horizontal (x, z) plane, sampled on a regular grid: each cell takes the ground height of the
  nearest path point (the camera position moved 1.65 m down its own y axis, smoothed along the
  path so that suspension bumps do not deform the road), smoothed again across the grid. The
  ground is therefore static and the same for every frame, level across the road, and follows
  the hills and pitch of real KITTI trajectories. The grid also stores, for every cell, the arc
  length ``s`` and the signed lateral offset ``d`` (metres, positive to the right of the
  direction of travel) of the nearest path point: the road coordinates that lane markings,
  kerbs and sidewalks are drawn in (centreline and ground: :mod:`.road`).
* **Static boxes**: facades (with windows, drawn by :mod:`mfg_lightning.scene.shading`) set back
  beyond the sidewalks, parked cars and textured boxes (containers, vans) in the parking lanes.
  Every box is yaw-aligned with the road where it stands, rests on the ground (its bottom is
  buried a little so that slopes leave no gap) and is kept clear of *every* pass of the path,
  so loops and revisited streets never put a building on the road.
* **Moving objects**: cars in the lanes beside the camera's (oncoming on the left, same
  direction on the right) and pedestrians on the sidewalks, each driving or walking along the
  road at its own constant speed. Their poses (:meth:`World.object_poses`) are continuous in
  the frame index; they wrap around only in the extensions beyond the trajectory's ends, out of
  sight of every frame.
* **Per-frame exposure**: a smooth AR(1) gain (mild, a few per cent) applied by the renderer.

Coordinates are the trajectory's world frame: for KITTI (and :func:`procedural_trajectory`)
that is the first camera's frame, x right, y down, z forward, so "up" is ``-y``. Boxes and
objects are described by poses ``T_world_obj`` whose axes follow the same convention: x to the
object's right, y down, z along its heading, origin at the box centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

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
from mfg_lightning.scene.road import Ground, ground_grid, road_centreline
from mfg_lightning.scene.seeding import seeded_rng
from mfg_lightning.scene.world_config import WorldConfig

__all__ = [
    "CAR",
    "CRATE",
    "FACADE",
    "KIND_NAMES",
    "PARKED_CAR",
    "PEDESTRIAN",
    "SECTION",
    "SECTION_MARGIN",
    "Boxes",
    "Ground",
    "MovingObjects",
    "World",
    "WorldConfig",
    "yaw_pose",
]

#: Box kinds. Facades, parked cars and crates are static; cars and pedestrians move.
FACADE, PARKED_CAR, CRATE, CAR, PEDESTRIAN = 0, 1, 2, 3, 4
KIND_NAMES = ("facade", "parked car", "crate", "car", "pedestrian")

#: Arc length of a section of the path (metres): frames in one section see one ground.
SECTION = 100.0
#: Centreline beyond a section's ends that its ground is built from (metres; at least the
#: renderer's culling distance, so that a switch of sections changes nothing in view).
SECTION_MARGIN = 200.0

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


@dataclass
class Boxes:
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

    def __len__(self) -> int:
        return len(self.kind)

    @staticmethod
    def concat(parts: list[Boxes]) -> Boxes:
        return Boxes(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("centre", "yaw", "half", "base", "kind", "colour", "colour2", "params")
            )
        )

    def select(self, keep: np.ndarray) -> Boxes:
        return Boxes(
            *(
                getattr(self, f)[keep]
                for f in ("centre", "yaw", "half", "base", "kind", "colour", "colour2", "params")
            )
        )


@dataclass
class MovingObjects:
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

    def __len__(self) -> int:
        return len(self.s0)


@dataclass
class _Placed:
    """Candidate static boxes, placed at road coordinates before any section picks its own
    (``n`` boxes)."""

    boxes: Boxes
    s: np.ndarray  # (n,) arc length each box was placed at (metres)
    clearance: np.ndarray  # (n,) distance it must keep from every pass of the path (metres)
    footprint_x: np.ndarray  # (n, 9) world x of its footprint points (metres)
    footprint_z: np.ndarray  # (n, 9) world z of its footprint points (metres)

    @staticmethod
    def concat(parts: list[_Placed]) -> _Placed:
        """The parts' boxes one after the other, in order."""
        return _Placed(
            Boxes.concat([p.boxes for p in parts]),
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("s", "clearance", "footprint_x", "footprint_z")
            ),
        )


@dataclass
class World:
    """A persistent street scene along one trajectory (see the module docstring).

    Build with :meth:`generate`. Attributes are read by the renderer; all lengths in metres.

    The ground is built in overlapping **sections** of the path: frame ``k`` sees the ground of
    section ``⌊s_k / SECTION⌋`` (``s_k`` its arc length), built from the centreline within
    ``SECTION_MARGIN`` of that section. A street the trajectory drives again much later (KITTI
    loops) thus keeps the height and lanes of the pass being driven, even where the ground-truth
    poses of the two passes disagree by metres in height (KITTI 08: up to 6 m). Sections share
    one lattice of cells, so near the camera the ground of two sections at a switch agrees (to a
    few centimetres in height, exactly in road coordinates) unless a revisited street enters
    one of them; boxes that differ are at least ``SECTION_MARGIN`` of path away.

    Attributes:
        poses: ``(N, 4, 4)`` float64 camera poses ``T_world_cam``.
        seed, name, config: what the world was generated from.
        path_s: ``(P,)`` arc length of the resampled road centreline (0 at the first camera,
            negative on the extension behind it).
        path_xyz: ``(P, 3)`` ground points of the centreline (world coordinates).
        path_dir: ``(P, 2)`` unit horizontal heading ``(dx, dz)`` of the centreline.
        frame_s: ``(N,)`` arc length of every frame.
        static: facades, parked cars and crates (:class:`Boxes`; ``centre`` y is filled in per
            section, see :meth:`static_boxes`).
        static_s: ``(M,)`` arc length each static box was placed at.
        static_clearance: ``(M,)`` the distance it keeps from every pass of the path.
        moving: cars and pedestrians (:class:`MovingObjects`).
        exposure: ``(N,)`` float64 exposure gain of every frame (around 1).
        sun: ``(3,)`` float64 unit vector towards the sun (world coordinates; up is ``-y``).
    """

    poses: torch.Tensor
    seed: int
    name: str
    config: WorldConfig
    path_s: np.ndarray
    path_xyz: np.ndarray
    path_dir: np.ndarray
    frame_s: np.ndarray
    static: Boxes
    static_s: np.ndarray
    static_clearance: np.ndarray
    moving: MovingObjects
    exposure: np.ndarray
    sun: np.ndarray
    _sections: dict = field(default_factory=dict, repr=False)
    # The 9 footprint points (x and z, ``(M, 9)``) of every static box, which each section
    # tests against its own ground (:meth:`_static_in`).
    _footprint_x: np.ndarray = field(default_factory=lambda: np.zeros((0, 9)), repr=False)
    _footprint_z: np.ndarray = field(default_factory=lambda: np.zeros((0, 9)), repr=False)

    # ----------------------------------------------------------------------------------------
    # Generation
    # ----------------------------------------------------------------------------------------

    @classmethod
    def generate(
        cls,
        poses: torch.Tensor,
        seed: int,
        name: str,
        config: WorldConfig | None = None,
    ) -> World:
        """The world of one trajectory, a pure function of ``(poses, seed, name, config)``.

        Args:
            poses: ``(N, 4, 4)`` camera-to-world poses ``T_world_cam`` (KITTI convention:
                camera x right, y down, z forward), e.g. KITTI ground truth or
                :func:`mfg_lightning.scene.camera.procedural_trajectory`.
            seed: seed of the world's content.
            name: the trajectory's name (e.g. ``"00"`` or ``"train03"``): worlds of different
                trajectories differ even with one seed.
            config: layout and densities (default :class:`WorldConfig`).

        Raises:
            ValueError: poses not ``(N, 4, 4)`` with N ≥ 1, or not finite.
        """
        cfg = config or WorldConfig()
        poses = torch.as_tensor(poses)
        if poses.dim() != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] < 1:
            raise ValueError(
                f"World.generate: poses must be (N, 4, 4) with N >= 1, got {tuple(poses.shape)}"
            )
        poses = poses.to(torch.float64).contiguous()
        if not bool(torch.isfinite(poses).all()):
            raise ValueError(f"World.generate: trajectory {name!r} has non-finite poses")
        path_s, path_xyz, path_dir, frame_s = road_centreline(poses.numpy())
        world = cls(
            poses=poses,
            seed=int(seed),
            name=str(name),
            config=cfg,
            path_s=path_s,
            path_xyz=path_xyz,
            path_dir=path_dir,
            frame_s=frame_s,
            static=_empty_boxes(),
            static_s=np.zeros(0),
            static_clearance=np.zeros(0),
            moving=MovingObjects(_empty_boxes(), *(np.zeros(0) for _ in range(4))),
            exposure=_exposure(seeded_rng(seed, "world", name, "exposure"), poses.shape[0], cfg),
            sun=_sun(seeded_rng(seed, "world", name, "sun")),
        )
        placed = world._place_static(seeded_rng(seed, "world", name, "static"))
        world.static, world.static_s, world.static_clearance = (
            placed.boxes,
            placed.s,
            placed.clearance,
        )
        world._footprint_x, world._footprint_z = placed.footprint_x, placed.footprint_z
        world.moving = world._place_moving(seeded_rng(seed, "world", name, "moving"))
        return world

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    # ----------------------------------------------------------------------------------------
    # Sections and queries
    # ----------------------------------------------------------------------------------------

    @property
    def num_sections(self) -> int:
        return max(1, math.ceil(float(self.frame_s.max()) / SECTION))

    def section_of(self, frame: int | float) -> int:
        """The section whose ground frame ``frame`` sees."""
        k = int(np.clip(round(float(frame)), 0, self.num_frames - 1))
        return int(np.clip(self.frame_s[k] // SECTION, 0, self.num_sections - 1))

    def ground(self, frame: int | float) -> Ground:
        """The ground frame ``frame`` sees (built on first use, then kept)."""
        j = self.section_of(frame)
        if j not in self._sections:
            lo = j * SECTION - SECTION_MARGIN
            hi = (j + 1) * SECTION + SECTION_MARGIN
            if j == 0:
                lo = -np.inf
            if j == self.num_sections - 1:
                hi = np.inf
            sel = (self.path_s >= lo) & (self.path_s <= hi)
            origin, cell, grid = ground_grid(
                self.path_s[sel],
                self.path_xyz[sel],
                self.path_dir[sel],
                self.config,
                extension=(self.path_s[sel] < 0) | (self.path_s[sel] > self.frame_s.max()),
            )
            ground = Ground(
                float(self.path_s[sel][0]), float(self.path_s[sel][-1]), origin, cell, grid
            )
            ground.static_index, ground.static_centre = self._static_in(ground)
            self._sections[j] = ground
        return self._sections[j]

    def ground_height(self, x: torch.Tensor, z: torch.Tensor, frame: int = 0):
        """:meth:`Ground.height` of the ground frame ``frame`` sees."""
        return self.ground(frame).height(x, z)

    def road_coordinates(self, x: torch.Tensor, z: torch.Tensor, frame: int = 0):
        """:meth:`Ground.road_coordinates` of the ground frame ``frame`` sees."""
        return self.ground(frame).road_coordinates(x, z)

    def path_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centreline ground point ``(n, 3)`` and heading ``(n, 2)`` (unit dx, dz) at arc lengths
        ``s`` ``(n,)`` (clamped to the extended path)."""
        xyz = np.stack([np.interp(s, self.path_s, self.path_xyz[:, i]) for i in range(3)], -1)
        h = np.stack([np.interp(s, self.path_s, self.path_dir[:, i]) for i in range(2)], -1)
        h /= np.linalg.norm(h, axis=-1, keepdims=True).clip(1e-9)
        return xyz, h

    def static_boxes(self, frame: int | float) -> tuple[np.ndarray, np.ndarray]:
        """The static boxes frame ``frame`` sees: indices into :attr:`static` ``(m,)`` and
        their centres ``(m, 3)`` standing on that frame's ground."""
        ground = self.ground(frame)
        return ground.static_index, ground.static_centre

    def object_arc(self, frame: int | float) -> np.ndarray:
        """Arc length ``(M,)`` of every moving object at a frame."""
        m = self.moving
        lo, hi = self.path_s[0] + 20.0, self.path_s[-1] - 20.0
        return lo + np.mod(m.s0 + m.direction * m.speed * float(frame) - lo, hi - lo)

    def object_poses(self, frame: int | float) -> torch.Tensor:
        """Poses of every moving object at a frame (continuous in ``frame``).

        Args:
            frame: frame index (fractional frames interpolate the motion; the ground the
                objects stand on is that of the nearest frame).

        Returns:
            ``(M, 4, 4)`` float64 ``T_world_obj`` (box centre; x right, y down, z heading),
            one per object of :attr:`moving`, in the same order (the order of instance ids).
        """
        m = self.moving
        if not len(m):
            return torch.zeros(0, 4, 4, dtype=torch.float64)
        xyz, heading = self.path_at(self.object_arc(frame))
        right = np.stack([heading[:, 1], -heading[:, 0]], -1)  # (dz, -dx): x = y × z, y down
        x = xyz[:, 0] + m.lateral * right[:, 0]
        z = xyz[:, 2] + m.lateral * right[:, 1]
        y = self.ground(frame).height(torch.from_numpy(x), torch.from_numpy(z))[0].numpy()
        yaw = np.arctan2(heading[:, 0] * m.direction, heading[:, 1] * m.direction)
        return yaw_pose(np.stack([x, y - m.boxes.base, z], -1), yaw)

    # ----------------------------------------------------------------------------------------
    # Placement
    # ----------------------------------------------------------------------------------------

    def _static_in(self, ground: Ground) -> tuple[np.ndarray, np.ndarray]:
        """Static boxes of a section: placed within its arc range, clear of every pass of the
        path in it and standing where their own pass is the nearest one (so revisited streets
        are furnished once), with centres on its ground."""
        st = self.static
        inside = np.nonzero((self.static_s >= ground.lo + 5) & (self.static_s <= ground.hi - 5))[0]
        px, pz = self._footprint_x[inside], self._footprint_z[inside]
        s, _, dist = ground.road_coordinates(
            torch.from_numpy(px.ravel()), torch.from_numpy(pz.ravel())
        )
        dist = dist.numpy().reshape(px.shape)
        s = s.numpy().reshape(px.shape)
        clear = (dist >= self.static_clearance[inside, None]).all(1)
        owned = np.abs(s[:, 0] - self.static_s[inside]) < 15.0
        keep = inside[clear & owned]
        centre = st.centre[keep].copy()
        centre[:, 1] = (
            ground.height(torch.from_numpy(centre[:, 0]), torch.from_numpy(centre[:, 2]))[0].numpy()
            - st.base[keep]
        )
        return keep, centre

    def _footprints(self, s: np.ndarray, lateral: np.ndarray, half: np.ndarray):
        """Centres, yaws and 9 footprint points ``(n, 9)`` of boxes at road coordinates; point 0
        is the centre of the face towards the road."""
        xyz, heading = self.path_at(s)
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

    def _boxes_at(
        self,
        s: np.ndarray,
        lateral: np.ndarray,
        size: np.ndarray,
        bury: float,
        kind: int,
        colour: np.ndarray,
        colour2: np.ndarray,
        params: np.ndarray,
        clearance: float,
    ) -> _Placed:
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
        cx, cz, yaw, px, pz = self._footprints(s, lateral, half)
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
        return _Placed(boxes, s, np.full(len(s), clearance), px, pz)

    def _place_static(self, rng: np.random.Generator) -> _Placed:
        """Every candidate static box: on each side of the path its facades, then its parked
        boxes (the order of the random draws, which the worlds depend on)."""
        parts: list[_Placed] = []
        for side in (-1.0, 1.0):
            for placed in (self._place_facades(rng, side), self._place_parked(rng, side)):
                if placed is not None:
                    parts.append(placed)
        if not parts:
            return _Placed(_empty_boxes(), np.zeros(0), np.zeros(0), *(np.zeros((0, 9)),) * 2)
        return _Placed.concat(parts)

    def _place_facades(self, rng: np.random.Generator, side: float) -> _Placed | None:
        """Facades on one side (``side`` -1 left, +1 right): a sequence of blocks and gaps
        along the path, set back behind the building line (None: no block)."""
        cfg = self.config
        s_lo, s_hi = float(self.path_s[0]), float(self.path_s[-1])
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
        return self._boxes_at(
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

    def _place_parked(self, rng: np.random.Generator, side: float) -> _Placed | None:
        """Parked cars and crates in the parking strip on one side (``side`` -1 left, +1
        right), at least 5.5 m between centres (None: no parking, ``parked_per_100m`` 0)."""
        cfg = self.config
        s_lo, s_hi = float(self.path_s[0]), float(self.path_s[-1])
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
        placed = self._boxes_at(
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

    def _place_moving(self, rng: np.random.Generator) -> MovingObjects:
        cfg = self.config
        s_lo, s_hi = float(self.path_s[0]) + 20.0, float(self.path_s[-1]) - 20.0
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


# --------------------------------------------------------------------------------------------
# Helpers of generation
# --------------------------------------------------------------------------------------------


def _empty_boxes() -> Boxes:
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


def _exposure(rng: np.random.Generator, n: int, cfg: WorldConfig) -> np.ndarray:
    """Exposure gains of ``n`` frames: ``exp`` of a stationary AR(1) process."""
    a = cfg.exposure_corr
    innov = rng.normal(0.0, cfg.exposure_std * math.sqrt(1 - a * a), n)
    log_gain = np.empty(n)
    log_gain[0] = rng.normal(0.0, cfg.exposure_std)
    for k in range(1, n):
        log_gain[k] = a * log_gain[k - 1] + innov[k]
    return np.exp(log_gain)


def _sun(rng: np.random.Generator) -> np.ndarray:
    """Unit vector towards the sun: random azimuth, 30-60 degrees above the horizon."""
    az = rng.uniform(0, 2 * np.pi)
    el = np.radians(rng.uniform(30, 60))
    return np.array([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)])
