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

import numpy as np
import torch

from mfg_lightning import geometry
from mfg_lightning.data.base import MFGDataModule, MotionDataset
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


class SyntheticDrivingDataset(MotionDataset):
    """Samples along given trajectories; sample ``i`` is generated from ``(seed, sequence, frame)``.

    Args:
        trajectories: sequence name → ``(N, 4, 4)`` float64 ``T_world_cam`` poses.
        frames: sequence name → ``(first, last)`` range of source frames to use (inclusive).
        height, width: output resolution.
        seed: seed of the scene content.
        offsets: target frame offsets from each source frame (``[1]``: consecutive frames;
            ``[-2, -1, 1, 2]``: the central-frame snippets).
        noise_std, outlier_fraction: flow corruption (pixels, fraction).
        scene: ranges of the procedural scene.
        name: dataset name used in sample ids.
    """

    def __init__(
        self,
        trajectories: dict[str, torch.Tensor],
        frames: dict[str, tuple[int, int]],
        height: int,
        width: int,
        seed: int = 0,
        offsets: Sequence[int] = (1,),
        noise_std: float = 0.3,
        outlier_fraction: float = 0.01,
        scene: SceneConfig | None = None,
        name: str = "synthetic",
    ) -> None:
        self.height, self.width, self.seed, self.name = height, width, seed, name
        self.noise_std, self.outlier_fraction = noise_std, outlier_fraction
        self.scene = scene or SceneConfig()
        self.trajectories = trajectories
        self.intrinsics = kitti_like_intrinsics(height, width)
        index: list[tuple[str, int, int]] = []
        for seq, (first, last) in frames.items():
            n = trajectories[seq].shape[0]
            for k in range(first, last + 1):
                for off in offsets:
                    if 0 <= k + off < n:
                        index.append((seq, k, k + off))
        self.index = index

    def __len__(self) -> int:
        return len(self.index)

    def _pose(self, seq: str, src: int, tgt: int) -> torch.Tensor:
        traj = self.trajectories[seq]
        return geometry.relative_pose(traj[src], traj[tgt])

    def relative_poses(self) -> torch.Tensor:
        if not self.index:
            return torch.zeros(0, 4, 4, dtype=torch.float64)
        return torch.stack([self._pose(s, a, b) for s, a, b in self.index])

    def sequences(self) -> dict[str, list[int]]:
        groups: dict[str, list[int]] = {}
        for i, (seq, _, _) in enumerate(self.index):
            groups.setdefault(seq, []).append(i)
        return groups

    def __getitem__(self, i: int) -> dict:
        if not 0 <= i < len(self.index):
            raise IndexError(f"{self.name}: sample {i} out of range (0 … {len(self.index) - 1})")
        seq, src, tgt = self.index[i]
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
        sample.update(
            pose=pose.float(),
            intrinsics=self.intrinsics.float(),
            sequence=seq,
            frame=src,
            target=tgt,
            sample_id=f"{self.name}/{seq}/{src:06d}->{tgt:06d}",
        )
        return sample


class SyntheticDataModule(MFGDataModule):
    """The default dataset: procedural driving or real KITTI trajectories, no download.

    Splits: ``train`` and ``test`` are disjoint sets of trajectories; ``val`` is the last
    ``val_fraction`` of every training trajectory (held out from training).

    Args:
        trajectory: ``"procedural"`` or ``"kitti"``.
        poses_dir: directory of KITTI ``XX.txt`` pose files (``trajectory=kitti``).
        train_sequences, test_sequences: procedural: how many trajectories; kitti: lists of
            sequence names (paper split: train 00–08, test 09, 10).
        sequence_length: frames per procedural trajectory.
        max_frames: use at most this many frames of each KITTI sequence (None: all).
        val_fraction: tail of each training trajectory used for validation.
        noise_std, outlier_fraction: flow corruption.
        test_offsets: target offsets of test samples (``[1]``, or ``[-2, -1, 1, 2]`` for the
            central-frame ATE mode).
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
        noise_std: float = 0.3,
        outlier_fraction: float = 0.01,
        test_offsets: Sequence[int] = (1,),
        scene: dict | None = None,
        scene_seed: int | None = None,
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
        if noise_std < 0 or not 0.0 <= outlier_fraction <= 1.0:
            raise ValueError("dataset.noise_std must be ≥ 0 and dataset.outlier_fraction in [0, 1]")
        self.trajectory = trajectory
        self.poses_dir = poses_dir
        self.train_sequences = train_sequences
        self.test_sequences = test_sequences
        self.sequence_length = sequence_length
        self.max_frames = max_frames
        self.val_fraction = val_fraction
        self.noise_std, self.outlier_fraction = noise_std, outlier_fraction
        self.test_offsets = tuple(test_offsets)
        self.scene = SceneConfig(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in (scene or {}).items()}
        )
        self._trajectories: dict[str, dict[str, torch.Tensor]] = {}

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
            for seq in spec:
                seq = f"{int(seq):02d}" if str(seq).isdigit() else str(seq)
                path = root / f"{seq}.txt"
                if not path.is_file():
                    raise FileNotFoundError(
                        f"KITTI pose file not found: {path} (dataset.poses_dir={root})"
                    )
                poses = torch.from_numpy(read_kitti_poses(path))
                trajs[seq] = poses[: self.max_frames] if self.max_frames else poses
        self._trajectories[which] = trajs
        return trajs

    def build_dataset(self, split: str) -> SyntheticDrivingDataset:
        trajs = self._load("test" if split == "test" else "train")
        frames: dict[str, tuple[int, int]] = {}
        offsets: tuple[int, ...] = (1,)
        for seq, poses in trajs.items():
            last = poses.shape[0] - 2  # the last source frame with a successor
            n_val = round(self.val_fraction * (last + 1))
            if split == "train":
                frames[seq] = (0, last - n_val)
            elif split == "val":
                if n_val:
                    frames[seq] = (last - n_val + 1, last)
            else:
                frames[seq] = (0, poses.shape[0] - 1)
                offsets = self.test_offsets
        return SyntheticDrivingDataset(
            trajs,
            frames,
            self.height,
            self.width,
            seed=self.scene_seed + {"train": 0, "val": 0, "test": 7919}[split],
            offsets=offsets,
            noise_std=self.noise_std,
            outlier_fraction=self.outlier_fraction,
            scene=self.scene,
            name=f"synthetic/{split}",
        )
