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
  kerbs and sidewalks are drawn in.
* **Static boxes**: facades (with windows, drawn by :mod:`mfg_lightning.scene.render`) set back
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
from scipy.ndimage import gaussian_filter, gaussian_filter1d
from scipy.spatial import cKDTree

from mfg_lightning.scene.camera import CAMERA_HEIGHT
from mfg_lightning.scene.seeding import seeded_rng

__all__ = [
    "CAR",
    "CRATE",
    "FACADE",
    "KIND_NAMES",
    "PARKED_CAR",
    "PEDESTRIAN",
    "World",
    "WorldConfig",
    "yaw_pose",
]

#: Box kinds. Facades, parked cars and crates are static; cars and pedestrians move.
FACADE, PARKED_CAR, CRATE, CAR, PEDESTRIAN = 0, 1, 2, 3, 4
KIND_NAMES = ("facade", "parked car", "crate", "car", "pedestrian")

#: Straight road added beyond both ends of the trajectory (metres).
EXTENSION = 250.0
#: Arc-length spacing of the resampled path (metres).
PATH_STEP = 0.5
#: Largest number of grid cells of a section's ground: longer sections get coarser cells.
MAX_GRID_CELLS = 600_000
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
    [
        [196, 178, 150],
        [170, 160, 150],
        [205, 195, 175],
        [150, 85, 60],
        [120, 120, 125],
        [215, 205, 190],
        [180, 140, 100],
        [160, 170, 160],
    ],
    dtype=np.float64,
)
_CAR_PAINT = np.array(
    [
        [200, 200, 205],
        [30, 30, 35],
        [120, 125, 130],
        [150, 30, 30],
        [25, 50, 110],
        [230, 230, 230],
        [70, 90, 60],
        [180, 150, 60],
    ],
    dtype=np.float64,
)
_CRATE_PAINT = np.array(
    [[170, 60, 40], [40, 90, 150], [60, 120, 70], [210, 140, 40], [200, 200, 190]],
    dtype=np.float64,
)
_CLOTHES = np.array(
    [[40, 40, 50], [60, 70, 110], [150, 40, 40], [200, 190, 170], [90, 90, 90], [40, 100, 60]],
    dtype=np.float64,
)
_SKIN = np.array([[225, 190, 160], [190, 140, 110], [120, 85, 60]], dtype=np.float64)


@dataclass(frozen=True)
class WorldConfig:
    """Layout and densities of a persistent world.

    Lengths in metres; densities per 100 m of path (per side where stated); speeds in metres per
    frame (KITTI's 10 Hz: 1 m/frame = 36 km/h).

    Attributes:
        lane_width: width of one lane. The camera drives in the middle of its lane.
        lanes_per_side: lanes beside the camera's on each side (oncoming on the left, same
            direction on the right). The road spans ``±lane_width · (lanes_per_side + 0.5)``.
        parking_width: parking strip between the outer lane and the kerb on each side.
        sidewalk_width: sidewalk between the kerb and the building line.
        facade_coverage: fraction of the path's length lined with facades on each side.
        facade_setback: range of the distance of a facade behind the sidewalk.
        facade_length, facade_depth, facade_height: ranges of a facade box's size.
        parked_per_100m: parked boxes per 100 m per side (at most one per 5.5 m).
        crate_fraction: fraction of parked boxes that are textured boxes (containers, vans)
            rather than cars.
        cars_per_100m: moving cars per 100 m of path (all lanes beside the camera's).
        car_speed: range of a moving car's speed.
        pedestrians_per_100m: pedestrians per 100 m of path (both sidewalks).
        pedestrian_speed: range of a pedestrian's walking speed.
        exposure_std: stationary standard deviation of the log exposure gain.
        exposure_corr: frame-to-frame correlation of the log exposure gain (AR(1)).
        sensor_noise: standard deviation of the per-pixel sensor noise, grey levels.
        grid_cell: ground-grid cell size (grown automatically beyond ``MAX_GRID_CELLS``).
        margin: ground grid beyond the path's bounding box.
    """

    lane_width: float = 3.3
    lanes_per_side: int = 1
    parking_width: float = 2.2
    sidewalk_width: float = 3.0
    facade_coverage: float = 0.8
    facade_setback: tuple[float, float] = (0.3, 6.0)
    facade_length: tuple[float, float] = (8.0, 30.0)
    facade_depth: tuple[float, float] = (8.0, 16.0)
    facade_height: tuple[float, float] = (6.0, 20.0)
    parked_per_100m: float = 6.0
    crate_fraction: float = 0.2
    cars_per_100m: float = 2.5
    car_speed: tuple[float, float] = (0.4, 1.3)
    pedestrians_per_100m: float = 3.0
    pedestrian_speed: tuple[float, float] = (0.08, 0.16)
    exposure_std: float = 0.04
    exposure_corr: float = 0.9
    sensor_noise: float = 1.0
    grid_cell: float = 1.0
    margin: float = 80.0

    def __post_init__(self) -> None:
        for name in ("lane_width", "parking_width", "sidewalk_width", "grid_cell", "margin"):
            if not getattr(self, name) > 0:
                raise ValueError(f"WorldConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in (
            "facade_setback",
            "facade_length",
            "facade_depth",
            "facade_height",
            "car_speed",
            "pedestrian_speed",
        ):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"WorldConfig.{name} must be a range 0 <= lo <= hi, got {lo, hi}")
        for name in ("parked_per_100m", "cars_per_100m", "pedestrians_per_100m", "sensor_noise"):
            if getattr(self, name) < 0:
                raise ValueError(f"WorldConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.facade_coverage <= 1 or not 0 <= self.crate_fraction <= 1:
            raise ValueError("WorldConfig.facade_coverage and crate_fraction must be in [0, 1]")
        if self.lanes_per_side < 0:
            raise ValueError(f"WorldConfig.lanes_per_side must be >= 0, got {self.lanes_per_side}")
        if not 0 <= self.exposure_corr < 1 or self.exposure_std < 0:
            raise ValueError("WorldConfig.exposure_corr must be in [0, 1), exposure_std >= 0")

    @property
    def road_half_width(self) -> float:
        """Distance from the path to the outer edge of the outer lane (metres)."""
        return self.lane_width * (self.lanes_per_side + 0.5)

    @property
    def kerb(self) -> float:
        """Distance from the path to the kerb (outer edge of the parking strip, metres)."""
        return self.road_half_width + self.parking_width

    @property
    def building_line(self) -> float:
        """Distance from the path to the back of the sidewalk (metres)."""
        return self.kerb + self.sidewalk_width


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
        params: ``(M, 8)`` float64 kind-specific texture parameters (see the renderer).
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


class Ground:
    """The ground of one section of a world: a height field and road coordinates on a grid.

    Attributes:
        lo, hi: the range of centreline arc lengths this ground is built from (metres).
        origin: ``(x0, z0)`` world coordinates of grid cell ``(0, 0)``'s centre.
        cell: cell size (metres).
        grid: ``(nz, nx, 4)`` float32 per cell: ground y, and the arc length ``s``, lateral
            offset ``d`` and ``|d|`` of the nearest centreline point.
        max_slope: the steepest ground slope (rise over run).
        static_index, static_centre: the static boxes standing in this section (indices into
            ``World.static``, ``(m,)``) and their centres on this ground (``(m, 3)``), set by
            :meth:`World.ground`.
    """

    def __init__(
        self, lo: float, hi: float, origin: tuple[float, float], cell: float, grid: np.ndarray
    ) -> None:
        self.lo, self.hi, self.origin, self.cell = lo, hi, origin, cell
        self.grid = torch.from_numpy(grid)
        self._height = self.grid[..., 0].contiguous().view(-1)
        self._road = self.grid[..., 1:].contiguous().view(-1, 3)
        gz, gx = np.gradient(grid[..., 0], cell)
        self.max_slope = float(np.sqrt(gx * gx + gz * gz).max())

    def _cells(self, x: torch.Tensor, z: torch.Tensor):
        """Corner index and bilinear fractions of world points (clamped at the border)."""
        nz, nx = self.grid.shape[:2]
        gx = ((x - self.origin[0]) / self.cell).clamp(0, nx - 1.001)
        gz = ((z - self.origin[1]) / self.cell).clamp(0, nz - 1.001)
        ix, iz = gx.floor(), gz.floor()
        return iz.long() * nx + ix.long(), nx, gx - ix, gz - iz

    def height(
        self, x: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Ground y (down) at world points and its slopes.

        Args:
            x, z: world coordinates (metres), equal shapes, float32 or float64.

        Returns:
            ``(y, dy/dx, dy/dz)`` of the bilinear height field, shaped and typed like ``x``.
        """
        i00, nx, fx, fz = self._cells(x.reshape(-1), z.reshape(-1))
        h = self._height
        h00, h01, h10, h11 = (
            h.index_select(0, i).to(x.dtype) for i in (i00, i00 + 1, i00 + nx, i00 + nx + 1)
        )
        a = h00 + (h01 - h00) * fx
        b = h10 + (h11 - h10) * fx
        dx = ((h01 - h00) + (h11 - h10 - h01 + h00) * fz) / self.cell
        shape = x.shape
        return (a + (b - a) * fz).view(shape), dx.view(shape), ((b - a) / self.cell).view(shape)

    def road_coordinates(
        self, x: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Road coordinates of world points.

        Args:
            x, z: world coordinates (metres), ``(n,)`` each.

        Returns:
            ``(s, d, dist)``: arc length and signed lateral offset (metres, positive to the
            right of the direction of travel) of the nearest centreline point, and the distance
            to the centreline. Between two passes of the path, where the nearest point jumps
            from one to the other, ``d`` is meaningless: there it is 10 km (off any road).
        """
        i00, nx, fx, fz = self._cells(x, z)
        g = self._road
        c00, c01, c10, c11 = (
            g.index_select(0, i).to(x.dtype) for i in (i00, i00 + 1, i00 + nx, i00 + nx + 1)
        )
        fx, fz = fx[:, None], fz[:, None]
        a = c00 + (c01 - c00) * fx
        b = c10 + (c11 - c10) * fx
        v = a + (b - a) * fz
        s, d, dist = v[:, 0], v[:, 1], v[:, 2]
        # Bilinear |d| exceeds |bilinear d| only where d changes sign in the cell: by less than a
        # cell at the centreline, by metres where the nearest pass jumps (d flips from +D to -D).
        torn = (dist - d.abs()) > 2.0 * self.cell
        return s, torch.where(torn, torch.full_like(d, 1e4), d), dist


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
                :func:`mfg_lightning.data.camera.procedural_trajectory`.
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
        path_s, path_xyz, path_dir, frame_s = _road_centreline(poses.numpy())
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
        world._place_static(seeded_rng(seed, "world", name, "static"))
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
            origin, cell, grid = _ground_grid(
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
    ) -> tuple[Boxes, np.ndarray, np.ndarray]:
        """Candidate boxes at road coordinates ``(s, lateral)`` (their centre y is set per
        section), with their footprints ``(n, 9)`` x and z."""
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
        self._candidates.append((boxes, s, np.full(len(s), clearance), px, pz))
        return boxes

    def _place_static(self, rng: np.random.Generator) -> None:
        cfg = self.config
        s_lo, s_hi = float(self.path_s[0]), float(self.path_s[-1])
        self._candidates: list = []
        for side in (-1.0, 1.0):
            # Facades: a sequence of blocks and gaps along the path.
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
            if k:
                depth_a = np.asarray(depth)
                lateral = side * (cfg.building_line + np.asarray(setback) + depth_a / 2)
                height = rng.uniform(*cfg.facade_height, k)
                size = np.stack([depth_a, height + 1.5, np.asarray(length)], -1)
                wall = _WALLS[rng.integers(0, len(_WALLS), k)] * rng.uniform(0.85, 1.1, (k, 1))
                glass = np.stack([rng.uniform(35, 70, k)] * 3, -1) + rng.uniform(-5, 10, (k, 3))
                params = np.stack(
                    [
                        rng.uniform(2.9, 3.6, k),  # floor height
                        rng.uniform(2.2, 3.6, k),  # window spacing
                        rng.uniform(0.45, 0.7, k),  # window width / spacing
                        rng.uniform(0.4, 0.6, k),  # window height / floor height
                        rng.integers(0, 3, k).astype(np.float64),  # wall style
                        rng.uniform(0, 1000, k),  # texture offset
                        rng.uniform(0, 1000, k),
                        rng.uniform(0.0, 1.0, k),  # shop front on the ground floor if < 0.4
                    ],
                    -1,
                )
                self._boxes_at(
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
            # Parked boxes in the parking strip: gaps of at least 5.5 m between centres.
            rate = cfg.parked_per_100m / 100.0
            if rate > 0:
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
                lateral = side * (cfg.road_half_width + cfg.parking_width / 2) + rng.normal(
                    0, 0.1, k
                )
                paint = np.where(
                    crate[:, None],
                    _CRATE_PAINT[rng.integers(0, len(_CRATE_PAINT), k)],
                    _CAR_PAINT[rng.integers(0, len(_CAR_PAINT), k)],
                ) * rng.uniform(0.9, 1.05, (k, 1))
                glass = np.stack([rng.uniform(25, 45, k)] * 3, -1)
                params = np.stack(
                    [
                        rng.uniform(0, 1000, k),
                        rng.uniform(0, 1000, k),
                        rng.uniform(0.25, 0.4, k),  # crate corrugation period
                        rng.integers(0, 2, k).astype(np.float64),  # crate label
                        *(np.zeros(k) for _ in range(4)),
                    ],
                    -1,
                )
                # Parked cars stand either way round.
                flip = rng.random(k) < 0.3
                boxes = self._boxes_at(
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
                boxes.kind = np.where(crate, CRATE, PARKED_CAR)
                boxes.yaw = boxes.yaw + np.pi * flip
        parts = self._candidates
        del self._candidates
        if not parts:
            self._footprint_x = self._footprint_z = np.zeros((0, 9))
            return
        self.static = Boxes.concat([p[0] for p in parts])
        self.static_s = np.concatenate([p[1] for p in parts])
        self.static_clearance = np.concatenate([p[2] for p in parts])
        self._footprint_x = np.concatenate([p[3] for p in parts])
        self._footprint_z = np.concatenate([p[4] for p in parts])

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
        params = np.zeros((n, 8))
        params[:, 0:2] = rng.uniform(0, 1000, (n, 2))
        params[n_car:, 2:5] = skin
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
        params=np.zeros((0, 8)),
    )


def _road_centreline(
    poses: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The road centreline under a trajectory, resampled every ``PATH_STEP`` metres.

    The ground point of every frame is the camera position moved ``CAMERA_HEIGHT`` down the
    camera's own y axis. Frames where the car stands still add nothing; heights are smoothed
    along the path over a couple of metres (suspension bumps and pitch jitter are not the
    road's), the horizontal course over a metre. The path is extended ``EXTENSION`` metres
    straight beyond both ends.

    Returns:
        ``(s, xyz, heading, frame_s)``: ``(P,)`` arc length (horizontal; 0 at the first frame),
        ``(P, 3)`` ground points, ``(P, 2)`` unit horizontal heading ``(dx, dz)``, ``(N,)`` arc
        length of every frame.
    """
    ground = poses[:, :3, 3] + CAMERA_HEIGHT * poses[:, :3, 1]
    step = np.linalg.norm(np.diff(ground[:, [0, 2]], axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(step)])
    frame_arc = arc
    moving = np.concatenate([[True], np.diff(arc) > 1e-3])
    arc, ground = arc[moving], ground[moving]
    if arc[-1] < 1.0:
        # A standing car: a straight road along the first camera's horizontal forward axis.
        fwd = poses[0, :3, 2][[0, 2]]
        fwd = fwd / n if (n := np.linalg.norm(fwd)) > 1e-6 else np.array([0.0, 1.0])
        s = np.arange(0.0, 1.0 + 1e-9, PATH_STEP)
        xyz = ground[:1] + s[:, None] * np.array([fwd[0], 0.0, fwd[1]])
    else:
        s = np.linspace(0.0, arc[-1], max(int(np.ceil(arc[-1] / PATH_STEP)), 1) + 1)
        xyz = np.stack([np.interp(s, arc, ground[:, i]) for i in range(3)], -1)
        xyz[:, [0, 2]] = gaussian_filter1d(xyz[:, [0, 2]], 1.0 / PATH_STEP, axis=0, mode="nearest")
        xyz[:, 1] = gaussian_filter1d(xyz[:, 1], 2.0 / PATH_STEP, mode="nearest")
    heading = np.gradient(xyz[:, [0, 2]], axis=0)
    norm = np.linalg.norm(heading, axis=1, keepdims=True)
    heading = np.where(norm > 1e-9, heading / norm.clip(1e-12), np.array([0.0, 1.0]))
    # Recompute the arc length of the smoothed course, then extend both ends straight.
    raw = s
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz[:, [0, 2]], axis=0), axis=1))])
    frame_s = np.interp(frame_arc, raw, s)
    ext = np.arange(PATH_STEP, EXTENSION + 1e-9, PATH_STEP)
    h0, h1 = heading[0], heading[-1]
    before = xyz[0] - ext[::-1, None] * np.array([h0[0], 0.0, h0[1]])
    after = xyz[-1] + ext[:, None] * np.array([h1[0], 0.0, h1[1]])
    s = np.concatenate([-ext[::-1], s, s[-1] + ext])
    xyz = np.concatenate([before, xyz, after])
    heading = np.concatenate(
        [np.repeat(h0[None], len(ext), 0), heading, np.repeat(h1[None], len(ext), 0)]
    )
    return s, xyz, heading, frame_s


def _ground_grid(
    s: np.ndarray,
    xyz: np.ndarray,
    heading: np.ndarray,
    cfg: WorldConfig,
    extension: np.ndarray,
) -> tuple[tuple[float, float], float, np.ndarray]:
    """The ground grid: per cell the ground y, and s, d, |d| of the nearest centreline point.

    Returns:
        ``((x0, z0), cell, grid)`` with ``grid`` ``(nz, nx, 4)`` float32.
    """
    lo = xyz[:, [0, 2]].min(0) - cfg.margin
    hi = xyz[:, [0, 2]].max(0) + cfg.margin
    area = float(np.prod(hi - lo))
    cell = max(cfg.grid_cell, math.sqrt(area / MAX_GRID_CELLS))
    # Cells on one world-wide lattice: overlapping sections interpolate the same cell values.
    lo = np.floor(lo / cell) * cell
    nx, nz = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
    gx = lo[0] + cell * np.arange(nx)
    gz = lo[1] + cell * np.arange(nz)
    X, Z = np.meshgrid(gx, gz, indexing="xy")
    pts = np.stack([X.ravel(), Z.ravel()], -1)
    _, idx = cKDTree(xyz[:, [0, 2]]).query(pts)
    rel = pts - xyz[idx][:, [0, 2]]
    h = heading[idx]
    along = (rel * h).sum(-1)
    lateral = rel[:, 0] * h[:, 1] - rel[:, 1] * h[:, 0]  # · right = (dz, -dx)
    # Heights: a Gaussian-weighted mean of the centreline heights nearby (kernel regression,
    # splatted on the grid and filtered), so that passes of the path that meet blend smoothly
    # and every frame's ground point keeps its height; the straight extensions count little
    # where they cross the real path. Away from the path the weights fade (through ``floor``)
    # into a broadly smoothed field of the nearest centreline heights, so the ground is smooth
    # everywhere.
    weight = np.where(extension, 0.05, 1.0)
    num = np.zeros(nz * nx)
    den = np.zeros(nz * nx)
    fx = (xyz[:, 0] - lo[0]) / cell
    fz = (xyz[:, 2] - lo[1]) / cell
    ix, iz = np.floor(fx).astype(int), np.floor(fz).astype(int)
    for dx, dz in ((0, 0), (1, 0), (0, 1), (1, 1)):
        w = weight * np.abs(1 - dx - (fx - ix)) * np.abs(1 - dz - (fz - iz))
        flat = np.clip(iz + dz, 0, nz - 1) * nx + np.clip(ix + dx, 0, nx - 1)
        np.add.at(num, flat, w * xyz[:, 1])
        np.add.at(den, flat, w)
    num = gaussian_filter(num.reshape(nz, nx), 3.0 / cell, mode="nearest")
    den = gaussian_filter(den.reshape(nz, nx), 3.0 / cell, mode="nearest")
    far = gaussian_filter(xyz[idx, 1].reshape(nz, nx), 20.0 / cell, mode="nearest")
    # On the path den ≈ (1 / PATH_STEP) · cell² / (√(2π) · 3 m) ≈ 0.27 per m² of cell.
    floor = 0.0003 * cell * cell
    height = (num + floor * far) / (den + floor)
    grid = np.stack(
        [
            height.ravel(),
            s[idx] + along,
            lateral,
            np.abs(lateral),
        ],
        -1,
    ).reshape(nz, nx, 4)
    return (float(lo[0]), float(lo[1])), float(cell), grid.astype(np.float32)


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
