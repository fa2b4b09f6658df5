"""Tiny KITTI odometry and Virtual KITTI trees, written on the fly in the published layouts.

Each builder writes a few small frames with the real encodings (16-bit PNG flow and depth,
text pose files) and returns the ground truth it encoded, so tests compare what the loaders
decode with what was written:

* :func:`make_vkitti` — Virtual KITTI 1.3.1 (``version=1``) or 2.0.3 (``version=2``). Every
  frame's depth is a smooth random surface with a far-plane sky band on top; the flow is the
  exact rigid flow of the camera motion (:func:`mfg_lightning.core.geometry.reprojection_flow`) plus
  a known extra displacement inside a "moving car" box. Part of the sky is marked invalid
  (``B == 0``) and part carries a bogus *valid* flow, which must still never become an object.
* :func:`make_kitti` — KITTI odometry: textured images in which frame ``k`` is the texture shifted
  by ``k · shift`` pixels (so the true flow ``t → t + 1`` is ``+shift`` everywhere and DIS can
  find it), ``calib.txt`` with distinct P0–P3, and KITTI's real poses from the shared data
  (``conftest.KITTI_POSES``, under ``MFG_SHARED_DIR``): without them a test that asks for real
  poses skips, naming where it looked, and any other gets a synthetic drive with a warning.

:func:`png_header_only` and :func:`npy_header_only` write files whose header claims a size their
data does not have (a corrupt download, or a file meant to exhaust memory).
"""

from __future__ import annotations

import io
import struct
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from mfg_lightning.core import geometry
from mfg_lightning.flow import io as flow_io

VKITTI1_K = np.array([725.0, 725.0, 620.5, 187.0])


def texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A multi-scale random texture ``(H, W)`` uint8 (structure at every scale for DIS)."""
    img = np.zeros((height, width), np.float32)
    for sigma, amp in ((1.0, 0.3), (3.0, 0.4), (8.0, 0.5)):
        noise = cv2.GaussianBlur(
            rng.standard_normal((height, width)).astype(np.float32), (0, 0), sigma
        )
        img += amp * noise / (noise.std() + 1e-6)
    img = (img - img.min()) / (img.max() - img.min() + 1e-6)
    return (img * 255).astype(np.uint8)


def _pose(yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = geometry.so3_exp(torch.tensor([0.0, yaw, 0.0], dtype=torch.float64)).numpy()
    T[:3, 3] = t
    return T


def synthetic_drive(n_frames: int, speed: float = 0.8, yaw_rate: float = 0.01) -> np.ndarray:
    """``(N, 4, 4)`` camera-to-world poses of a car driving forward (+z) while turning."""
    return np.stack(
        [_pose(yaw_rate * k, (0.05 * k, 0.01 * np.sin(k), speed * k)) for k in range(n_frames)]
    )


def _fmt(values: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in values)


# --------------------------------------------------------------------------------------------
# Virtual KITTI
# --------------------------------------------------------------------------------------------


@dataclass
class FakeVkitti:
    """What :func:`make_vkitti` wrote, per world."""

    root: Path
    version: int
    height: int
    width: int
    T_world_cam: dict[str, np.ndarray] = field(default_factory=dict)  # (N, 4, 4)
    intrinsics: dict[str, np.ndarray] = field(default_factory=dict)  # (4,) native
    depth: dict[str, np.ndarray] = field(default_factory=dict)  # (N, H, W) metres (far: 655.35)
    flow: dict[str, np.ndarray] = field(default_factory=dict)  # (N-1, H, W, 2)
    valid: dict[str, np.ndarray] = field(default_factory=dict)  # (N-1, H, W)
    moving: dict[str, np.ndarray] = field(default_factory=dict)  # (N-1, H, W) true object pixels
    object_shift: tuple[float, float] = (0.0, 0.0)
    sky_rows: int = 0

    def file(self, kind: str, world: str, frame: int, variation: str = "clone") -> Path:
        if self.version == 1:
            sub = {"rgb": "rgb", "depth": "depthgt", "flow": "flowgt"}[kind]
            return self.root / f"vkitti_1.3.1_{sub}" / world / variation / f"{frame:05d}.png"
        scene = f"Scene{int(world):02d}"
        sub, folder, prefix, ext = {
            "rgb": ("rgb", "rgb", "rgb_", "jpg"),
            "depth": ("depth", "depth", "depth_", "png"),
            "flow": ("forwardFlow", "forwardFlow", "flow_", "png"),
        }[kind]
        return (
            self.root / f"vkitti_2.0.3_{sub}" / scene / variation / "frames" / folder / "Camera_0"
            / f"{prefix}{frame:05d}.{ext}"
        )  # fmt: skip

    def extrinsics_file(self, world: str, variation: str = "clone") -> Path:
        if self.version == 1:
            return self.root / "vkitti_1.3.1_extrinsicsgt" / f"{world}_{variation}.txt"
        return (
            self.root
            / "vkitti_2.0.3_textgt"
            / f"Scene{int(world):02d}"
            / variation
            / "extrinsic.txt"
        )


def make_vkitti(
    root: Path,
    version: int = 1,
    worlds: tuple[str, ...] = ("0001", "0002", "0006", "0018", "0020"),
    n_frames: int = 6,
    height: int = 64,
    width: int = 200,
    variation: str = "clone",
    object_shift: tuple[float, float] = (4.0, -1.0),
    seed: int = 0,
) -> FakeVkitti:
    """Write a tiny Virtual KITTI tree (all of ``worlds``, ``n_frames`` each) under ``root``.

    The 1.3.1 intrinsics are fixed by the format (fx = fy = 725, cx = 620.5, cy = 187, meant
    for 1242×375); on these small images they still define an exact camera, just an off-centre
    one. 2.0.3 writes its own ``intrinsic.txt`` (a centred camera) for both cameras, and
    extrinsics for a second camera (Camera_1) that the loader must ignore.
    """
    rng = np.random.default_rng(seed)
    fake = FakeVkitti(root, version, height, width, object_shift=object_shift, sky_rows=height // 6)
    K = (
        VKITTI1_K
        if version == 1
        else np.array([0.8 * width, 0.8 * width, width / 2 - 0.5, height / 2 - 0.5])
    )
    sky = fake.sky_rows
    for w_i, world in enumerate(worlds):
        T = synthetic_drive(n_frames, speed=0.6 + 0.1 * w_i)
        fake.T_world_cam[world] = T
        fake.intrinsics[world] = K
        depths, flows, valids, movings = [], [], [], []
        for k in range(n_frames):
            # A smooth random surface 4–40 m away, with a far-plane sky band on top.
            base = cv2.resize(rng.uniform(4.0, 40.0, (4, 8)).astype(np.float32), (width, height))
            depth = np.round(base.astype(np.float64) * 100) / 100  # what 1 cm steps can hold
            depth[:sky] = flow_io.VKITTI_FAR_PLANE_M
            depths.append(depth)
            flow_io.write_vkitti_depth(fake.file("depth", world, k), depth)
            rgb = np.stack([texture(rng, height, width)] * 3, axis=2)
            path = fake.file("rgb", world, k)
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), rgb)
            if k == n_frames - 1:
                if version == 1:  # 1.3.1 ships a flow file for the last frame too (unused)
                    flow_io.write_vkitti_flow_png(
                        fake.file("flow", world, k), np.zeros((height, width, 2))
                    )
                continue
            rel = geometry.relative_pose(torch.from_numpy(T[k]), torch.from_numpy(T[k + 1]))
            rigid = (
                geometry.reprojection_flow(
                    torch.from_numpy(depth)[None], rel[None], torch.from_numpy(K)[None]
                )[0]
                .permute(1, 2, 0)
                .numpy()
            )
            flow = rigid.copy()
            moving = np.zeros((height, width), bool)
            r0, c0 = height // 2, width // 3 + 10 * w_i
            moving[r0 : r0 + height // 4, c0 : c0 + width // 5] = True
            flow[moving] += np.array(object_shift)
            valid = np.ones((height, width), bool)
            valid[:sky, : width // 2] = False  # invalid sky (B == 0)
            flow[:sky, width // 2 :] = np.array([25.0, -7.0])  # bogus but "valid" sky flow
            flow_io.write_vkitti_flow_png(fake.file("flow", world, k), flow, valid)
            flows.append(np.where(valid[..., None], flow, 0.0))
            valids.append(valid)
            movings.append(moving)
        fake.depth[world] = np.stack(depths)
        fake.flow[world] = np.stack(flows)
        fake.valid[world] = np.stack(valids)
        fake.moving[world] = np.stack(movings)
        _write_vkitti_text(fake, world, variation, T, K)
    return fake


def _write_vkitti_text(
    fake: FakeVkitti, world: str, variation: str, T: np.ndarray, K: np.ndarray
) -> None:
    path = fake.extrinsics_file(world, variation)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fake.version == 1:
        header = "frame " + " ".join(f"r{i},{j}" for i in range(1, 5) for j in range(1, 5))
        lines = [header] + [f"{k} {_fmt(np.linalg.inv(T[k]).ravel())}" for k in range(len(T))]
        path.write_text("\n".join(lines) + "\n")
        return
    right = np.eye(4)
    right[0, 3] = 0.532725  # Camera_1 sits to the right; the loader must read Camera_0 only
    lines = ["frame cameraID " + " ".join(f"r{i},{j}" for i in range(1, 5) for j in range(1, 5))]
    intr = ["frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]"]
    for k in range(len(T)):
        for cam, Tc in ((0, T[k]), (1, T[k] @ right)):
            lines.append(f"{k} {cam} {_fmt(np.linalg.inv(Tc).ravel())}")
            intr.append(f"{k} {cam} {_fmt(K)}")
    path.write_text("\n".join(lines) + "\n")
    (path.parent / "intrinsic.txt").write_text("\n".join(intr) + "\n")


# --------------------------------------------------------------------------------------------
# KITTI odometry
# --------------------------------------------------------------------------------------------


@dataclass
class FakeKitti:
    """What :func:`make_kitti` wrote."""

    root: Path
    height: int
    width: int
    shift: tuple[float, float]
    intrinsics: np.ndarray  # (4,) native (fx, fy, cx, cy) of P2
    poses: dict[str, np.ndarray] = field(default_factory=dict)  # (N, 4, 4) T_world_cam
    real_poses: bool = False

    def image(self, seq: str, frame: int) -> Path:
        return self.root / "sequences" / seq / "image_2" / f"{frame:06d}.png"


def make_kitti(
    root: Path,
    sequences: tuple[str, ...] = ("00", "01", "02", "03", "04", "05", "06", "07", "08", "09", "10"),
    n_frames: int = 8,
    height: int = 64,
    width: int = 200,
    shift: tuple[float, float] = (2.0, 0.5),
    seed: int = 0,
    real_poses: bool | None = None,
) -> FakeKitti:
    """Write a tiny KITTI odometry tree under ``root`` (``n_frames`` frames per sequence).

    ``real_poses``: True, KITTI's real poses or a skip; None, real ones where the shared data
    has them, else a synthetic drive and a warning saying so; False, a synthetic drive."""
    import pytest

    from conftest import KITTI_POSES, NO_KITTI_POSES

    found = KITTI_POSES.is_dir()
    if real_poses and not found:
        pytest.skip(NO_KITTI_POSES)
    if real_poses is None and not found:
        warnings.warn(f"make_kitti: synthetic poses, {NO_KITTI_POSES}", stacklevel=2)
    use_real = found if real_poses is None else real_poses
    rng = np.random.default_rng(seed)
    K = np.array([0.9 * width, 0.9 * width, width / 2 + 3.25, height / 2 - 1.5])
    fake = FakeKitti(root, height, width, shift, K, real_poses=use_real)
    margin = 8 + int(np.ceil(max(abs(s) for s in shift) * n_frames))
    for seq in sequences:
        seq_dir = root / "sequences" / seq
        (seq_dir / "image_2").mkdir(parents=True, exist_ok=True)
        big = texture(rng, height + 2 * margin, width + 2 * margin)
        for k in range(n_frames):
            # Frame k shows the texture moved by k·shift: frame_k(x) = frame_{k+1}(x + shift).
            M = np.float32([[1, 0, -margin + k * shift[0]], [0, 1, -margin + k * shift[1]]])
            img = cv2.warpAffine(big, M, (width, height), flags=cv2.INTER_LINEAR)
            cv2.imwrite(str(fake.image(seq, k)), np.stack([img, (img // 2) + 60, img], axis=2))
        P = {}
        for cam, tx in (("P0", 0.0), ("P1", -0.54), ("P2", 0.06), ("P3", -0.47)):
            # The other cameras differ from P2 on purpose, so reading the wrong line shows.
            off = 0.0 if cam == "P2" else 5.0
            P[cam] = np.array(
                [
                    [K[0] + off, 0, K[2] + off, tx * K[0]],
                    [0, K[1] + off, K[3], 0.0],
                    [0, 0, 1, 0.003],
                ]
            )
        lines = [f"{cam}: {_fmt(M.ravel())}" for cam, M in P.items()] + [
            f"Tr: {_fmt(np.eye(4)[:3].ravel())}"
        ]
        (seq_dir / "calib.txt").write_text("\n".join(lines) + "\n")
        (seq_dir / "times.txt").write_text("".join(f"{0.1 * k:.6e}\n" for k in range(n_frames)))
        shared = KITTI_POSES / f"{seq}.txt"
        if use_real and shared.is_file():
            with shared.open() as f:
                rows = [next(f).split() for _ in range(n_frames)]
            poses = np.tile(np.eye(4), (n_frames, 1, 1))
            poses[:, :3] = np.array(rows, np.float64).reshape(-1, 3, 4)
        else:
            poses = synthetic_drive(n_frames)
        fake.poses[seq] = poses
        (root / "poses").mkdir(exist_ok=True)
        (root / "poses" / f"{seq}.txt").write_text(
            "".join(_fmt(p[:3].ravel()) + "\n" for p in poses)
        )
    return fake


def tree_snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """``relative path → (size, mtime_ns)`` of every file under ``root`` (to prove nothing was
    written there)."""
    return {
        str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# --------------------------------------------------------------------------------------------
# Files whose header claims a size their data does not have
# --------------------------------------------------------------------------------------------


def _png_chunk(tag: bytes, payload: bytes) -> bytes:
    crc = struct.pack(">I", zlib.crc32(tag + payload))
    return struct.pack(">I", len(payload)) + tag + payload + crc


def png_header_only(width: int, height: int, depth: int = 16, channels: int = 3) -> bytes:
    """A PNG whose IHDR claims ``width × height`` (``depth`` bits, 1, 3 or 4 channels) and
    whose image data is a few zero bytes: what a corrupt or hostile file looks like."""
    colour = {1: 0, 3: 2, 4: 6}[channels]
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", ihdr)
        + _png_chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + _png_chunk(b"IEND", b"")
    )


def npy_header_only(shape: tuple[int, ...], dtype: str = "<f4", data: bytes = b"\0" * 64) -> bytes:
    """A ``.npy`` whose header claims ``shape`` and ``dtype``, followed by ``data`` only."""
    buf = io.BytesIO()
    header = {"descr": dtype, "fortran_order": False, "shape": tuple(shape)}
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + data
