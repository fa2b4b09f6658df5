"""geometry.project_to_se3 against scipy's polar decomposition (the nearest orthogonal matrix)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.linalg import polar
from scipy.spatial.transform import Rotation

from mfg_lightning.core import geometry as G


def _poses(rotations: np.ndarray, translations: np.ndarray) -> torch.Tensor:
    T = np.tile(np.eye(4), (len(rotations), 1, 1))
    T[:, :3, :3] = rotations
    T[:, :3, 3] = translations
    return torch.from_numpy(T)


def test_exact_rigid_transforms_are_unchanged() -> None:
    rng = np.random.default_rng(0)
    T = _poses(Rotation.random(50, random_state=1).as_matrix(), rng.normal(size=(50, 3)))
    np.testing.assert_allclose(G.project_to_se3(T).numpy(), T.numpy(), atol=1e-14)


def test_perturbed_rotations_go_to_the_polar_factor() -> None:
    rng = np.random.default_rng(2)
    R = Rotation.random(40, random_state=3).as_matrix() + 1e-3 * rng.normal(size=(40, 3, 3))
    t = rng.normal(size=(40, 3))
    T = _poses(R, t)
    T[:, 3, :3] = 0.5  # a damaged bottom row is reset too
    out = G.project_to_se3(T).numpy()
    for i in range(40):
        # For det > 0 the orthogonal polar factor is the closest rotation (Frobenius norm).
        np.testing.assert_allclose(out[i, :3, :3], polar(R[i])[0], atol=1e-12)
    np.testing.assert_allclose(out[:, :3, 3], t, atol=0)
    np.testing.assert_allclose(out[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (40, 1)), atol=0)


def test_result_is_a_proper_rotation_even_for_reflections_and_singular_blocks() -> None:
    reflection = np.diag([1.0, 1.0, -1.0])
    singular = np.zeros((3, 3))
    rotated_reflection = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix() @ reflection
    T = _poses(np.stack([reflection, singular, rotated_reflection]), np.zeros((3, 3)))
    R = G.project_to_se3(T)[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(3, dtype=torch.float64))


def test_batched_leading_dimensions_and_float32() -> None:
    R = torch.from_numpy(Rotation.random(6, random_state=4).as_matrix()).float()
    T = torch.eye(4).repeat(2, 3, 1, 1)
    T[..., :3, :3] = R.reshape(2, 3, 3, 3) * 1.001
    out = G.project_to_se3(T)
    assert out.shape == (2, 3, 4, 4) and out.dtype == torch.float32
    torch.testing.assert_close(out[..., :3, :3], R.reshape(2, 3, 3, 3), atol=1e-5, rtol=0)
