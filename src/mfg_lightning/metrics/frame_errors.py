"""Per-frame egomotion errors: the distance between a predicted and a true relative motion, and
the per-batch mean the LightningModule keeps of them without a device synchronisation."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import MeanMetric

from mfg_lightning.core import geometry


@geometry.full_precision
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


class FiniteMean(MeanMetric):
    """A weighted mean that leaves NaN values out, with tensor ops only.

    ``torchmetrics.MeanMetric`` leaves NaN values out too, but finds them with ``nans.any()`` in
    every ``update``: a device synchronisation in every evaluation batch on a GPU. Here the NaN
    values (or NaN weights) get weight 0 and are counted in the state ``nan_count``, which the
    caller reads once, after ``compute``. Without NaN the sums are MeanMetric's, bit for bit.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(nan_strategy="disable", **kwargs)
        self.add_state("nan_count", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, value: float | Tensor, weight: float | Tensor | None = None) -> None:
        """Add ``value`` (any shape) with ``weight`` (broadcast to it; default 1)."""
        # A Python number becomes a tensor by a fill on the device, never by torch.as_tensor(x,
        # device=...), which is a synchronous host-to-device copy on a GPU (the batch size
        # given as a weight, twice per evaluation batch).
        if not isinstance(value, Tensor):
            value = torch.full((), float(value), device=self.device)
        value = value.to(self.device)
        if weight is None:
            weight = torch.ones_like(value)
        elif isinstance(weight, Tensor):
            weight = weight.to(device=self.device, dtype=value.dtype)
        else:
            weight = torch.full_like(value, float(weight))
        weight = torch.broadcast_to(weight, value.shape)
        nan = torch.isnan(value) | torch.isnan(weight)
        value = value.to(self.dtype)
        weight = weight.to(self.dtype)
        self.mean_value += torch.where(nan, 0.0, value * weight).sum()
        self.weight += torch.where(nan, 0.0, weight).sum()
        self.nan_count += nan.sum()


__all__ = ["FiniteMean", "constant_motion_errors", "frame_errors"]
