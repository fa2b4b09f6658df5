"""Per-frame egomotion errors: the distance between a predicted and a true relative motion."""

from __future__ import annotations

from torch import Tensor

from mfg_lightning.core import geometry


def frame_errors(t_pred: Tensor, omega_pred: Tensor, pose_gt: Tensor) -> tuple[Tensor, Tensor]:
    """Translation and rotation error of each frame's predicted motion.

    Args:
        t_pred: ``(B, 3)`` predicted translation (m per frame).
        omega_pred: ``(B, 3)`` predicted rotation vector (rad per frame).
        pose_gt: ``(B, 4, 4)`` ground-truth relative pose ``T_k,k+1``.

    Returns:
        ``(trans_err, rot_err)``, ``(B,)`` each: ``‖t̃ − t‖`` in metres and the angle of
        ``R̃ᵀ R`` in radians (the RPE of a single step, Δ = 1, without composing a trajectory).
    """
    # float64: the arccos of a trace near 3 loses ~1e-3 rad in float32, as much as the errors
    # being measured.
    t_pred, omega_pred = t_pred.double(), omega_pred.double()
    pose_gt = geometry.project_to_se3(pose_gt.to(t_pred))
    t_gt = pose_gt[:, :3, 3]
    R_pred = geometry.so3_exp(omega_pred)
    trans_err = (t_pred - t_gt).norm(dim=-1)
    rot_err = geometry.rotation_angle(R_pred.transpose(-1, -2) @ pose_gt[:, :3, :3])
    return trans_err, rot_err


def constant_motion_errors(
    t_const: Tensor, omega_const: Tensor, pose_gt: Tensor
) -> tuple[Tensor, Tensor]:
    """Errors of always predicting one motion (``(3,)`` each), e.g. the training-set mean."""
    batch = pose_gt.shape[0]
    return frame_errors(
        t_const.to(pose_gt).expand(batch, 3), omega_const.to(pose_gt).expand(batch, 3), pose_gt
    )


__all__ = ["constant_motion_errors", "frame_errors"]
