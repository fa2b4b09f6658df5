"""Relative pose error (Sturm et al. 2012, the TUM RGB-D benchmark; the paper's Table 2).

Definition (``docs/protocols.md``, "RPE"): for ground-truth poses ``Q`` and estimated
poses ``P`` of one sequence and a frame gap ``Δ``,

    E_i = (Q_i^-1 · Q_i+Δ)^-1 · (P_i^-1 · P_i+Δ),   i = 0 … N − 1 − Δ,

the translational error is ``‖translation(E_i)‖`` (pose units, metres for KITTI) and the rotational
error is the angle of ``rotation(E_i)``, ``arccos(clip((tr R − 1) / 2, −1, 1))`` in radians. Over
all ``i`` (and all sequences): mean, population standard deviation and RMSE. This equals ``evo``'s
``evo_rpe --delta Δ --delta_unit f`` with pose relations ``trans_part`` and ``angle_rad``
(cross-checked in ``tests/test_metrics_rpe.py``); for Δ > 1 add ``--all_pairs``, since evo's
default then steps the first frame by Δ instead of taking every ``i``. Rotation blocks are first
projected onto SO(3) (:func:`mfg_lightning.trajectory.trajectories.evaluation_poses`): rounding in
pose files otherwise puts a floor of ~5e-4 rad under the arccos. ``project=False`` skips that and
inverts with general matrix inverses, kitti-odom-eval's ``compute_RPE`` arithmetic (whose mean
rotational RPE on 6-digit KITTI files is ~1 % from the projected one, evo's).

The pairs are consecutive rows of the trajectories given: for a matched estimate with holes or at
another rate (``mfg-eval-poses``), consecutive matched poses, as ``evo_rpe`` pairs the poses it
associated.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from mfg_lightning.core import geometry
from mfg_lightning.metrics.stats import MetricValues, cat_state, summary
from mfg_lightning.trajectory.trajectories import (
    check_sequence_pair,
    evaluation_poses,
    relative_poses,
)

__all__ = [
    "RPE_NAMES",
    "RelativePoseError",
    "relative_error_poses",
    "relative_pose_error",
    "relative_pose_errors",
]


def _check_sequence(pred: Tensor, target: Tensor, delta: int) -> None:
    check_sequence_pair(pred, target)
    if delta < 1:
        raise ValueError(f"delta must be a positive number of frames, got {delta}")


def relative_pose_errors(
    pred: Tensor, target: Tensor, delta: int = 1, project: bool = True
) -> tuple[Tensor, Tensor]:
    """Per-pair RPE of one sequence.

    Args:
        pred: ``(N, 4, 4)`` estimated camera-to-world poses ``P_i``, in frame order.
        target: ``(N, 4, 4)`` ground-truth camera-to-world poses ``Q_i``, in frame order.
        delta: ``Δ``, the frame gap.
        project: rotation blocks onto SO(3) first (default; evo); ``False``: as written, with
            general inverses (kitti-odom-eval).

    Returns:
        ``(trans, rot)``, ``(max(N − Δ, 0),)`` float64 each: ``‖translation(E_i)‖`` in pose units
        and the rotation angle of ``E_i`` in radians.
    """
    _check_sequence(pred, target, delta)
    first = torch.arange(max(pred.shape[0] - delta, 0), device=pred.device)
    error = relative_error_poses(pred, target, first, first + delta, project)
    return error[:, :3, 3].norm(dim=-1), geometry.rotation_angle(error[:, :3, :3])


def relative_error_poses(
    pred: Tensor, target: Tensor, first: Tensor, second: Tensor, project: bool = True
) -> Tensor:
    """The RPE's error poses ``E = (Q_i^-1 · Q_j)^-1 · (P_i^-1 · P_j)`` of the pairs ``(i, j)``.

    Args:
        pred, target: ``(N, 4, 4)`` estimated and ground-truth camera-to-world poses.
        first, second: ``(K,)`` int64 rows ``i`` and ``j`` of each pair.
        project: as :func:`relative_pose_errors`.

    Returns:
        ``(K, 4, 4)`` float64 error poses (translation in pose units).
    """
    P = evaluation_poses(pred, project)
    Q = evaluation_poses(target, project).to(P.device)
    first, second = first.to(P.device), second.to(P.device)
    motion_est = relative_poses(P[first], P[second], project)
    motion_gt = relative_poses(Q[first], Q[second], project)
    return relative_poses(motion_gt, motion_est, project)


#: The published names of :func:`relative_pose_error` and :class:`RelativePoseError`.
RPE_NAMES: tuple[str, ...] = tuple(
    f"rpe_{part}{stat}" for part in ("trans", "rot") for stat in ("", "_std", "_rmse")
)


def _summary(trans: Tensor, rot: Tensor) -> MetricValues:
    """Mean, population std and RMSE of each error; NaN when there are no pairs."""
    out = MetricValues()
    for name, values in (("rpe_trans", trans), ("rpe_rot", rot)):
        stats = summary(values)
        out.update(
            {name: stats["mean"], f"{name}_std": stats["std"], f"{name}_rmse": stats["rmse"]}
        )
    return out


def relative_pose_error(pred: Tensor, target: Tensor, delta: int = 1) -> MetricValues:
    """RPE of one sequence: the functional twin of :class:`RelativePoseError`.

    Args:
        pred, target: ``(N, 4, 4)`` estimated and ground-truth camera-to-world poses, in order.
        delta: ``Δ`` in frames (the paper: 1).

    Returns:
        ``{"rpe_trans", "rpe_trans_std", "rpe_trans_rmse", "rpe_rot", "rpe_rot_std",
        "rpe_rot_rmse"}`` (:data:`RPE_NAMES`): float64 scalars, translations in pose units,
        rotations in radians; NaN when ``N <= Δ``. The names returned before the logged ones
        (``"trans"``, …) still read (:class:`~mfg_lightning.metrics.stats.MetricValues`).
    """
    return _summary(*relative_pose_errors(pred, target, delta))


class RelativePoseError(Metric):
    """Accumulated RPE over one or several sequences (Sturm et al. 2012), DDP-safe.

    Each ``update`` takes the whole (or a contiguous chunk of a) sequence; pairs never span two
    updates. To feed one long sequence in chunks, overlap consecutive chunks by ``Δ`` frames.
    Per-pair errors are stored in list states reduced by concatenation, so the result does not
    depend on how the pairs were split over updates or processes.

    Args:
        delta: ``Δ`` in frames (the paper: 1).
        kwargs: passed to :class:`torchmetrics.Metric`.

    ``compute()`` returns the six :data:`RPE_NAMES` (``rpe_trans``, ``rpe_trans_std``, …; float64
    scalars; pose units and radians).
    """

    names = RPE_NAMES
    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, delta: int = 1, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if delta < 1:
            raise ValueError(f"delta must be a positive number of frames, got {delta}")
        self.delta = delta
        self.add_state("trans_values", default=[], dist_reduce_fx="cat")
        self.add_state("rot_values", default=[], dist_reduce_fx="cat")

    def update(self, pred: Tensor, target: Tensor) -> None:
        """Add the pairs of one sequence.

        Args:
            pred: ``(N, 4, 4)`` estimated camera-to-world poses, in frame order.
            target: ``(N, 4, 4)`` ground-truth camera-to-world poses, in frame order.
        """
        trans, rot = relative_pose_errors(pred, target, self.delta)
        self.trans_values.append(trans)
        self.rot_values.append(rot)

    def compute(self) -> MetricValues:
        """The six RPE statistics over every pair seen (NaN if none)."""
        return _summary(cat_state(self.trans_values), cat_state(self.rot_values))
