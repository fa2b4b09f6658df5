"""Snippets and trajectories formed from motions, checked against obvious loops."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mfg_lightning.core import geometry as G
from mfg_lightning.trajectory import trajectories as T


def _random_poses(n: int, seed: int) -> torch.Tensor:
    """A random camera-to-world trajectory (float64), not starting at the identity."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.5, (n, 3))).as_matrix()
    poses[:, :3, 3] = np.cumsum(rng.normal(0, 1.0, (n, 3)), axis=0)
    return torch.from_numpy(poses)


def test_motions_and_sequence_trajectory_are_inverse() -> None:
    poses = _random_poses(12, 0)
    motions = T.motions_from_poses(poses)
    assert motions.shape == (11, 4, 4)
    for k in range(11):
        expected = np.linalg.inv(poses[k].numpy()) @ poses[k + 1].numpy()
        np.testing.assert_allclose(motions[k].numpy(), expected, atol=1e-12)
    trajectory = T.sequence_trajectory(motions)
    assert trajectory.shape == (12, 4, 4)
    # The trajectory is the input re-expressed in the first camera's frame.
    expected = np.linalg.inv(poses[0].numpy()) @ poses.numpy()
    np.testing.assert_allclose(trajectory.numpy(), expected, atol=1e-12)


def test_snippets_from_poses_match_a_loop() -> None:
    poses = _random_poses(9, 1)
    snippets = T.snippets_from_poses(poses, 5)
    assert snippets.shape == (5, 5, 4, 4)
    for i in range(5):
        first_inv = np.linalg.inv(poses[i].numpy())
        for j in range(5):
            np.testing.assert_allclose(
                snippets[i, j].numpy(), first_inv @ poses[i + j].numpy(), atol=1e-12
            )
    np.testing.assert_allclose(snippets[:, 0].numpy(), np.tile(np.eye(4), (5, 1, 1)), atol=1e-12)


def test_frame_by_frame_snippets_compose_from_the_identity() -> None:
    poses = _random_poses(10, 2)
    motions = T.motions_from_poses(poses)
    snippets = T.snippets_from_motions(motions, 5)
    assert snippets.shape == (6, 5, 4, 4)
    for i in range(6):
        pose = np.eye(4)
        np.testing.assert_allclose(snippets[i, 0].numpy(), pose, atol=0)
        for j in range(1, 5):
            pose = pose @ motions[i + j - 1].numpy()
            np.testing.assert_allclose(snippets[i, j].numpy(), pose, atol=1e-12)
    # Exact motions give exactly the ground-truth snippets.
    torch.testing.assert_close(snippets, T.snippets_from_poses(poses, 5), atol=1e-12, rtol=0)


def test_central_frame_snippets_re_express_relative_to_the_first_frame() -> None:
    poses = _random_poses(11, 3)
    count = 11 - 4
    # T_center,other for offsets −2, −1, +1, +2 around centre i + 2, from the true poses.
    center_to_others = torch.stack(
        [
            torch.stack([G.relative_pose(poses[i + 2], poses[i + 2 + o]) for o in (-2, -1, 1, 2)])
            for i in range(count)
        ]
    )
    snippets = T.snippets_from_central_frame(center_to_others)
    assert snippets.shape == (count, 5, 4, 4)
    torch.testing.assert_close(snippets, T.snippets_from_poses(poses, 5), atol=1e-12, rtol=0)


def test_short_sequences_give_no_snippets_and_bad_shapes_raise() -> None:
    poses = _random_poses(4, 4)
    assert T.snippets_from_poses(poses, 5).shape == (0, 5, 4, 4)
    assert T.snippets_from_motions(T.motions_from_poses(poses), 5).shape == (0, 5, 4, 4)
    with pytest.raises(ValueError, match="poses"):
        T.snippets_from_poses(poses[:, :3], 5)
    with pytest.raises(ValueError, match="odd snippet length"):
        T.snippets_from_central_frame(torch.eye(4).repeat(2, 3, 1, 1))


def test_evaluation_poses_are_float64_detached_rigid() -> None:
    poses = _random_poses(5, 5).float().requires_grad_(True)
    out = T.evaluation_poses(poses * 1.0001)
    assert out.dtype == torch.float64 and not out.requires_grad
    R = out[:, :3, :3]
    torch.testing.assert_close(
        R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-12, rtol=0
    )


def test_consecutive_windows_skip_holes_and_repeats() -> None:
    frames = torch.tensor([0, 1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 11, 12])
    assert T.consecutive_windows(frames, 5).tolist() == [0, 1, 6]
    assert T.consecutive_windows(frames, 2).tolist() == [0, 1, 2, 3, 4, 6, 7, 8, 9, 11]
    assert T.consecutive_windows(frames[:3], 5).numel() == 0


def test_relative_poses_with_general_inverses() -> None:
    poses = T.sequence_trajectory(G.se3_exp(torch.randn(6, 6, dtype=torch.float64) * 0.3))
    rigid = T.relative_poses(poses[:-1], poses[1:])
    torch.testing.assert_close(T.relative_poses(poses[:-1], poses[1:], project=False), rigid)
    # Off SO(3) (a rounded file) the general inverse is the matrix inverse, not the transpose.
    rounded = torch.round(poses * 1e3) / 1e3
    general = T.relative_poses(rounded[1:2], rounded, project=False)
    torch.testing.assert_close(general[1], torch.eye(4, dtype=torch.float64))
    assert not torch.allclose(T.relative_poses(rounded[1:2], rounded)[1], general[1], atol=1e-9)
    assert torch.equal(T.evaluation_poses(rounded, project=False), rounded)
