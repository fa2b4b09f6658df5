"""The road of a persistent world: its centreline under the trajectory, and the ground of a
section of it, a height field with road coordinates on a regular grid (:class:`Ground`).

The centreline is the camera path itself (the camera drives in the middle of its lane), smoothed
and resampled by arc length, and extended ``EXTENSION`` metres straight beyond both ends. The
ground grid stores per cell the ground height (a Gaussian-weighted mean of the centreline
heights nearby) and the road coordinates of the nearest centreline point: the arc length ``s``
and the signed lateral offset ``d`` (metres, positive to the right of the direction of travel).
World coordinates as :mod:`.worlds`: x right, y down, z forward, so "up" is ``-y``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.ndimage import gaussian_filter, gaussian_filter1d
from scipy.spatial import cKDTree

from mfg_lightning.scene.camera import CAMERA_HEIGHT
from mfg_lightning.scene.world_config import WorldConfig

__all__ = ["EXTENSION", "MAX_GRID_CELLS", "PATH_STEP", "Ground", "ground_grid", "road_centreline"]

#: Straight road added beyond both ends of the trajectory (metres).
EXTENSION = 250.0
#: Arc-length spacing of the resampled path (metres).
PATH_STEP = 0.5
#: Largest number of grid cells of a section's ground: longer sections get coarser cells.
MAX_GRID_CELLS = 600_000


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
        # Empty until the world that builds this ground places its static boxes on it.
        self.static_index = np.zeros(0, dtype=np.int64)
        self.static_centre = np.zeros((0, 3))

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


def road_centreline(
    poses: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The road centreline under a trajectory, resampled every ``PATH_STEP`` metres.

    The ground point of every frame is the camera position moved ``CAMERA_HEIGHT`` down the
    camera's own y axis. Frames where the car stands still add nothing; heights are smoothed
    along the path over a couple of metres (suspension bumps and pitch jitter are not the
    road's), the horizontal course over a metre. The path is extended ``EXTENSION`` metres
    straight beyond both ends.

    Args:
        poses: ``(N, 4, 4)`` float64 camera poses ``T_world_cam``.

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


def ground_grid(
    s: np.ndarray,
    xyz: np.ndarray,
    heading: np.ndarray,
    cfg: WorldConfig,
    extension: np.ndarray,
) -> tuple[tuple[float, float], float, np.ndarray]:
    """The ground grid: per cell the ground y, and s, d, |d| of the nearest centreline point.

    Args:
        s, xyz, heading: ``(P,)``, ``(P, 3)``, ``(P, 2)`` the centreline the ground is built
            from (as :func:`road_centreline` returns).
        cfg: the world's layout (its ``grid_cell`` and ``margin``).
        extension: ``(P,)`` bool, centreline points on the straight extensions beyond the
            trajectory's ends (they weigh little where they cross the real path).

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
