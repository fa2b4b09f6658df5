"""Forming trajectories and snippets from predicted motions and ground-truth poses.

The evaluation protocols (``docs/protocols.md``) compare *trajectories*; the network
predicts *relative motions*. This module turns the latter into the former, in the conventions of
:mod:`mfg_lightning.core.geometry`:

* a pose ``T_world_cam`` is camera-to-world (a line of a KITTI ``poses/XX.txt``);
* the relative motion ``T_k,k+1 = T_world_cam(k)^-1 · T_world_cam(k+1)`` is camera k+1 expressed
  in camera k;
* a trajectory formed from motions starts at the identity: ``T(0) = I``,
  ``T(k+1) = T(k) · T_k,k+1``.

A *snippet* is ``L`` consecutive frames (``L = 5`` in Table 1) whose poses are expressed in the
camera of its first frame, so its first pose is the identity. All functions are batched, keep the
device and dtype of their input and never re-derive geometry: they compose the helpers of
:mod:`mfg_lightning.core.geometry`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from mfg_lightning.core import geometry

__all__ = [
    "check_sequence_pair",
    "consecutive_windows",
    "evaluation_poses",
    "motions_from_poses",
    "relative_poses",
    "sequence_trajectory",
    "snippets_from_central_frame",
    "snippets_from_motions",
    "snippets_from_poses",
]


def _check_poses(x: Tensor, name: str, min_dim: int = 3) -> None:
    if x.dim() < min_dim or tuple(x.shape[-2:]) != (4, 4):
        raise ValueError(
            f"{name} must be 4×4 poses shaped (..., 4, 4) with at least {min_dim} dimensions, "
            f"got shape {tuple(x.shape)}"
        )


def check_sequence_pair(pred: Tensor, target: Tensor) -> None:
    """Refuse anything but the estimated and ground-truth poses of one sequence, both
    ``(N, 4, 4)`` (what every whole-trajectory metric compares)."""
    if pred.shape != target.shape or pred.dim() != 3 or tuple(pred.shape[-2:]) != (4, 4):
        raise ValueError(
            "pred and target must both be the poses of one sequence shaped (N, 4, 4), got "
            f"{tuple(pred.shape)} and {tuple(target.shape)}"
        )


def motions_from_poses(poses: Tensor) -> Tensor:
    """Relative motions between consecutive frames of a sequence of absolute poses.

    Args:
        poses: ``(..., N, 4, 4)`` camera-to-world poses ``T_world_cam(k)``, any world frame.

    Returns:
        ``(..., N − 1, 4, 4)`` relative motions ``T_k,k+1`` (camera k+1 in camera k), the inverse
        of :func:`sequence_trajectory`.
    """
    _check_poses(poses, "poses")
    return geometry.relative_pose(poses[..., :-1, :, :], poses[..., 1:, :, :])


def sequence_trajectory(motions: Tensor) -> Tensor:
    """The full-sequence trajectory of per-frame motions (the protocol's composition).

    Args:
        motions: ``(..., N − 1, 4, 4)`` relative motions ``T_k,k+1``, k = 0 … N − 2.

    Returns:
        ``(..., N, 4, 4)`` camera-to-world poses in the frame of the first camera
        (``T(0) = I``, ``T(k+1) = T(k) · T_k,k+1``), via
        :func:`mfg_lightning.core.geometry.trajectory_from_motions`.
    """
    _check_poses(motions, "motions")
    return geometry.trajectory_from_motions(motions)


def snippets_from_poses(poses: Tensor, snippet_length: int = 5) -> Tensor:
    """All overlapping snippets (stride 1) of a sequence of absolute poses.

    This forms the ground-truth snippets of the ATE protocol (Zhou et al. 2017) and the predicted
    ones of any method that outputs absolute poses.

    Args:
        poses: ``(N, 4, 4)`` camera-to-world poses of one sequence, any world frame.
        snippet_length: ``L``, frames per snippet.

    Returns:
        ``(N − L + 1, L, 4, 4)``: snippet ``i`` holds ``T_i,i+j = T_world_cam(i)^-1 ·
        T_world_cam(i+j)`` for j = 0 … L − 1, i.e. frames i … i+L−1 in the camera of frame i
        (its first pose is the identity). Empty along the first dimension when ``N < L``.
    """
    _check_poses(poses, "poses")
    if poses.dim() != 3:
        raise ValueError(f"poses must be (N, 4, 4), got shape {tuple(poses.shape)}")
    if snippet_length < 1:
        raise ValueError(f"snippet_length must be >= 1, got {snippet_length}")
    count = max(poses.shape[0] - snippet_length + 1, 0)
    # (count, L, 4, 4) view-free gather: window i, offset j → frame i + j.
    index = torch.arange(count, device=poses.device)[:, None] + torch.arange(
        snippet_length, device=poses.device
    )
    windows = poses[index]
    return geometry.relative_pose(windows[:, :1], windows)


def snippets_from_motions(motions: Tensor, snippet_length: int = 5) -> Tensor:
    """Frame-by-frame snippets (Table 1's †): compose consecutive predicted motions.

    Snippet ``i`` starts at the identity and composes ``T_i,i+1, …, T_i+L−2,i+L−1``
    (``docs/protocols.md``, "frame by frame").

    Args:
        motions: ``(N − 1, 4, 4)`` relative motions ``T_k,k+1`` of one sequence of N frames.
        snippet_length: ``L``, frames per snippet.

    Returns:
        ``(N − L + 1, L, 4, 4)`` poses of frames i … i+L−1 in the camera of frame i. Empty along
        the first dimension when ``N < L``.
    """
    _check_poses(motions, "motions")
    if motions.dim() != 3:
        raise ValueError(f"motions must be (N - 1, 4, 4), got shape {tuple(motions.shape)}")
    if snippet_length < 1:
        raise ValueError(f"snippet_length must be >= 1, got {snippet_length}")
    steps = snippet_length - 1
    count = max(motions.shape[0] - steps + 1, 0)
    index = torch.arange(count, device=motions.device)[:, None] + torch.arange(
        steps, device=motions.device
    )
    # (count, L − 1, 4, 4): the motions inside each snippet, composed from the identity.
    return geometry.trajectory_from_motions(motions[index])


def snippets_from_central_frame(center_to_others: Tensor) -> Tensor:
    """Central-frame snippets (Table 1's *): motions from the centre frame, re-expressed.

    For snippet ``i`` of odd length ``L = 2c + 1`` the method predicts, from the centre frame
    ``i + c``, the pose of every other frame: ``T_center,other`` = camera ``other`` expressed in
    camera ``center`` (with flow from the centre frame to frames at offsets −c … −1, +1 … +c).
    The centre's own pose is the identity; all ``L`` poses are then re-expressed relative to
    frame ``i``: ``T_i,k = T_center,i^-1 · T_center,k`` (``docs/protocols.md``).

    Args:
        center_to_others: ``(S, L − 1, 4, 4)`` for S snippets, the poses ``T_center,other`` in
            the order of offsets −c, …, −1, +1, …, +c (for L = 5: −2, −1, +1, +2).

    Returns:
        ``(S, L, 4, 4)`` poses of frames i … i+L−1 in the camera of frame i.
    """
    _check_poses(center_to_others, "center_to_others")
    if center_to_others.dim() != 4 or center_to_others.shape[1] % 2 != 0:
        raise ValueError(
            "center_to_others must be (S, L - 1, 4, 4) with an even L - 1 (odd snippet length), "
            f"got shape {tuple(center_to_others.shape)}"
        )
    half = center_to_others.shape[1] // 2
    eye = torch.eye(4, dtype=center_to_others.dtype, device=center_to_others.device)
    center = eye.expand(center_to_others.shape[0], 1, 4, 4)
    in_center = torch.cat([center_to_others[:, :half], center, center_to_others[:, half:]], dim=1)
    return geometry.relative_pose(in_center[:, :1], in_center)


def evaluation_poses(poses: Tensor, project: bool = True) -> Tensor:
    """Poses prepared for the trajectory metrics: detached, float64, rotations on SO(3).

    Metrics compute in float64 so that results do not depend on the precision the model ran in;
    the rotation blocks are projected onto SO(3)
    (:func:`mfg_lightning.core.geometry.project_to_se3`)
    because pose files are only orthonormal to ~1e-7, which the arccos of rotation angles would
    otherwise amplify into a spurious error floor (evo's angles agree with the projected ones).
    Apple's MPS has no float64, so such tensors move to the CPU.

    Args:
        poses: ``(..., 4, 4)`` approximately rigid transforms.
        project: ``False`` keeps the rotation blocks as written (kitti-odom-eval's and the KITTI
            devkit's arithmetic, with :func:`relative_poses` ``project=False``).

    Returns:
        ``(..., 4, 4)`` float64 transforms (rigid when projected), on the input's device (CPU for
        MPS input).
    """
    _check_poses(poses, "poses", min_dim=2)
    poses = poses.detach()
    if poses.device.type == "mps":
        poses = poses.cpu()
    poses = poses.to(torch.float64)
    return geometry.project_to_se3(poses) if project else poses


def relative_poses(T_world_a: Tensor, T_world_b: Tensor, project: bool = True) -> Tensor:
    """``T_world_a^-1 · T_world_b`` (``b`` in the frame of ``a``), batched.

    Args:
        T_world_a, T_world_b: ``(..., 4, 4)`` camera-to-world poses (broadcast together).
        project: ``True``: the rigid inverse ``[Rᵀ | −Rᵀt]`` of poses on SO(3)
            (:func:`mfg_lightning.core.geometry.relative_pose`); ``False``: the general matrix
            inverse, as kitti-odom-eval's ``np.linalg.inv`` on rotation blocks as written (which
            differs from the rigid one by their rounding, ~1e-7 for 6-digit files).

    Returns:
        ``(..., 4, 4)`` relative poses.
    """
    if project:
        return geometry.relative_pose(T_world_a, T_world_b)
    return torch.linalg.inv(T_world_a) @ T_world_b


def consecutive_windows(frames: Tensor, length: int) -> Tensor:
    """The starts of the windows of ``length`` rows whose frame indices are consecutive.

    Args:
        frames: ``(M,)`` integer frame indices of the rows of a matched trajectory, increasing
            (a row per matched pose; holes where the estimate has no pose).
        length: rows per window (a snippet's ``L``).

    Returns:
        ``(S,)`` int64 row indices ``i`` with ``frames[i + j] = frames[i] + j`` for every
        ``j < length``: the snippets of :func:`snippets_from_poses` that span no hole.
    """
    if frames.dim() != 1:
        raise ValueError(f"frames must be (M,), got shape {tuple(frames.shape)}")
    count = max(frames.shape[0] - length + 1, 0)
    starts = torch.arange(count, device=frames.device)
    if count == 0:
        return starts
    # Every step inside the window is +1: no hole, and no repeated frame (timestamp association
    # can match two estimated poses to one ground-truth frame).
    steps = torch.diff(frames) == 1
    ok = torch.ones(count, dtype=torch.bool, device=frames.device)
    for j in range(length - 1):
        ok &= steps[j : j + count]
    return starts[ok]
