"""The procedural street world that the renderer's tests share (tests/test_render.py,
tests/test_flow_visibility.py): world ``"r"`` of seed 5 along its procedural drive, and frames
of it rendered at a size."""

from __future__ import annotations

from collections.abc import Iterable

import torch

from mfg_lightning.scene import camera, render, seeding
from mfg_lightning.scene.worlds import World, WorldConfig


def street_world(frames: int, config: WorldConfig | None = None) -> World:
    """World ``"r"`` of seed 5 along ``frames`` poses of its procedural drive (``config``: its
    furnishing, the default's when None)."""
    poses = camera.procedural_trajectory(seeding.seeded_rng(5, "trajectory", "r"), frames)
    return World.generate(poses, seed=5, name="r", config=config)


def rendered_frames(
    world: World, K: torch.Tensor, keys: Iterable[int], height: int, width: int
) -> dict[int, render.RenderedFrame]:
    """Frames ``keys`` of ``world`` rendered at ``height × width`` through intrinsics ``K``
    (``(fx, fy, cx, cy)`` in pixels), by frame number."""
    return {k: render.render_frame(world, k, K, height, width) for k in keys}
