"""Whole-trajectory absolute trajectory error (Sturm et al. 2012; ``evo_ape``; kitti-odom-eval).

Definition, for one sequence of ground-truth poses ``Q_k`` and estimated poses ``P_k``
(camera-to-world, the same frames in the same order):

1. align the estimate to the ground truth with one of the modes of
   :mod:`mfg_lightning.metrics.alignment` (``none``, ``se3``, ``sim3``, ``scale``), optionally
   fitted on the first ``n_to_align`` poses only;
2. the per-pose error is the distance between the positions, ``e_k = ‖g_k − p'_k‖`` (evo's pose
   relation ``translation_part``; kitti-odom-eval's ``compute_ATE``);
3. ``ate_traj`` is the RMSE ``sqrt(mean_k e_k²)``, reported with the mean and the population
   standard deviation of ``e_k`` beside it (``ate_traj_mean``, ``ate_traj_std``), and the fitted
   scale (``ate_traj_scale``).

With ``none`` the poses are compared as they are (``evo_ape`` without ``-a``); kitti-odom-eval
always expresses both trajectories relative to their first frame first, which is the same for
trajectories that start at the identity (KITTI's ground truth, and every trajectory this project
writes). Units: those of the ground-truth positions (metres for KITTI). Over several sequences (the
:class:`TrajectoryATE` metric), each sequence is aligned on its own and the statistics pool the
errors of every pose of every sequence. This is not the ATE of the paper's Table 1, which is taken
over 5-frame snippets (:mod:`mfg_lightning.metrics.ate`).

:func:`aligned_trajectory_metrics` scores whole trajectories after an alignment as
``mfg-eval-poses --align`` does: this ATE, the RPE and the KITTI drift of the aligned estimates
(``evaluate eval.align=…``, ``predict predict.align=…``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from mfg_lightning.metrics.alignment import Alignment, align_trajectory, check_align_options
from mfg_lightning.metrics.drift import kitti_drift_from_segments, kitti_segment_errors
from mfg_lightning.metrics.rpe import relative_pose_errors
from mfg_lightning.metrics.stats import cat_state, summary

__all__ = [
    "ATE_TRAJ_NAMES",
    "TrajectoryATE",
    "aligned_trajectory_metrics",
    "ate_traj",
    "ate_traj_errors",
]

#: The published names of :class:`TrajectoryATE` (:func:`ate_traj` adds ``ate_traj_scale``).
ATE_TRAJ_NAMES: tuple[str, ...] = ("ate_traj", "ate_traj_mean", "ate_traj_std")


def ate_traj_errors(aligned: Alignment) -> Tensor:
    """Per-pose position errors ``‖g_k − p'_k‖`` of an aligned trajectory.

    Args:
        aligned: the result of :func:`mfg_lightning.metrics.alignment.align_trajectory`.

    Returns:
        ``(N,)`` float64 distances in ground-truth units (metres).
    """
    return (aligned.target[:, :3, 3] - aligned.pred[:, :3, 3]).norm(dim=-1)


def _named(errors: Tensor) -> dict[str, Tensor]:
    stats = summary(errors)
    return {"ate_traj": stats["rmse"], "ate_traj_mean": stats["mean"], "ate_traj_std": stats["std"]}


def ate_traj(
    pred: Tensor, target: Tensor, align: str = "none", n_to_align: int | None = None
) -> dict[str, Tensor]:
    """Whole-trajectory ATE of one sequence: the functional twin of :class:`TrajectoryATE`.

    Args:
        pred: ``(N, 4, 4)`` estimated camera-to-world poses, any world frame, in frame order.
        target: ``(N, 4, 4)`` ground-truth camera-to-world poses of the same frames (metres).
        align: ``"none"``, ``"se3"``, ``"sim3"`` or ``"scale"``.
        n_to_align: fit the alignment on the first N poses (``None``: all).

    Returns:
        ``{"ate_traj", "ate_traj_mean", "ate_traj_std", "ate_traj_scale"}``: float64 scalars, the
        RMSE, mean and population std of the per-pose errors (metres) and the fitted scale.
    """
    aligned = align_trajectory(pred, target, align, n_to_align)
    return {**_named(ate_traj_errors(aligned)), "ate_traj_scale": aligned.scale}


class TrajectoryATE(Metric):
    """Whole-trajectory ATE accumulated over sequences, DDP-safe.

    Each ``update`` takes one whole sequence, aligned on its own (alignment needs every pose of
    it). Per-pose errors are stored in a list state reduced by concatenation, so ``compute``
    pools the errors of every pose of every sequence, whatever the order or the process.

    Args:
        align: ``"none"``, ``"se3"``, ``"sim3"`` or ``"scale"``.
        n_to_align: fit each sequence's alignment on its first N poses (``None``: all).
        kwargs: passed to :class:`torchmetrics.Metric`.

    ``compute()`` returns ``{"ate_traj", "ate_traj_mean", "ate_traj_std"}`` (float64 scalars,
    metres; NaN before any update). The fitted scale is per sequence: :func:`ate_traj`.
    """

    names = ATE_TRAJ_NAMES
    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, align: str = "none", n_to_align: int | None = None, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        check_align_options(align, n_to_align)
        self.align = align
        self.n_to_align = n_to_align
        self.add_state("errors", default=[], dist_reduce_fx="cat")

    def update(self, pred: Tensor, target: Tensor) -> None:
        """Add one sequence.

        Args:
            pred: ``(N, 4, 4)`` estimated camera-to-world poses, in frame order.
            target: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres).
        """
        aligned = align_trajectory(pred, target, self.align, self.n_to_align)
        self.errors.append(ate_traj_errors(aligned))

    def compute(self) -> dict[str, Tensor]:
        """``{"ate_traj", "ate_traj_mean", "ate_traj_std"}`` over every pose seen."""
        return _named(cat_state(self.errors))


def aligned_trajectory_metrics(
    sequences: Mapping[str, tuple[Tensor, Tensor]],
    align: str,
    delta: int = 1,
    n_to_align: int | None = None,
) -> dict[str, float]:
    """Whole-trajectory metrics of aligned estimates, per sequence and pooled.

    Each sequence's estimate is aligned on its own (:func:`align_trajectory`), then scored: this
    module's ATE, the RPE (:mod:`mfg_lightning.metrics.rpe`) and the KITTI drift
    (:mod:`mfg_lightning.metrics.drift`) of the aligned poses, the way ``mfg-eval-poses --align``
    scores files.

    Args:
        sequences: sequence → ``(pred, gt)``, ``(N, 4, 4)`` camera-to-world poses each (metres).
        align: ``"none"``, ``"se3"``, ``"sim3"``, ``"scale"`` or ``"scale_7dof"``.
        delta: the RPE frame gap.
        n_to_align: fit each alignment on the first N poses (``None``: all).

    Returns:
        Floats (NaN where undefined): pooled ``ate_traj``, ``ate_traj_mean``, ``ate_traj_std``,
        ``rpe_trans``, ``rpe_rot`` (+ ``_std``, ``_rmse``), ``drift_t_err``, ``drift_r_err``, and
        per sequence ``<seq>/ate_traj``, ``<seq>/ate_traj_scale``, ``<seq>/rpe_trans``,
        ``<seq>/rpe_rot``, ``<seq>/drift_t_err``, ``<seq>/drift_r_err`` (metres, radians, %,
        deg/100 m).
    """
    check_align_options(align, n_to_align)
    parts: dict[str, list[Tensor]] = {"traj": [], "trans": [], "rot": [], "t": [], "r": []}
    out: dict[str, float] = {}
    for seq, (pred, gt) in sequences.items():
        aligned = align_trajectory(pred, gt, align, n_to_align)
        errors = {"traj": ate_traj_errors(aligned)}
        errors["trans"], errors["rot"] = relative_pose_errors(aligned.pred, aligned.target, delta)
        errors["t"], errors["r"], _ = kitti_segment_errors(aligned.pred, aligned.target)
        for key, value in errors.items():
            parts[key].append(value.cpu())
        drift = kitti_drift_from_segments(errors["t"], errors["r"])
        out.update({
            f"{seq}/ate_traj": float(_named(errors["traj"])["ate_traj"]),
            f"{seq}/ate_traj_scale": float(aligned.scale),
            f"{seq}/rpe_trans": float(summary(errors["trans"])["mean"]),
            f"{seq}/rpe_rot": float(summary(errors["rot"])["mean"]),
            f"{seq}/drift_t_err": float(drift["t_err"]),
            f"{seq}/drift_r_err": float(drift["r_err"]),
        })  # fmt: skip
    pooled = {
        k: torch.cat(v) if v else torch.zeros(0, dtype=torch.float64) for k, v in parts.items()
    }
    out.update({k: float(v) for k, v in _named(pooled["traj"]).items()})
    for part in ("trans", "rot"):
        stats = summary(pooled[part])
        out.update({f"rpe_{part}": float(stats["mean"]), f"rpe_{part}_std": float(stats["std"]),
                    f"rpe_{part}_rmse": float(stats["rmse"])})  # fmt: skip
    drift = kitti_drift_from_segments(pooled["t"], pooled["r"])
    out.update({"drift_t_err": float(drift["t_err"]), "drift_r_err": float(drift["r_err"])})
    return out
