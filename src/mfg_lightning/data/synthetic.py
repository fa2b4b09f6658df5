"""The built-in synthetic driving dataset: procedural scenes, exact flow, no download.

A car-mounted camera (KITTI-like intrinsics, 1.65 m above a ground plane) drives along a
continuous trajectory: either a procedural driving model (speed, yaw rate, small pitch and roll,
bumps; all smooth AR(1) processes) or the real KITTI ground-truth poses
(``trajectory=kitti``, ``poses_dir`` pointing at KITTI's ``poses/XX.txt``). Around it: building
facades and parked boxes at random distances, sky at the far plane (655.35 m, as Virtual KITTI),
and a random number of independently moving objects (cars and pedestrians) with their own 3D
velocity.

Every sample is generated on the fly from ``(seed, sequence, frame)``: the same index always
yields the same sample, in any worker. The input flow is the *exact* reprojection flow
(:func:`mfg_lightning.geometry.reprojection_flow`, not the linearised field) plus Gaussian noise
and a fraction of outliers. Each sample also carries depth, the relative pose, intrinsics, the
ground-truth moving-object mask and the flow due to object motion alone (see
:mod:`mfg_lightning.data.sample`).

Scenes are drawn anew for every frame (the world does not persist along a trajectory): the flow of
a frame depends only on the relative pose and the scene in front of the camera at that moment,
which is what egomotion and object motion are evaluated on.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning import geometry
from mfg_lightning.data import transforms
from mfg_lightning.data.base import (
    MFGDataModule,
    MotionDataset,
    check_offsets,
    normalize_sequence,
)
from mfg_lightning.data.flow_estimation import (
    EstimatedFlow,
    ExactFlow,
    FlowCache,
    FlowSource,
    parse_flow,
)
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.pose_io import read_kitti_poses

log = logging.getLogger(__name__)

#: KITTI odometry sequences 00–02 at full resolution (formats.md): fx, fy, cx, cy, width, height.
KITTI_INTRINSICS = (718.856, 718.856, 607.1928, 185.2157, 1241, 376)
FAR_PLANE = 655.35
CAMERA_HEIGHT = 1.65

# Surface classes, for the RGB rendering and for telling moving pixels apart.
SKY, GROUND, BUILDING, PARKED, MOVING = 0, 1, 2, 3, 4
_COLOURS = np.array(
    [[135, 190, 235], [110, 110, 110], [170, 130, 100], [60, 90, 170], [210, 50, 40]],
    dtype=np.float32,
)


@dataclass(frozen=True)
class SceneConfig:
    """Ranges of the procedural scene (metres, metres per frame at 10 Hz).

    Attributes:
        buildings_per_side: maximum number of facade boxes on each side of the road.
        building_distance: lateral distance range of the facades from the camera.
        parked_boxes: maximum number of static car-sized boxes.
        moving_objects: maximum number of independently moving objects.
        object_speed: maximum speed of moving cars; pedestrians move at up to a tenth of it.
        pedestrian_fraction: probability that a moving object is a pedestrian.
    """

    buildings_per_side: int = 4
    building_distance: tuple[float, float] = (5.0, 15.0)
    parked_boxes: int = 6
    moving_objects: int = 4
    object_speed: float = 1.5
    pedestrian_fraction: float = 0.25


def _rng(seed: int, *keys: object) -> np.random.Generator:
    """A generator seeded from ``seed`` and any keys: independent of call order and workers."""
    digest = hashlib.blake2b(repr((seed, *keys)).encode(), digest_size=8).digest()
    return np.random.default_rng(int.from_bytes(digest, "little"))


def kitti_like_intrinsics(height: int, width: int) -> torch.Tensor:
    """KITTI's left colour camera intrinsics scaled to ``height × width``. ``(4,)`` pixels."""
    fx, fy, cx, cy, w0, h0 = KITTI_INTRINSICS
    return geometry.scale_intrinsics(
        torch.tensor([fx, fy, cx, cy], dtype=torch.float64), width / w0, height / h0
    )


# --------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------


def procedural_trajectory(rng: np.random.Generator, length: int) -> torch.Tensor:
    """A continuous driving trajectory from a smooth random driving model.

    Speed, yaw rate, pitch, roll and vertical bumps follow AR(1) processes, so consecutive
    motions are correlated as in real driving (stops, turns, straight stretches).

    Returns:
        ``(length, 4, 4)`` float64 camera-to-world poses ``T_world_cam``, starting at identity.
    """
    speed = rng.uniform(0.2, 1.4)
    yaw = pitch = roll = bump = 0.0
    motions = np.zeros((length - 1, 6))
    for k in range(length - 1):
        speed = float(np.clip(0.98 * speed + 0.02 * 0.8 + rng.normal(0, 0.04), 0.0, 1.6))
        yaw = 0.92 * yaw + rng.normal(0, 0.006)
        pitch = 0.7 * pitch + rng.normal(0, 0.0015)
        roll = 0.7 * roll + rng.normal(0, 0.001)
        bump = 0.6 * bump + rng.normal(0, 0.004)
        # The car moves along the chord of its turn: a little sideways when it yaws.
        motions[k] = [speed * np.sin(yaw / 2), bump, speed * np.cos(yaw / 2), pitch, yaw, roll]
    rel = geometry.motion_to_pose(
        torch.from_numpy(motions[:, :3]), torch.from_numpy(motions[:, 3:])
    )
    return geometry.trajectory_from_motions(rel)


# --------------------------------------------------------------------------------------------
# Scenes and rendering
# --------------------------------------------------------------------------------------------


def _sample_boxes(
    rng: np.random.Generator, cfg: SceneConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of one scene in camera coordinates (x right, y down, z forward).

    Returns:
        ``(boxes, kinds, motion)``: ``(K, 2, 3)`` min and max corners, ``(K,)`` surface class,
        ``(K, 3)`` displacement of each box over one frame (zero for static ones).
    """
    h = CAMERA_HEIGHT
    boxes, kinds, motion = [], [], []
    for side in (-1.0, 1.0):
        z = rng.uniform(-5.0, 10.0)
        for _ in range(rng.integers(0, cfg.buildings_per_side + 1)):
            length = rng.uniform(8.0, 40.0)
            near = rng.uniform(*cfg.building_distance)
            depth = rng.uniform(6.0, 15.0)
            top = h - rng.uniform(4.0, 20.0)
            x0, x1 = sorted((side * near, side * (near + depth)))
            boxes.append([[x0, top, z], [x1, h, z + length]])
            kinds.append(BUILDING)
            motion.append([0.0, 0.0, 0.0])
            z += length + rng.uniform(0.0, 12.0)
    for _ in range(rng.integers(0, cfg.parked_boxes + 1)):
        side = rng.choice([-1.0, 1.0])
        x = side * rng.uniform(2.5, 5.0)
        z = rng.uniform(4.0, 60.0)
        boxes.append([[x - 0.9, h - 1.5, z], [x + 0.9, h, z + 4.2]])
        kinds.append(PARKED)
        motion.append([0.0, 0.0, 0.0])
    for _ in range(rng.integers(0, cfg.moving_objects + 1)):
        if rng.random() < cfg.pedestrian_fraction:
            size = np.array([0.6, 1.75, 0.6])
            speed = rng.uniform(0.02, 0.15) * cfg.object_speed
            heading = rng.uniform(0, 2 * np.pi)
            d = [speed * np.cos(heading), 0.0, speed * np.sin(heading)]
            x, z = rng.uniform(-7.0, 7.0), rng.uniform(5.0, 40.0)
        else:
            size = np.array([1.8, 1.5, 4.2])
            # Oncoming or same-direction traffic, occasionally crossing.
            if rng.random() < 0.2:
                d = [rng.choice([-1, 1]) * rng.uniform(0.2, 1.0) * cfg.object_speed, 0.0, 0.0]
            else:
                d = [rng.normal(0, 0.05), 0.0, rng.uniform(-1.0, 1.0) * cfg.object_speed]
            x, z = rng.uniform(-7.0, 7.0), rng.uniform(6.0, 70.0)
        lo = np.array([x - size[0] / 2, h - size[1], z])
        boxes.append([lo, lo + size])
        kinds.append(MOVING)
        motion.append(d)
    if not boxes:
        return np.zeros((0, 2, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    return (
        np.asarray(boxes, dtype=np.float64),
        np.asarray(kinds),
        np.asarray(motion, dtype=np.float64),
    )


def _reciprocal(r: torch.Tensor) -> torch.Tensor:
    """``1 / r``, components below 1e-12 in magnitude taken as 1e-12 (a ray parallel to a slab
    then gets a huge but finite parameter instead of a division by zero)."""
    return 1.0 / torch.where(r.abs() < 1e-12, torch.full_like(r, 1e-12), r)


def ray_cast(rays: torch.Tensor, boxes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First hit of every ray against a ground plane and axis-aligned boxes (slab method).

    Rays are ``(x, y, 1)`` through normalised image coordinates, so the ray parameter of a hit
    *is* its depth along z. This is the general form for any set of rays; the renderer uses
    :func:`ray_cast_grid`, which gives the same result for the rays of a pixel grid.

    Args:
        rays: ``(N, 3)`` ray directions with z = 1.
        boxes: ``(K, 2, 3)`` min/max corners in camera coordinates (metres).

    Returns:
        ``(depth, hit)``: ``(N,)`` depth in metres (the far plane where nothing is hit) and
        ``(N,)`` index of the surface hit: −2 sky, −1 ground, k ≥ 0 box k.
    """
    n = rays.shape[0]
    depth = torch.full((n,), FAR_PLANE, dtype=rays.dtype)
    hit = torch.full((n,), -2, dtype=torch.long)
    down = rays[:, 1] > 1e-9
    ground = torch.where(
        down, CAMERA_HEIGHT / rays[:, 1].clamp_min(1e-9), torch.full_like(depth, np.inf)
    )
    on_ground = ground < depth
    depth = torch.where(on_ground, ground, depth)
    hit[on_ground] = -1
    if boxes.shape[0]:
        inv = _reciprocal(rays)
        # One (N, K) slab interval per axis; the entry and exit are their max and min. Taking
        # them axis by axis (rather than reducing a (N, K, 3) tensor over its short last
        # dimension) is several times faster and gives the same numbers (max/min are exact).
        bounds = boxes.permute(1, 2, 0)  # (2, 3, K): min/max, axis, box
        near, far = _slab(inv[:, 0, None], bounds[:, 0])  # (N, K)
        for axis in (1, 2):
            lo, hi = _slab(inv[:, axis, None], bounds[:, axis])
            near, far = torch.maximum(near, lo), torch.minimum(far, hi)
        best, idx = _first_hit(near, far, dim=1)
        closer = best < depth
        depth = torch.where(closer, best, depth)
        hit = torch.where(closer, idx, hit)
    return depth, hit


def _slab(inv: torch.Tensor, bounds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit ray parameters of every box's slab along one axis.

    Args:
        inv: reciprocal ray components along the axis, shaped to broadcast against the bounds.
        bounds: ``(2, ...)`` the boxes' min and max coordinates along the axis.

    Returns:
        ``(near, far)``, the broadcast shape of ``inv`` and one bound.
    """
    t0 = bounds[0] * inv
    t1 = bounds[1] * inv
    return torch.minimum(t0, t1), torch.maximum(t0, t1)


def _first_hit(
    near: torch.Tensor, far: torch.Tensor, dim: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest box hit in front of the camera from slab entries and exits with the boxes along
    ``dim``: the depth (inf where no box is hit) and the box index (the first box on a tie, as
    ``torch.min`` documents, whichever dimension the boxes are on)."""
    valid = (near <= far) & (near > 0.1)
    near = torch.where(valid, near, torch.full_like(near, np.inf))
    return near.min(dim=dim)


def ray_cast_grid(
    x: torch.Tensor, y: torch.Tensor, boxes: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`ray_cast` for the rays of a pixel grid, exploiting that they are separable.

    The ray through pixel ``(v, u)`` is ``(x_u, y_v, 1)``: its x slab interval depends on the
    column only and its y interval on the row only, so they are computed on ``(K, W)`` and
    ``(K, H)`` and only their combination runs over ``(K, H, W)``, with the boxes on the outer
    dimension so that every op is elementwise over contiguous image planes. The result equals
    ``ray_cast`` on the flattened grid exactly (the same products; max and min are exact;
    tested).

    Args:
        x: ``(W,)`` normalised x coordinate of every column.
        y: ``(H,)`` normalised y coordinate of every row.
        boxes: ``(K, 2, 3)`` min/max corners in camera coordinates (metres).

    Returns:
        ``(depth, hit)``: ``(H, W)`` depth in metres (the far plane where nothing is hit) and
        ``(H, W)`` surface index (−2 sky, −1 ground, k ≥ 0 box k).
    """
    height, width = y.shape[0], x.shape[0]
    # The ground is hit at a depth that depends on the row only.
    ground = torch.where(y > 1e-9, CAMERA_HEIGHT / y.clamp_min(1e-9), torch.full_like(y, np.inf))
    on_ground = (ground < FAR_PLANE)[:, None].expand(height, width)
    depth = torch.where(on_ground, ground[:, None], torch.full_like(ground, FAR_PLANE)[:, None])
    hit = torch.where(on_ground, -1, -2).to(torch.long)
    if boxes.shape[0]:
        bounds = boxes.permute(1, 2, 0)  # (2, 3, K): min/max, axis, box
        near_x, far_x = _slab(_reciprocal(x), bounds[:, 0, :, None])  # (K, W)
        near_y, far_y = _slab(_reciprocal(y), bounds[:, 1, :, None])  # (K, H)
        # z = 1 for every ray: the z slab is the box's own z range (times 1/1, as ray_cast).
        near_z, far_z = _slab(torch.ones(1, dtype=x.dtype), bounds[:, 2, :, None, None])
        near = torch.maximum(torch.maximum(near_x[:, None, :], near_y[:, :, None]), near_z)
        far = torch.minimum(torch.minimum(far_x[:, None, :], far_y[:, :, None]), far_z)
        best, idx = _first_hit(near, far, dim=0)
        closer = best < depth
        depth = torch.where(closer, best, depth)
        hit = torch.where(closer, idx, hit)
    return depth, hit


def render_sample(
    rel_pose: torch.Tensor,
    intrinsics: torch.Tensor,
    height: int,
    width: int,
    rng: np.random.Generator,
    scene: SceneConfig,
    noise_std: float,
    outlier_fraction: float,
) -> dict[str, torch.Tensor]:
    """Draw a scene, ray-cast it and compute the exact flow for one camera motion.

    Args:
        rel_pose: ``(4, 4)`` float64 ``T_src,tgt``.
        intrinsics: ``(4,)`` float64 pixels at ``height × width``.
        noise_std: standard deviation of the Gaussian flow noise, pixels.
        outlier_fraction: fraction of pixels whose flow is replaced by a uniform random vector.

    Returns:
        The tensor fields of a sample (float32, bool, uint8) — see :mod:`..sample`.
    """
    boxes, kinds, motion = _sample_boxes(rng, scene)
    K = intrinsics[None]
    xy = geometry.normalized_grid(K, height, width)[0]
    depth, hit = ray_cast_grid(xy[0, 0], xy[1, :, 0], torch.from_numpy(boxes))
    depth = depth[None]
    # Per-surface lookup tables indexed by ``surface``: box k at row k, then one row for the
    # ground and one for the sky. One gather per table replaces boolean-mask indexing.
    n_box = boxes.shape[0]
    surface = torch.where(hit >= 0, hit, n_box + (hit == -2).long())  # (H, W)
    box_motion = torch.from_numpy(motion)
    displacement = torch.cat([box_motion, box_motion.new_zeros(2, 3)])[surface]  # (H, W, 3)
    moving = torch.cat([box_motion.norm(dim=-1) > 0, torch.zeros(2, dtype=torch.bool)])
    object_mask = moving[surface]
    if bool(object_mask.any()):
        # The rigid flow and the flow with the objects' displacement in one batched call (the
        # same numbers as two calls, bit for bit; the reprojection is the costliest step left).
        rigid, flow = geometry.reprojection_flow(
            depth.expand(2, -1, -1),
            rel_pose[None].expand(2, -1, -1),
            K.expand(2, -1),
            torch.stack([torch.zeros_like(displacement), displacement]),
        )
    else:
        # Nothing moves in view: the displacement is zero everywhere and the flow is the rigid one.
        rigid = flow = geometry.reprojection_flow(depth, rel_pose[None], K)[0]
    object_flow = torch.where(object_mask[None], flow - rigid, torch.zeros_like(flow))

    # Points that end up behind the target camera have no meaningful flow.
    limit = 2.0 * max(height, width)
    valid = torch.isfinite(flow).all(0) & (flow.abs().amax(0) < limit)
    noisy = flow + noise_std * torch.from_numpy(rng.standard_normal(flow.shape))
    if outlier_fraction > 0:
        outliers = torch.from_numpy(rng.random((height, width)) < outlier_fraction)
        random_flow = torch.from_numpy(
            rng.uniform(-1, 1, flow.shape)
        ) * flow.abs().amax().clamp_min(1.0)
        noisy = torch.where(outliers[None], random_flow, noisy)
    noisy = torch.where(valid[None], noisy, torch.zeros_like(noisy))

    kind = torch.cat([torch.from_numpy(kinds).long(), torch.tensor([GROUND, SKY])])[surface]
    shade = (1.0 - 0.6 * (depth[0].clamp(max=80.0) / 80.0)).numpy()[..., None]
    shade[kind.numpy() == SKY] = 1.0
    rgb = (_COLOURS[kind.numpy()] * shade).clip(0, 255).astype(np.uint8)
    return {
        "flow": noisy.float(),
        "flow_valid": valid,
        "depth": depth[0].float(),
        "object_mask": object_mask & valid,
        "object_flow": object_flow.float(),
        "rgb": torch.from_numpy(rgb).permute(2, 0, 1).contiguous(),
    }


# --------------------------------------------------------------------------------------------
# Dataset and DataModule
# --------------------------------------------------------------------------------------------


class TrajectoryDataset(MotionDataset):
    """Samples ``frame → frame + offset`` along given trajectories: the index, the poses.

    Args:
        trajectories: sequence name → ``(N, 4, 4)`` float64 ``T_world_cam`` poses.
        frames: sequence name → ``(first, last)`` range of source frames to use (inclusive).
        height, width: output resolution.
        seed: seed of the scene content.
        offsets: target frame offsets from each source frame (``[1]``: consecutive frames;
            ``[-2, -1, 1, 2]``: the central-frame snippets).
        name: dataset name used in sample ids.
        stride: use the source frames whose index is a multiple of ``stride`` (1: all); counted
            from frame 0 of the sequence, so that a split's frames are those of the union.
    """

    def __init__(
        self,
        trajectories: dict[str, torch.Tensor],
        frames: dict[str, tuple[int, int]],
        height: int,
        width: int,
        seed: int = 0,
        offsets: Sequence[int] = (1,),
        name: str = "synthetic",
        stride: int = 1,
    ) -> None:
        self.height, self.width, self.seed, self.name = height, width, seed, name
        self.trajectories = trajectories
        self.intrinsics = kitti_like_intrinsics(height, width)
        self.offsets = check_offsets(offsets)
        self.samples = []
        for seq, (first, last) in frames.items():
            n = trajectories[seq].shape[0]
            for k in range(first + (-first) % stride, last + 1, stride):
                for off in self.offsets:
                    if 0 <= k + off < n:
                        self.samples.append((seq, k, k + off))

    def _pose(self, seq: str, src: int, tgt: int) -> torch.Tensor:
        traj = self.trajectories[seq]
        return geometry.relative_pose(traj[src], traj[tgt])

    def relative_poses(self) -> torch.Tensor:
        if not self.samples:
            return torch.zeros(0, 4, 4, dtype=torch.float64)
        return torch.stack([self._pose(s, a, b) for s, a, b in self.samples])

    def _check_index(self, i: int) -> None:
        if not 0 <= i < len(self.samples):
            raise IndexError(f"{self.name}: sample {i} out of range (0 … {len(self.samples) - 1})")

    def _identity(self, seq: str, src: int, tgt: int, pose: torch.Tensor) -> dict:
        """The fields every sample carries besides its images and flow."""
        return {
            "pose": pose.float(),
            "intrinsics": self.intrinsics.float(),
            "sequence": seq,
            "frame": src,
            "target": tgt,
            "sample_id": f"{self.name}/{seq}/{src:06d}->{tgt:06d}",
        }


class SyntheticDrivingDataset(TrajectoryDataset):
    """``flow=exact``: sample ``i`` is generated from ``(seed, sequence, frame)`` on a scene drawn
    for that frame, with the exact flow corrupted by noise and outliers.

    Args:
        noise_std, outlier_fraction: flow corruption (pixels, fraction).
        scene: ranges of the procedural scene.
        args, kwargs: ``trajectories``, ``frames``, ``height``, ``width``, ``seed``, ``offsets``,
            ``name`` of :class:`TrajectoryDataset`.
    """

    def __init__(
        self,
        *args: Any,
        noise_std: float = 0.3,
        outlier_fraction: float = 0.01,
        scene: SceneConfig | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.noise_std, self.outlier_fraction = noise_std, outlier_fraction
        self.scene = scene or SceneConfig()

    def __getitem__(self, i: int) -> dict:
        self._check_index(i)
        seq, src, tgt = self.samples[i]
        pose = self._pose(seq, src, tgt)
        rng = _rng(self.seed, seq, src, tgt)
        sample = render_sample(
            pose,
            self.intrinsics,
            self.height,
            self.width,
            rng,
            self.scene,
            self.noise_std,
            self.outlier_fraction,
        )
        sample.update(self._identity(seq, src, tgt, pose))
        return sample


#: The render size of ``flow=dis`` when ``flow.height``/``flow.width`` are unset: the released
#: code's image size (its flow, the model input, is a quarter of it).
RENDER_SIZE = (192, 512)
#: The regions flow quality is reported for (the renderer's region map), then all pixels.
QUALITY_REGIONS = ("road", "structure", "moving", "far", "all")
# Bump when the arrays cached per pair change, so old caches are not misread.
_RENDER_CACHE_FORMAT = 2
#: What :class:`RenderedDrivingDataset` caches per pair, at the model input ``h × w``: the
#: float fields as channels of one ``(h, w, 7)`` float32 array and the byte fields of one
#: ``(h, w, 4)`` uint8 array (two array headers to parse per sample instead of eight).
_FLOAT_FIELDS = (
    ("flow", 2),  # estimated flow, NaN where it was not finite
    ("exact_flow", 2),  # exact flow, 0 where unknown
    ("object_flow", 2),  # flow due to object motion alone, 0 off objects
    ("depth", 1),  # metres, 0 where unknown
)
_BYTE_FIELDS = (("rgb", 3), ("object_mask", 1))  # source frame; moving-object mask (0 / 1)
# plus "stats": (len(QUALITY_REGIONS) * 3 + 1,) float64, the quality (EPE sum, Fl outliers,
# pixels per region, at the image size) and the number of non-finite estimated pixels.


def _renderer():
    """The persistent-world renderer (:mod:`.worlds`, :mod:`.render`), imported on first use so
    that ``flow=exact`` never loads it."""
    from mfg_lightning.data import render, worlds

    return worlds, render


def _numpy(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _hw2(field: Any) -> np.ndarray:
    """A ``(2, H, W)`` tensor or ``(H, W, 2)`` array → ``(H, W, 2)`` float32."""
    a = _numpy(field)
    if a.ndim == 3 and a.shape[0] == 2 and a.shape[2] != 2:
        a = np.moveaxis(a, 0, 2)
    return np.ascontiguousarray(a, dtype=np.float32)


def region_codes() -> list[tuple[str, int | None]]:
    """``(name, code)`` of every :data:`QUALITY_REGIONS` entry in the renderer's region map
    (``None``: all pixels)."""
    _, render = _renderer()
    codes = {
        "road": render.REGION_ROAD,
        "structure": render.REGION_STRUCTURE,
        "moving": render.REGION_MOVING,
        "far": render.REGION_FAR,
    }
    return [(name, codes.get(name)) for name in QUALITY_REGIONS]


def flow_quality(
    estimated: np.ndarray, exact: np.ndarray, valid: np.ndarray, region: np.ndarray
) -> np.ndarray:
    """End-point error and KITTI's Fl outliers of an estimated flow against the exact one.

    A pixel is an Fl outlier when its end-point error exceeds 3 px *and* 5 % of the exact flow's
    magnitude (the KITTI 2015 flow benchmark's definition).

    Args:
        estimated, exact: ``(H, W, 2)`` pixels (at the image size the flow was estimated at).
        valid: ``(H, W)`` bool, the pixels that count (exact flow known, estimate finite).
        region: ``(H, W)`` the renderer's region code of every pixel.

    Returns:
        ``(len(QUALITY_REGIONS), 3)`` float64: per region, the sum of the end-point errors
        (pixels), the number of outliers and the number of pixels counted; sums, so that pairs
        pool by addition.
    """
    epe = np.linalg.norm(estimated.astype(np.float64) - exact, axis=2)
    outlier = (epe > 3.0) & (epe > 0.05 * np.linalg.norm(exact.astype(np.float64), axis=2))
    out = np.zeros((len(QUALITY_REGIONS), 3))
    for r, (_, code) in enumerate(region_codes()):
        m = valid if code is None else valid & (region == code)
        out[r] = (epe[m].sum(), outlier[m].sum(), m.sum())
    return out


def summarize_quality(stats: np.ndarray) -> dict[str, dict[str, float | None]]:
    """Pooled ``{region: {"epe": px, "fl": %, "pixels": n}}`` from summed per-pair stats
    (``(..., R, 3)``: pairs pooled pixel by pixel; None where a region had no pixel)."""
    total = stats.reshape(-1, len(QUALITY_REGIONS), 3).sum(axis=0)
    out: dict[str, dict[str, float | None]] = {}
    for name, (epe, outliers, n) in zip(QUALITY_REGIONS, total, strict=True):
        out[name] = {
            "epe": float(epe / n) if n else None,
            "fl": float(100.0 * outliers / n) if n else None,
            "pixels": float(n),
        }
    return out


_DIGESTS: dict[tuple[str, ...], str] = {}


def _source_digest(*modules: Any) -> str:
    """A digest of the source files of ``modules``: any change to the renderer changes it.

    Read once per process, so that one process keeps one cache key even if the files are
    edited while it runs (it runs the code it imported)."""
    names = tuple(m.__file__ for m in modules)
    if names not in _DIGESTS:
        h = hashlib.sha256()
        for name in names:
            h.update(Path(name).read_bytes())
        _DIGESTS[names] = h.hexdigest()[:16]
    return _DIGESTS[names]


@dataclass
class _Frame:
    """One rendered frame, kept while pairs still need it."""

    rendered: Any  # render.RenderedFrame at the image size
    image: np.ndarray  # the estimator's input (DIS: grey)


class RenderedDrivingDataset(TrajectoryDataset):
    """``flow=dis`` (any estimator): frames rendered from one persistent world per trajectory,
    flow estimated on them at the image size, resized to the model input, cached.

    Each trajectory gets a :class:`~mfg_lightning.data.worlds.World` from ``(seed, sequence
    name, poses)``; a frame is rendered (:func:`~mfg_lightning.data.render.render_frame`) at
    ``image_hw`` and its pairs get the exact flow from the same ray casts
    (:func:`~mfg_lightning.data.render.exact_flow`) and the estimated flow. The sample's ``flow``
    is the estimate (valid where finite); ``exact_flow``, ``depth``, ``object_mask`` and
    ``object_flow`` are the ground truth at the model input. The flow quality (EPE and Fl per
    region, at the image size, against the exact flow) is computed with the estimate and kept
    in the cache beside it.

    Cache: ``<cache_dir>/synthetic_flow/<key>/<seq>/<src:06d>_<tgt:06d>.npz``, ``<key>`` a hash
    of everything that changes a pair (estimator and its settings, image and input size, seed,
    world config, the trajectory's poses, the renderer's source, library versions).
    :meth:`precompute_flow` fills it rendering every frame once; ``__getitem__`` computes a
    missing pair on its own.

    Args:
        flow: the estimator and the image size (``flow.height × flow.width``, default
            :data:`RENDER_SIZE`).
        world: :class:`~mfg_lightning.data.worlds.WorldConfig` fields (None: its defaults).
        cache_dir: the user cache directory (``paths.cache_dir``).
        args, kwargs: ``trajectories``, ``frames``, ``height``, ``width``, ``seed``, ``offsets``,
            ``name`` of :class:`TrajectoryDataset`.
    """

    def __init__(
        self,
        *args: Any,
        flow: EstimatedFlow,
        world: dict[str, Any] | None = None,
        cache_dir: str | Path | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.flow_source = flow
        self.estimator = flow.estimator
        self.image_hw = check_render_size(flow, (self.height, self.width))
        self.image_intrinsics = kitti_like_intrinsics(*self.image_hw)
        self.world_fields = dict(world or {})
        self.world_config = _world_config(self.world_fields)
        self._worlds: dict[str, Any] = {}
        self.span = max(abs(o) for o in self.offsets)
        worlds, render = _renderer()
        key = {
            "format": _RENDER_CACHE_FORMAT,
            "flow": flow.key(),
            "image_hw": list(self.image_hw),
            "output_hw": [self.height, self.width],
            "seed": self.seed,
            "world": {k: self.world_fields[k] for k in sorted(self.world_fields)},
            "trajectories": {
                seq: hashlib.sha256(
                    np.ascontiguousarray(poses.double().numpy()).tobytes()
                ).hexdigest()[:16]
                for seq, poses in sorted(self.trajectories.items())
            },
            "renderer": _source_digest(worlds, render),
            "torch": torch.__version__,
            "numpy": np.__version__,
        }
        if cache_dir is None:
            from mfg_lightning.data.kitti import default_cache_dir

            cache_dir = default_cache_dir()
        self.cache = FlowCache.create(cache_dir, key, namespace="synthetic_flow")
        # What this object rendered and estimated (the tests count them; a cached run: 0).
        self.rendered_frames = 0
        self.estimated_pairs = 0

    # -- cache -------------------------------------------------------------------------------

    def pair_path(self, i: int) -> Path:
        seq, src, tgt = self.samples[i]
        return self.cache.root / seq / f"{src:06d}_{tgt:06d}.npz"

    def missing(self) -> list[int]:
        """Indices of the samples whose pair is not cached yet (stat calls only)."""
        return [i for i in range(len(self.samples)) if not self.pair_path(i).exists()]

    def _cached(self, i: int) -> dict[str, np.ndarray] | None:
        packed = self.cache.load_arrays(self.pair_path(i), ("floats", "bytes"))
        if packed is None or packed["floats"].shape != (self.height, self.width, 7):
            return None
        return _unpack(packed)

    # -- rendering and estimation ------------------------------------------------------------

    def world(self, seq: str) -> Any:
        """The persistent world of trajectory ``seq`` (generated on first use)."""
        if seq not in self._worlds:
            worlds, _ = _renderer()
            self._worlds[seq] = worlds.World.generate(
                self.trajectories[seq], seed=self.seed, name=seq, config=self.world_config
            )
        return self._worlds[seq]

    def render(self, seq: str, frame: int) -> _Frame:
        """Render frame ``frame`` of ``seq`` at the image size, with the estimator's input."""
        _, render = _renderer()
        rendered = render.render_frame(
            self.world(seq), frame, self.image_intrinsics, *self.image_hw
        )
        self.rendered_frames += 1
        rgb = np.ascontiguousarray(_numpy(rendered.rgb).transpose(1, 2, 0))
        return _Frame(rendered, self.estimator.prepare(rgb))

    def compute_pair(self, seq: str, src: int, tgt: int, a: _Frame, b: _Frame) -> dict:
        """Exact and estimated flow of ``src → tgt`` from the rendered frames ``a``, ``b``: the
        fields of a sample at the model input (``flow`` ``(h, w, 2)``, ``exact_flow``,
        ``object_flow``, ``depth`` ``(h, w)``, ``rgb`` ``(h, w, 3)``, ``object_mask``), the
        ``quality`` (:func:`flow_quality`) and ``nonfinite`` count at the image size, and the
        image-size fields under ``"full"`` (for pictures)."""
        _, render = _renderer()
        exact = render.exact_flow(
            self.world(seq), src, tgt, self.image_intrinsics, *self.image_hw, source=a.rendered
        )
        est = np.asarray(self.estimator(a.image, b.image), dtype=np.float32)
        self.estimated_pairs += 1
        finite = np.isfinite(est).all(axis=2)
        est = np.where(finite[..., None], est, 0.0).astype(np.float32)
        exact_flow = _hw2(exact["flow"])
        exact_valid = _numpy(exact["flow_valid"]).astype(bool) & np.isfinite(exact_flow).all(2)
        exact_flow = np.where(exact_valid[..., None], exact_flow, 0.0).astype(np.float32)
        region = _numpy(a.rendered.region)
        quality = flow_quality(est, exact_flow, exact_valid & finite, region)
        h, w = self.height, self.width
        flow, flow_ok = transforms.resize_flow(est, finite, h, w)
        exact_small, _ = transforms.resize_flow(exact_flow, exact_valid, h, w)
        mask = _numpy(exact["object_mask"]).astype(bool) & exact_valid
        object_flow = _hw2(exact["object_flow"])
        mask_small = transforms.resize_mask(mask, h, w, defined=exact_valid)
        object_small, _ = transforms.resize_flow(
            np.where(mask[..., None], object_flow, 0.0).astype(np.float32), mask, h, w, 0.0
        )
        rgb = np.ascontiguousarray(_numpy(a.rendered.rgb).transpose(1, 2, 0))
        return {
            "flow": np.where(flow_ok[..., None], flow, np.nan).astype(np.float32),
            "exact_flow": exact_small.astype(np.float32),
            "object_mask": mask_small,
            "object_flow": np.where(mask_small[..., None], object_small, 0.0).astype(np.float32),
            "depth": transforms.resize_depth(_numpy(exact["depth"]).astype(np.float32), h, w),
            "rgb": transforms.resize_rgb(rgb, h, w),
            "quality": quality,
            "nonfinite": np.int64((~finite).sum()),
            "full": {
                "frame": a.rendered,
                "exact": exact,
                "exact_flow": exact_flow,
                "exact_valid": exact_valid,
                "flow": est,
                "flow_valid": finite,
            },
        }

    def _store(self, i: int, pair: dict) -> dict[str, np.ndarray]:
        packed = {
            "floats": np.concatenate(
                [pair[k].reshape(self.height, self.width, n) for k, n in _FLOAT_FIELDS], axis=2
            ).astype(np.float32),
            "bytes": np.concatenate(
                [pair[k].reshape(self.height, self.width, n) for k, n in _BYTE_FIELDS], axis=2
            ).astype(np.uint8),
            "stats": np.append(pair["quality"].ravel(), float(pair["nonfinite"])),
        }
        self.cache.store_arrays(self.pair_path(i), packed)
        return _unpack(packed)

    def __getstate__(self) -> dict[str, Any]:
        # Worlds are rebuilt where they are needed (a worker renders its own sequences).
        return {**self.__dict__, "_worlds": {}}

    def _compute(self, indices: Sequence[int], bar: Any = None) -> int:
        """Render, estimate and cache the pairs ``indices`` in sequence and frame order, each
        frame rendered once and kept while a later pair (up to the largest offset ahead) can
        use it; the middle pair of each sequence also leaves its picture grid
        (:meth:`picture_path`). Returns how many frames were rendered."""
        frames: dict[tuple[str, int], _Frame] = {}
        rendered = self.rendered_frames
        middle = {ix[len(ix) // 2]: seq for seq, ix in self.sequences().items()}
        for i in sorted(indices, key=lambda k: self.samples[k][:2]):
            seq, src, tgt = self.samples[i]
            for key in [k for k in frames if k[0] != seq or k[1] < src - self.span]:
                del frames[key]
            for f in (src, tgt):
                if (seq, f) not in frames:
                    frames[(seq, f)] = self.render(seq, f)
            pair = self.compute_pair(seq, src, tgt, frames[(seq, src)], frames[(seq, tgt)])
            self._store(i, pair)
            if i in middle:
                self.cache.store(self.picture_path(seq), flow_picture(pair["full"]))
            if bar is not None:
                bar.update(1)
        return self.rendered_frames - rendered

    def precompute_flow(self, progress: bool = True, workers: int = 0) -> int:
        """Render, estimate and cache every pair not cached yet; return how many.

        Every frame is rendered once (:meth:`_compute`). With ``workers > 1`` the sequences
        are shared among that many processes (one torch and OpenCV thread each: on a few
        cores, processes scale better than threads); the progress bar then advances per
        finished sequence.
        """
        from tqdm.auto import tqdm

        todo = self.missing()
        if not todo:
            return 0
        bar = tqdm(
            total=len(todo),
            desc=f"render + {self.estimator.name} flow ({self.name})",
            unit="pair",
            disable=not progress,
        )
        by_seq: dict[str, list[int]] = {}
        for i in todo:
            by_seq.setdefault(self.samples[i][0], []).append(i)
        try:
            if workers <= 1 or len(by_seq) == 1:
                self._compute(todo, bar)
                return len(todo)
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor, as_completed

            context = multiprocessing.get_context("spawn")  # no forked torch or OpenCV state
            with ProcessPoolExecutor(min(workers, len(by_seq)), mp_context=context) as pool:
                # the longest sequences first, so that the last one to finish is a short one
                jobs = {
                    pool.submit(_compute_in_worker, self, part): len(part)
                    for part in sorted(by_seq.values(), key=len, reverse=True)
                }
                for job in as_completed(jobs):
                    self.rendered_frames += job.result()
                    self.estimated_pairs += jobs[job]
                    bar.update(jobs[job])
        finally:
            bar.close()
        return len(todo)

    def picture_path(self, seq: str) -> Path:
        """Where the picture grid of ``seq`` is cached (``(H', W', 3)`` uint8 ``.npy``)."""
        return self.cache.root / f"picture-{seq}.npy"

    def picture(self, seq: str) -> np.ndarray:
        """The picture grid (:func:`flow_picture`) of the middle pair of ``seq``, at the image
        size (renders its two frames)."""
        indices = self.sequences()[seq]
        _, src, tgt = self.samples[indices[len(indices) // 2]]
        pair = self.compute_pair(seq, src, tgt, self.render(seq, src), self.render(seq, tgt))
        return flow_picture(pair["full"])

    def quality(self) -> dict[str, Any]:
        """The flow quality of this split (pooled over its pairs) and its non-finite pixels,
        from the cache (every pair must be cached)."""
        stats = np.zeros((len(QUALITY_REGIONS), 3))
        nonfinite = 0
        for i in range(len(self.samples)):
            arrays = self.cache.load_arrays(self.pair_path(i), ("stats",))
            if arrays is None:
                raise FileNotFoundError(f"{self.pair_path(i)}: pair not cached yet")
            stats += arrays["stats"][:-1].reshape(stats.shape)
            nonfinite += int(arrays["stats"][-1])
        return {"regions": summarize_quality(stats), "nonfinite_pixels": nonfinite}

    # -- samples -----------------------------------------------------------------------------

    def __getitem__(self, i: int) -> dict:
        self._check_index(i)
        seq, src, tgt = self.samples[i]
        arrays = self._cached(i)
        if arrays is None:
            arrays = self._store(
                i, self.compute_pair(seq, src, tgt, self.render(seq, src), self.render(seq, tgt))
            )
        flow = torch.from_numpy(np.ascontiguousarray(arrays["flow"].transpose(2, 0, 1)))
        flow, valid, _ = sanitize_flow(flow, torch.ones(flow.shape[1:], dtype=torch.bool))
        sample = {
            "flow": flow,
            "flow_valid": valid,
            "depth": torch.from_numpy(np.ascontiguousarray(arrays["depth"])),
            "object_mask": torch.from_numpy(arrays["object_mask"]),
            "object_flow": transforms.flow_to_tensor(arrays["object_flow"]),
            "exact_flow": transforms.flow_to_tensor(arrays["exact_flow"]),
            "rgb": torch.from_numpy(np.ascontiguousarray(arrays["rgb"].transpose(2, 0, 1))),
        }
        sample.update(self._identity(seq, src, tgt, self._pose(seq, src, tgt)))
        return sample


def _compute_in_worker(dataset: RenderedDrivingDataset, indices: list[int]) -> int:
    """:meth:`RenderedDrivingDataset._compute` in a worker process, on one thread."""
    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    return dataset._compute(indices)


def _unpack(packed: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The named fields of a cached pair (views of its two packed arrays)."""
    out: dict[str, np.ndarray] = {}
    for array, fields in ((packed["floats"], _FLOAT_FIELDS), (packed["bytes"], _BYTE_FIELDS)):
        start = 0
        for name, n in fields:
            part = array[..., start : start + n]
            out[name] = part if n > 1 else part[..., 0]
            start += n
    out["object_mask"] = out["object_mask"].astype(bool)
    return out


def check_render_size(flow: EstimatedFlow, model_hw: tuple[int, int]) -> tuple[int, int]:
    """The image size of estimated synthetic flow, refused (naming ``flow.height``/
    ``flow.width``) when the renderer cannot take it or the flow cannot be resized down to the
    model input from it (a side below ``dataset.height``/``dataset.width``)."""
    hw = flow.image_hw(RENDER_SIZE)
    _, render = _renderer()
    try:
        render.check_render_size(*hw)
    except ValueError as err:
        raise ValueError(f"flow.height={hw[0]}, flow.width={hw[1]}: {err}") from None
    for key, size, need in zip(("height", "width"), hw, model_hw, strict=True):
        if size < need:
            raise ValueError(
                f"flow.{key}={size}: the render size {hw[0]} × {hw[1]} is smaller than the model "
                f"input {model_hw[0]} × {model_hw[1]} (dataset.height × dataset.width); render at "
                "least at the input size (default 192 × 512)"
            )
    return hw


def _world_config(fields: dict[str, Any]) -> Any:
    """``dataset.world`` → :class:`~mfg_lightning.data.worlds.WorldConfig` (None: defaults)."""
    if not fields:
        return None
    worlds, _ = _renderer()
    import dataclasses

    known = {f.name for f in dataclasses.fields(worlds.WorldConfig)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise ValueError(f"unknown dataset.world setting(s) {unknown}; known: {sorted(known)}")
    return worlds.WorldConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()}
    )


class SyntheticDataModule(MFGDataModule):
    """The default dataset: procedural driving or real KITTI trajectories, no download.

    Splits: ``train`` and ``test`` are disjoint sets of trajectories; ``val`` is the last
    ``val_fraction`` of every training trajectory (held out from training).

    Flow (the ``flow`` config group): ``flow=exact`` (default) generates every sample on the
    fly on a scene drawn for its frame (:class:`SyntheticDrivingDataset`); ``flow=dis`` renders
    persistent worlds and estimates the flow on the frames (:class:`RenderedDrivingDataset`),
    precomputed into the cache by :meth:`prepare_data`, whose flow quality (EPE, Fl per region)
    is logged when training starts (``<split>/flow_epe/<region>``, ``<split>/flow_fl/<region>``
    and a picture grid, to TensorBoard) and written beside the cache (``quality-<split>.json``).

    Args:
        trajectory: ``"procedural"`` or ``"kitti"``.
        poses_dir: directory of KITTI ``XX.txt`` pose files (``trajectory=kitti``).
        train_sequences, test_sequences: procedural: how many trajectories; kitti: lists of
            sequence names (paper split: train 00–08, test 09, 10).
        sequence_length: frames per procedural trajectory.
        max_frames: use at most this many frames of each KITTI sequence (None: all).
        val_fraction: tail of each training trajectory used for validation.
        flow: the ``flow`` config (:func:`~mfg_lightning.data.flow_estimation.parse_flow`):
            ``{"source": "exact", "noise_std": …, "outlier_fraction": …}`` (the default) or an
            estimator (``{"source": "dis", "preset": …, "height": …, "width": …}``).
        world: :class:`~mfg_lightning.data.worlds.WorldConfig` fields of the rendered worlds.
        cache_dir: where estimated flow is cached (``paths.cache_dir``).
        precompute_flow: fill the cache in :meth:`prepare_data` (else on first use).
        offsets: target offsets of every split, ``target = frame + offset`` (``[1]``; ``[-2, -1,
            1, 2]``: the flows from a centre frame to its neighbours, for central-frame ATE), as
            ``dataset=kitti``'s.
        frame_stride: training and validation use the source frames whose index is a multiple
            of it (1: all; 3: a third of the pairs to render, on the same worlds and cache).
            The test split always uses every frame, as the published protocols do.
        scene: :class:`SceneConfig` fields.
        scene_seed: seed of the trajectories and scenes (None: ``seed``, which then also sets
            the training order); the config fixes it so that runs differing in ``seed`` see the
            same samples, in a different order.
        Remaining arguments: see :class:`MFGDataModule`.
    """

    def __init__(
        self,
        trajectory: str = "procedural",
        poses_dir: str | None = None,
        train_sequences: int | Sequence[str] = 8,
        test_sequences: int | Sequence[str] = 2,
        sequence_length: int = 400,
        max_frames: int | None = None,
        val_fraction: float = 0.05,
        flow: FlowSource | dict[str, Any] | None = None,
        offsets: Sequence[int] = (1,),
        frame_stride: int = 1,
        scene: dict | None = None,
        scene_seed: int | None = None,
        world: dict[str, Any] | None = None,
        cache_dir: str | None = None,
        precompute_flow: bool = True,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        self.scene_seed = self.seed if scene_seed is None else int(scene_seed)
        if trajectory not in ("procedural", "kitti"):
            raise ValueError(
                f"dataset.trajectory must be 'procedural' or 'kitti', got {trajectory!r}"
            )
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"dataset.val_fraction must be in [0, 1), got {val_fraction}")
        self.flow = parse_flow(flow, default="exact")
        if not isinstance(self.flow, (ExactFlow, EstimatedFlow)):
            raise ValueError(
                f"flow.source={self.flow.source}: dataset=synthetic makes its own flow; use "
                "flow=exact (the default) or an estimator on rendered frames (flow=dis)"
            )
        if isinstance(self.flow, EstimatedFlow):
            check_render_size(self.flow, (self.height, self.width))
            _world_config(dict(world or {}))  # a bad world setting fails here, not later
        self.trajectory = trajectory
        self.poses_dir = poses_dir
        self.train_sequences = train_sequences
        self.test_sequences = test_sequences
        self.sequence_length = sequence_length
        if max_frames is not None and (
            isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 2
        ):
            raise ValueError(
                f"dataset.max_frames must be an integer ≥ 2 or null, got {max_frames!r}"
            )
        self.max_frames = max_frames
        if isinstance(frame_stride, bool) or not isinstance(frame_stride, int) or frame_stride < 1:
            raise ValueError(
                f"dataset.frame_stride must be a positive integer, got {frame_stride!r}"
            )
        self.frame_stride = frame_stride
        self.val_fraction = val_fraction
        self.world = dict(world or {})
        self.cache_dir = cache_dir
        self.precompute = bool(precompute_flow)
        self.offsets = check_offsets(offsets)
        self.scene = SceneConfig(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in (scene or {}).items()}
        )
        self._trajectories: dict[str, dict[str, torch.Tensor]] = {}
        self._logged_quality: set[str] = set()

    def _load(self, which: str) -> dict[str, torch.Tensor]:
        """``which`` in ``{"train", "test"}`` → sequence name → poses."""
        if which in self._trajectories:
            return self._trajectories[which]
        spec = self.train_sequences if which == "train" else self.test_sequences
        trajs: dict[str, torch.Tensor] = {}
        if self.trajectory == "procedural":
            if not isinstance(spec, int) or spec <= 0:
                raise ValueError(
                    f"dataset.{which}_sequences must be a positive count (procedural trajectories)"
                )
            if self.sequence_length < 6:
                raise ValueError("dataset.sequence_length must be at least 6 frames")
            for s in range(spec):
                name = f"{which}{s:02d}"
                trajs[name] = procedural_trajectory(
                    _rng(self.scene_seed, "trajectory", name), self.sequence_length
                )
        else:
            if self.poses_dir is None:
                raise ValueError(
                    "dataset.trajectory=kitti needs dataset.poses_dir (KITTI's poses/ directory)"
                )
            root = Path(self.poses_dir).expanduser()
            if isinstance(spec, int):
                raise ValueError(
                    f"dataset.{which}_sequences must list KITTI sequences for trajectory=kitti"
                )
            for seq in map(normalize_sequence, spec):
                path = root / f"{seq}.txt"
                if not path.is_file():
                    raise FileNotFoundError(
                        f"KITTI pose file not found: {path} (dataset.poses_dir={root})"
                    )
                poses = torch.from_numpy(read_kitti_poses(path))
                trajs[seq] = poses[: self.max_frames] if self.max_frames else poses
        self._trajectories[which] = trajs
        return trajs

    def build_dataset(self, split: str) -> SyntheticDrivingDataset | RenderedDrivingDataset:
        trajs = self._load("test" if split == "test" else "train")
        frames: dict[str, tuple[int, int]] = {}
        for seq, poses in trajs.items():
            last = poses.shape[0] - 2  # the last source frame with a successor
            n_val = round(self.val_fraction * (last + 1))
            if split == "train":
                frames[seq] = (0, last - n_val)
            elif split == "val":
                if n_val:
                    frames[seq] = (last - n_val + 1, last)
            elif split == "train+val":  # every pair of both: what prepare_data computes
                frames[seq] = (0, last)
            else:
                frames[seq] = (0, poses.shape[0] - 1)
        # Every split samples the same offsets (train+val: the pairs of both, for the cache).
        common = {
            "seed": self.scene_seed + (7919 if split == "test" else 0),
            "offsets": self.offsets,
            "name": f"synthetic/{split}",
            "stride": 1 if split == "test" else self.frame_stride,
        }
        if isinstance(self.flow, EstimatedFlow):
            return RenderedDrivingDataset(
                trajs, frames, self.height, self.width,
                flow=self.flow, world=self.world, cache_dir=self.cache_dir, **common,
            )  # fmt: skip
        return SyntheticDrivingDataset(
            trajs, frames, self.height, self.width, noise_std=self.flow.noise_std,
            outlier_fraction=self.flow.outlier_fraction, scene=self.scene, **common,
        )  # fmt: skip

    # -- estimated flow: precompute, quality, pictures ---------------------------------------

    def quality_path(self, split: str) -> Path:
        ds = self.dataset(split)
        assert isinstance(ds, RenderedDrivingDataset)
        return ds.cache.root / f"quality-{split}.json"

    def prepare_data(self) -> None:
        """``flow=dis``: render and estimate every missing pair of every split into the cache
        (train and validation pairs of one trajectory in one pass, so that each frame is
        rendered once; ``dataset.num_workers`` processes when above 1), then write each split's
        flow quality and a picture per trajectory beside it. Lightning calls this on one process
        per node; ``flow=exact`` has nothing to prepare."""
        if not isinstance(self.flow, EstimatedFlow) or not self.precompute:
            return
        import json

        from mfg_lightning.atomic import atomic_write_text

        for part in ("train+val", "test"):
            ds = self.build_dataset(part)
            n = ds.precompute_flow(progress=True, workers=self.num_workers)
            if n:
                log.info(
                    "rendered %d frames and estimated the %s flow of %d %s pairs under %s",
                    ds.rendered_frames,
                    ds.estimator.name,
                    n,
                    part,
                    ds.cache.root,
                )
            for seq in ds.sequences():
                # (the middle pair was cached before without its picture: a run that read it)
                if not ds.picture_path(seq).exists():
                    ds.cache.store(ds.picture_path(seq), ds.picture(seq))
        for split in ("train", "val", "test"):
            path = self.quality_path(split)
            if path.exists():
                continue
            quality = self.dataset(split).quality()
            atomic_write_text(path, json.dumps(quality, indent=2) + "\n")
            if quality["nonfinite_pixels"]:
                log.warning(
                    "%d estimated flow pixels of the %s split were not finite: masked invalid",
                    quality["nonfinite_pixels"],
                    split,
                )
            log.info("flow quality (%s): %s", split, _quality_line(quality["regions"]))

    def setup(self, stage: str | None = None) -> None:
        super().setup(stage)
        if isinstance(self.flow, EstimatedFlow):
            self._log_flow_quality()

    def _log_flow_quality(self) -> None:
        """Log each built split's flow quality and pictures to the trainer's loggers (once):
        ``<split>/flow_epe/<region>`` (pixels) and ``<split>/flow_fl/<region>`` (%) at step 0,
        the picture grids as ``<split>/flow_picture/<seq>`` images."""
        import json

        trainer = self.trainer
        if trainer is None or not trainer.loggers:
            return
        for split, ds in self.datasets.items():
            path = self.quality_path(split)
            if split in self._logged_quality or not path.exists():
                continue
            self._logged_quality.add(split)
            quality = json.loads(path.read_text())
            metrics = {}
            for region, q in quality["regions"].items():
                if q["epe"] is not None:
                    metrics[f"{split}/flow_epe/{region}"] = q["epe"]
                    metrics[f"{split}/flow_fl/{region}"] = q["fl"]
            metrics[f"{split}/flow_nonfinite_pixels"] = float(quality["nonfinite_pixels"])
            for logger in trainer.loggers:
                logger.log_metrics(metrics, step=0)
            if split == "val":
                continue  # the validation tails share the training split's pictures
            for seq in ds.sequences():
                picture = ds.picture_path(seq)
                if not picture.exists():
                    continue
                grid = np.load(picture)
                for logger in trainer.loggers:
                    add_image = getattr(getattr(logger, "experiment", None), "add_image", None)
                    if add_image is not None:
                        add_image(f"{split}/flow_picture/{seq}", grid, 0, dataformats="HWC")


def _quality_line(regions: dict[str, dict[str, float | None]]) -> str:
    """``road EPE 1.23 px Fl 4.5 % · …`` for the log."""

    def one(name: str, q: dict[str, float | None]) -> str:
        if q["epe"] is None:
            return f"{name} –"
        return f"{name} EPE {q['epe']:.2f} px Fl {q['fl']:.1f} %"

    return " · ".join(one(k, v) for k, v in regions.items())


#: End-point errors at or above this many pixels get the brightest colour of the EPE panel.
PICTURE_MAX_EPE = 10.0


def flow_picture(full: dict[str, Any]) -> np.ndarray:
    """The picture grid of one rendered pair at the image size, with the renderer's panels
    (:func:`~mfg_lightning.data.render.frame_panels`: RGB, exact flow, regions, object mask)
    and two more: the estimated flow in the exact flow's colour scale and its end-point error
    against it (magma, 0 to :data:`PICTURE_MAX_EPE` px; black where the exact flow is
    unknown).

    Args:
        full: the ``"full"`` entry of :meth:`RenderedDrivingDataset.compute_pair`.

    Returns:
        ``(H', W', 3)`` uint8.
    """
    from matplotlib import colormaps

    from mfg_lightning.visualization import flow_to_rgb

    _, render = _renderer()
    valid = full["exact_valid"]
    magnitude = np.linalg.norm(full["exact_flow"], axis=2)[valid]
    max_flow = float(magnitude.max()) if magnitude.size else 1.0
    estimated = flow_to_rgb(np.moveaxis(full["flow"], 2, 0), max_flow)
    estimated[~full["flow_valid"]] = 0
    epe = np.linalg.norm(full["flow"] - full["exact_flow"], axis=2)
    error = (colormaps["magma"](np.clip(epe / PICTURE_MAX_EPE, 0, 1))[..., :3] * 255).astype(
        np.uint8
    )
    error[~(valid & full["flow_valid"])] = 0
    shown = valid & full["flow_valid"]
    mean = float(epe[shown].mean()) if shown.any() else float("nan")
    panels = render.frame_panels(
        full["frame"],
        full["exact"],
        extra=[
            ("estimated flow (same colours)", estimated),
            (f"end-point error (0-{PICTURE_MAX_EPE:g} px, mean {mean:.2f})", error),
        ],
        max_flow=max_flow,
    )
    return render.picture_grid([panels])
