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

from mfg_lightning.scene.furnishing import (
    CAR,
    CRATE,
    FACADE,
    KIND_NAMES,
    PARKED_CAR,
    PEDESTRIAN,
    Boxes,
    MovingObjects,
    empty_boxes,
    place_moving,
    place_static,
    yaw_pose,
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

#: Arc length of a section of the path (metres): frames in one section see one ground.
SECTION = 100.0
#: Centreline beyond a section's ends that its ground is built from (metres; at least the
#: renderer's culling distance, so that a switch of sections changes nothing in view).
SECTION_MARGIN = 200.0


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
            static=empty_boxes(),
            static_s=np.zeros(0),
            static_clearance=np.zeros(0),
            moving=MovingObjects(empty_boxes(), *(np.zeros(0) for _ in range(4))),
            exposure=_exposure(seeded_rng(seed, "world", name, "exposure"), poses.shape[0], cfg),
            sun=_sun(seeded_rng(seed, "world", name, "sun")),
        )
        placed = place_static(world, seeded_rng(seed, "world", name, "static"))
        world.static, world.static_s, world.static_clearance = (
            placed.boxes,
            placed.s,
            placed.clearance,
        )
        world._footprint_x, world._footprint_z = placed.footprint_x, placed.footprint_z
        world.moving = place_moving(world, seeded_rng(seed, "world", name, "moving"))
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


# --------------------------------------------------------------------------------------------
# Helpers of generation
# --------------------------------------------------------------------------------------------


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
