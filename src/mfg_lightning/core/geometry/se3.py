"""SO(3) and SE(3): exponential and logarithm maps, relative poses, egomotion ``(t, ω)`` and back,
trajectories, and the cleaning of poses read from files (conventions:
:mod:`mfg_lightning.core.geometry`)."""

from __future__ import annotations

import torch
from torch import Tensor

from mfg_lightning.core.geometry.precision import full_precision

# --------------------------------------------------------------------------------------------
# SO(3) and SE(3)
# --------------------------------------------------------------------------------------------


def _hat(w: Tensor) -> Tensor:
    """``(..., 3)`` vector → ``(..., 3, 3)`` skew-symmetric matrix ``[w]×``."""
    zero = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero], dim=-1).reshape(
        *w.shape[:-1], 3, 3
    )


def _sinc_terms(theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``sin θ/θ``, ``(1 - cos θ)/θ²`` and ``(θ - sin θ)/θ³`` with Taylor series near 0."""
    small = theta < 1e-4
    safe = torch.where(small, torch.ones_like(theta), theta)
    t2 = theta * theta
    a = torch.where(small, 1 - t2 / 6, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(safe)) / (safe * safe))
    c = torch.where(small, 1 / 6 - t2 / 120, (safe - torch.sin(safe)) / safe**3)
    return a, b, c


@full_precision
def so3_exp(omega: Tensor) -> Tensor:
    """Rodrigues: rotation vector ``(..., 3)`` (rad) → rotation matrix ``(..., 3, 3)``."""
    theta = omega.norm(dim=-1)[..., None, None]
    a, b, _ = _sinc_terms(theta)
    W = _hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(W)
    return eye + a * W + b * (W @ W)


@full_precision
def so3_log(R: Tensor) -> Tensor:
    """Rotation matrix ``(..., 3, 3)`` → rotation vector ``(..., 3)`` (rad), angle in [0, π]."""
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = ((trace - 1) / 2).clamp(-1.0, 1.0)
    vee = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        dim=-1,
    )
    sin = 0.5 * vee.norm(dim=-1)
    theta = torch.atan2(sin, cos)
    small = theta < 1e-4
    factor = torch.where(
        small, 0.5 + theta**2 / 12, theta / (2 * torch.sin(theta).clamp_min(1e-12))
    )
    w = vee * factor[..., None]
    # Near π the antisymmetric part vanishes: read the axis from the symmetric part instead.
    # Computed for every rotation and selected with where: asking whether any is near π would
    # be a device synchronisation in every training step (the ground-truth poses pass here).
    near_pi = theta > torch.pi - 1e-3
    S = (R + R.transpose(-1, -2)) / 2 - cos[..., None, None] * torch.eye(
        3, dtype=R.dtype, device=R.device
    )
    col = S.diagonal(dim1=-2, dim2=-1).argmax(dim=-1)
    axis = torch.gather(S, -1, col[..., None, None].expand(*S.shape[:-1], 1)).squeeze(-1)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # Choose the sign consistent with the (small) antisymmetric part.
    sign = torch.where((axis * vee).sum(-1) < 0, -1.0, 1.0).to(R.dtype)
    return torch.where(near_pi[..., None], axis * (theta * sign)[..., None], w)


@full_precision
def rotation_angle(R: Tensor) -> Tensor:
    """Angle of a rotation matrix ``(..., 3, 3)`` in radians: ``arccos(clip((tr R − 1)/2))``."""
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    return torch.arccos(((trace - 1) / 2).clamp(-1.0, 1.0))


def _make_pose(R: Tensor, t: Tensor) -> Tensor:
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


@full_precision
def se3_exp(xi: Tensor) -> Tensor:
    """Twist ``(..., 6)`` = ``(v, ω)`` → pose ``(..., 4, 4)`` (the SE(3) exponential)."""
    v, w = xi[..., :3], xi[..., 3:]
    _, b, c = _sinc_terms(w.norm(dim=-1)[..., None, None])
    W = _hat(w)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    V = eye + b * W + c * (W @ W)  # the left Jacobian of SO(3)
    return _make_pose(so3_exp(w), (V @ v[..., None])[..., 0])


@full_precision
def se3_log(T: Tensor) -> Tensor:
    """Pose ``(..., 4, 4)`` → twist ``(..., 6)`` = ``(v, ω)`` (the SE(3) logarithm)."""
    w = so3_log(T[..., :3, :3])
    theta = w.norm(dim=-1)[..., None, None]
    a, b, _ = _sinc_terms(theta)
    W = _hat(w)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(W)
    # V^-1 = I - W/2 + (1 - a / (2 b)) / θ² W²  (series near 0: 1/12).
    small = theta < 1e-4
    safe = torch.where(small, torch.ones_like(theta), theta)
    coef = torch.where(small, torch.full_like(theta, 1 / 12), (1 - a / (2 * b)) / (safe * safe))
    V_inv = eye - 0.5 * W + coef * (W @ W)
    v = (V_inv @ T[..., :3, 3:4])[..., 0]
    return torch.cat([v, w], dim=-1)


@full_precision
def invert_pose(T: Tensor) -> Tensor:
    """Inverse of rigid transforms ``(..., 4, 4)`` (exact, using Rᵀ)."""
    R = T[..., :3, :3].transpose(-1, -2)
    t = -(R @ T[..., :3, 3:4])[..., 0]
    return _make_pose(R, t)


@full_precision
def relative_pose(T_world_a: Tensor, T_world_b: Tensor) -> Tensor:
    """``T_a,b = T_world_a^-1 · T_world_b``: camera b expressed in camera a. ``(..., 4, 4)``."""
    return invert_pose(T_world_a) @ T_world_b


@full_precision
def pose_to_motion(T: Tensor) -> tuple[Tensor, Tensor]:
    """Relative pose ``T_k,k+1`` ``(..., 4, 4)`` → egomotion ``(t, ω)``, ``(..., 3)`` each.

    ``t`` is the translation column (metres) and ``ω = log(R)`` (radians); the module docstring
    gives the frames.
    """
    return T[..., :3, 3], so3_log(T[..., :3, :3])


@full_precision
def motion_to_pose(t: Tensor, omega: Tensor) -> Tensor:
    """Egomotion ``(t, ω)`` ``(..., 3)`` each → relative pose ``T_k,k+1`` ``(..., 4, 4)``."""
    return _make_pose(so3_exp(omega), t)


@full_precision
def trajectory_from_motions(relative: Tensor) -> Tensor:
    """Compose relative poses into a trajectory starting at the identity.

    ``T(0) = I``, ``T(k+1) = T(k) · T_k,k+1`` (``docs/protocols.md``).

    Args:
        relative: ``(..., N, 4, 4)`` relative poses ``T_k,k+1`` for k = 0 … N−1.

    Returns:
        ``(..., N + 1, 4, 4)`` camera-to-world poses in the frame of the first camera.
    """
    eye = torch.eye(4, dtype=relative.dtype, device=relative.device)
    poses = [eye.expand(*relative.shape[:-3], 4, 4)]
    for k in range(relative.shape[-3]):
        poses.append(poses[-1] @ relative[..., k, :, :])
    return torch.stack(poses, dim=-3)


# --------------------------------------------------------------------------------------------
# Cleaning up poses read from files
# --------------------------------------------------------------------------------------------


def _det3(M: Tensor) -> Tensor:
    """Determinant of ``(..., 3, 3)`` matrices as the triple product of their rows."""
    return (torch.linalg.cross(M[..., 0, :], M[..., 1, :], dim=-1) * M[..., 2, :]).sum(-1)


@full_precision
def project_to_se3(T: Tensor) -> Tensor:
    """The nearest rigid transform: rotation block projected onto SO(3), bottom row reset.

    Pose files store rotations to about seven significant digits (KITTI writes ``%e``), so
    ``RᵀR`` misses the identity by ~1e-7. The rotation angle ``arccos((tr R − 1) / 2)`` used by RPE
    and the KITTI drift is steep near zero and turns that rounding into a spurious error of
    ~5e-4 rad between two *identical* KITTI trajectories; projecting first removes it. Exact
    rotations come back unchanged up to rounding.

    The projection is the closest rotation in the Frobenius norm, ``U diag(1, 1, det(U Vᵀ)) Vᵀ``
    from the SVD ``R = U S Vᵀ`` (the orthogonal polar factor, with a reflection turned into the
    nearest proper rotation). The translation column is kept as it is.

    Args:
        T: ``(..., 4, 4)`` approximately rigid transforms (any float dtype).

    Returns:
        ``(..., 4, 4)`` rigid transforms with ``RᵀR = I``, ``det R = +1`` and bottom row
        ``(0, 0, 0, 1)``.
    """
    U, _, Vh = torch.linalg.svd(T[..., :3, :3])
    # det(U Vᵀ) = det U · det Vᵀ = ±1, each a triple product: linalg.det and a batched matmul
    # are an order of magnitude slower on thousands of 3×3 blocks.
    det = _det3(U) * _det3(Vh)
    # where, not sign: a singular block (det 0) still has to come back as a proper rotation.
    flip = torch.where(det < 0, -torch.ones_like(det), torch.ones_like(det))
    U = torch.cat([U[..., :2], U[..., 2:] * flip[..., None, None]], dim=-1)
    return _make_pose(U @ Vh, T[..., :3, 3])
