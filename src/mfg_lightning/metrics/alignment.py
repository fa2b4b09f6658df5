"""Aligning an estimated trajectory to the ground truth before it is scored (evo, kitti-odom-eval).

Whole-trajectory metrics of monocular methods mean little without alignment: a trajectory known
only up to scale "shrinks to a point" against metric ground truth. The modes, with ``p_k`` the
estimated and ``g_k`` the ground-truth positions (translation columns of camera-to-world poses):

* ``none``: the poses as they are (evo's default; the KITTI devkit).
* ``se3``: the rigid transform ``(R, t)`` minimising ``Σ_k ‖g_k − (R p_k + t)‖²``, applied to
  every estimated pose, ``P_k ← [R | t] · P_k`` (Umeyama 1991 without scale; ``evo_ape -a``;
  kitti-odom-eval ``--align 6dof``).
* ``sim3``: the similarity ``(s, R, t)`` minimising ``Σ_k ‖g_k − (s R p_k + t)‖²`` (Umeyama 1991;
  ``evo_ape -as``; kitti-odom-eval ``--align 7dof``): positions ``p_k ← s R p_k + t``,
  orientations ``R_k ← R R_k``.
* ``scale``: kitti-odom-eval's ``--align scale``: both trajectories are first expressed relative
  to their first frame (``P_0^-1 · P_k`` and ``Q_0^-1 · Q_k``), then the estimated positions are
  multiplied by the least-squares scale ``s = Σ_k g_k · p_k / Σ_k p_k · p_k``; no rotation.
* ``scale_7dof``: kitti-odom-eval's ``--align scale_7dof``: both relative to their first frame as
  for ``scale``, then Umeyama's similarity is fitted but only its scale ``s`` is applied to the
  estimated positions (no rotation, no translation).

* ``sim3_scale``: ``evo_ape -s`` without ``-a``: Umeyama's similarity is fitted to the positions
  as they are, and only its scale is applied, ``p_k ← s p_k`` (about the world origin); with
  ``align_origin`` the first poses are made equal after the scaling, as evo does.

``n_to_align`` fits the alignment on the first ``n`` poses only and applies it to all (evo's
``--n_to_align``; the first ``min(n, N)`` poses, as evo slices); ``se3``, ``sim3``,
``sim3_scale`` and ``scale_7dof`` need at least 3 of them. The fitted scale is reported (1 for
``none`` and ``se3``).

``align_origin`` (evo's ``--align_origin``) first moves the estimate so that its first pose is the
ground truth's, ``P_k ← Q_0 · P_0^-1 · P_k``. Position errors are then those of both trajectories
expressed relative to their first frame, which is what kitti-odom-eval always does first: its
results without ``--align`` are ``none`` with ``align_origin``. Every other mode is unchanged by it
(``scale`` and ``scale_7dof`` re-express both anyway; ``se3`` and ``sim3`` fit any rigid motion).

``project=False`` keeps the rotation blocks as written and inverts with general matrix inverses
(kitti-odom-eval's arithmetic: :func:`mfg_lightning.trajectory.trajectories.relative_poses`).

Umeyama's closed form (IEEE TPAMI 13(4), 1991, eqs. 38–42): with the centred point sets
``x̃ = p − μ_p``, ``ỹ = g − μ_g``, the cross-covariance ``Σ = (1/n) Σ_k ỹ_k x̃_kᵀ = U D Vᵀ`` and
``S = diag(1, 1, det(U) det(V))``: ``R = U S Vᵀ``, ``s = tr(D S) / σ_p²`` with
``σ_p² = (1/n) Σ_k ‖x̃_k‖²``, ``t = μ_g − s R μ_p``. Degenerate estimates (every aligned position
the same, ``σ_p² = 0``, or ``Σ p·p = 0`` for ``scale``) get ``s = 0``: any scale then gives the same
aligned points, and the error is that of predicting no motion, finite (as the snippet ATE of
:mod:`mfg_lightning.metrics.ate`).

Poses follow :mod:`mfg_lightning.core.geometry`'s conventions (camera-to-world ``T_world_cam``);
alignment acts on the world frame, from the left, and never re-derives the SE(3) helpers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from mfg_lightning.trajectory.trajectories import (
    check_sequence_pair,
    evaluation_poses,
    relative_poses,
)

__all__ = [
    "ALIGN_MODES",
    "KITTI_ODOM_EVAL_NAMES",
    "AlignMode",
    "Alignment",
    "align_trajectory",
    "check_align_options",
    "configured_align",
    "umeyama",
]

AlignMode = Literal["none", "se3", "sim3", "scale", "scale_7dof", "sim3_scale"]
#: The alignment modes, in the order the command line lists them.
ALIGN_MODES: tuple[str, ...] = ("none", "se3", "sim3", "scale", "scale_7dof", "sim3_scale")
#: kitti-odom-eval's ``--align`` name of each mode (its default, no ``--align``, is ``none`` with
#: ``align_origin``).
KITTI_ODOM_EVAL_NAMES: dict[str, str] = {
    "se3": "6dof",
    "sim3": "7dof",
    "scale": "scale",
    "scale_7dof": "scale_7dof",
}


def umeyama(
    source: Tensor, target: Tensor, with_scale: bool = True
) -> tuple[Tensor, Tensor, Tensor]:
    """The similarity (or rigid) transform taking ``source`` points closest to ``target`` points.

    Minimises ``Σ_k ‖target_k − (s R source_k + t)‖²`` in closed form (Umeyama 1991; module
    docstring). Batched over leading dimensions.

    Args:
        source: ``(..., N, 3)`` points (e.g. estimated positions, any unit), ``N >= 1``.
        target: ``(..., N, 3)`` corresponding points (e.g. ground-truth positions, metres).
        with_scale: fit ``s`` (Sim(3)); ``False`` keeps ``s = 1`` (SE(3)).

    Returns:
        ``(R, t, s)``: ``(..., 3, 3)`` rotation (det +1), ``(..., 3)`` translation in the unit of
        ``target`` and ``(...)`` scale (dimensionless; 0 when every source point is the same).
    """
    if source.shape != target.shape or source.dim() < 2 or source.shape[-1] != 3:
        raise ValueError(
            "source and target must both be points shaped (..., N, 3), got "
            f"{tuple(source.shape)} and {tuple(target.shape)}"
        )
    if source.shape[-2] < 1:
        raise ValueError("umeyama needs at least one pair of points")
    mu_x = source.mean(dim=-2)
    mu_y = target.mean(dim=-2)
    x = source - mu_x[..., None, :]
    y = target - mu_y[..., None, :]
    n = source.shape[-2]
    cov = y.transpose(-1, -2) @ x / n
    U, D, Vh = torch.linalg.svd(cov)
    sign = torch.linalg.det(U) * torch.linalg.det(Vh)
    S = torch.ones_like(D)
    S[..., 2] = torch.where(sign < 0, -1.0, 1.0).to(D)
    R = U @ (S[..., :, None] * Vh)
    if with_scale:
        var_x = x.square().sum(dim=(-1, -2)) / n
        positive = var_x > 0
        s = torch.where(
            positive, (D * S).sum(-1) / torch.where(positive, var_x, torch.ones_like(var_x)), 0.0
        )
    else:
        s = torch.ones_like(D[..., 0])
    t = mu_y - s[..., None] * (R @ mu_x[..., :, None])[..., 0]
    return R, t, s


@dataclass(frozen=True)
class Alignment:
    """An estimate aligned to its ground truth, and the transform that did it.

    Attributes:
        pred: ``(N, 4, 4)`` float64 aligned estimated poses (camera-to-world; the rotation blocks
            stay rotations, the positions carry the scale).
        target: ``(N, 4, 4)`` float64 ground truth to compare with: as given, or relative to its
            first frame for ``scale`` and ``scale_7dof``.
        rotation: ``(3, 3)`` the fitted rotation (identity for ``none``, ``scale`` and
            ``scale_7dof``).
        translation: ``(3,)`` the fitted translation (ground-truth units).
        scale: ``()`` the fitted scale (1 for ``none`` and ``se3``).
        mode: the alignment mode.
        num_aligned: how many leading poses the fit used.
    """

    pred: Tensor
    target: Tensor
    rotation: Tensor
    translation: Tensor
    scale: Tensor
    mode: str
    num_aligned: int


def configured_align(value: str | None, key: str) -> str:
    """An alignment mode read from a config, checked: ``none`` where it is unset.

    Args:
        value: the configured mode, or None.
        key: the setting's name, for the error (``predict.align``).

    Raises:
        ValueError: ``<key>='<value>': use one of …``, a mode not in :data:`ALIGN_MODES`.
    """
    align = str(value or "none")
    if align not in ALIGN_MODES:
        raise ValueError(f"{key}={align!r}: use one of {', '.join(ALIGN_MODES)}")
    return align


def check_align_options(mode: str, n_to_align: int | None) -> None:
    """Raise ``ValueError`` for an unknown mode or a non-positive ``n_to_align``."""
    if mode not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {mode!r}: use one of {', '.join(ALIGN_MODES)}")
    if n_to_align is not None and n_to_align < 1:
        raise ValueError(f"n_to_align must be a positive number of poses or None, got {n_to_align}")


def align_trajectory(
    pred: Tensor,
    target: Tensor,
    mode: str = "none",
    n_to_align: int | None = None,
    *,
    align_origin: bool = False,
    project: bool = True,
) -> Alignment:
    """Align an estimated trajectory to the ground truth (module docstring for the modes).

    Args:
        pred: ``(N, 4, 4)`` estimated camera-to-world poses, in frame order, any world frame.
        target: ``(N, 4, 4)`` ground-truth camera-to-world poses of the same frames (metres).
        mode: one of :data:`ALIGN_MODES` (module docstring).
        n_to_align: fit on the first ``min(n_to_align, N)`` poses; ``None``: all of them.
        align_origin: first put the estimate's first pose on the ground truth's (evo's
            ``--align_origin``; kitti-odom-eval's expression relative to the first frame).
        project: project the rotation blocks onto SO(3) first, as every trajectory metric does
            (:func:`mfg_lightning.trajectory.trajectories.evaluation_poses`); ``False``: as
            written, with general inverses (kitti-odom-eval).

    Returns:
        :class:`Alignment` (float64).
    """
    check_align_options(mode, n_to_align)
    check_sequence_pair(pred, target)
    if pred.shape[0] == 0:
        raise ValueError("cannot align an empty trajectory")
    P = evaluation_poses(pred, project)
    Q = evaluation_poses(target, project).to(P.device)
    n = pred.shape[0] if n_to_align is None else min(n_to_align, pred.shape[0])
    eye = torch.eye(3, dtype=P.dtype, device=P.device)
    zero = torch.zeros(3, dtype=P.dtype, device=P.device)
    one = torch.ones((), dtype=P.dtype, device=P.device)
    if mode == "sim3_scale":
        if n < 3:
            raise ValueError(f"{mode} alignment needs at least 3 poses to fit a rotation, got {n}")
        s = umeyama(P[:n, :3, 3], Q[:n, :3, 3])[2]
        P = P.clone()
        P[:, :3, 3] = s * P[:, :3, 3]
        if align_origin:  # evo scales first, then moves the first pose onto the ground truth's
            P = Q[:1] @ relative_poses(P[:1], P, project)
        return Alignment(P, Q, eye, zero, s, mode, n)
    if align_origin:
        P = Q[:1] @ relative_poses(P[:1], P, project)
    if mode == "none":
        return Alignment(P, Q, eye, zero, one, mode, n)
    if mode in ("scale", "scale_7dof"):
        P = relative_poses(P[:1], P, project)
        Q = relative_poses(Q[:1], Q, project)
    if mode == "scale":
        p, g = P[:n, :3, 3], Q[:n, :3, 3]
        num, den = (g * p).sum(), (p * p).sum()
        s = torch.where(den > 0, num / torch.where(den > 0, den, one), 0.0)
        aligned = P.clone()
        aligned[:, :3, 3] = s * P[:, :3, 3]
        return Alignment(aligned, Q, eye, zero, s, mode, n)
    if n < 3:
        # Fewer points leave the rotation about the line through them undetermined.
        raise ValueError(f"{mode} alignment needs at least 3 poses to fit a rotation, got {n}")
    R, t, s = umeyama(P[:n, :3, 3], Q[:n, :3, 3], with_scale=mode != "se3")
    aligned = P.clone()
    if mode == "scale_7dof":
        # kitti-odom-eval fits the similarity but keeps only its scale.
        aligned[:, :3, 3] = s * P[:, :3, 3]
        return Alignment(aligned, Q, eye, zero, s, mode, n)
    aligned[:, :3, :3] = R @ P[:, :3, :3]
    aligned[:, :3, 3] = s * (P[:, :3, 3] @ R.T) + t
    return Alignment(aligned, Q, R, t, s, mode, n)
