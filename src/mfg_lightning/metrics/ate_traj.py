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
"""

from __future__ import annotations

from typing import Any

from torch import Tensor
from torchmetrics import Metric

from mfg_lightning.metrics.alignment import Alignment, align_trajectory, check_align_options
from mfg_lightning.metrics.stats import cat_state, summary

__all__ = ["ATE_TRAJ_NAMES", "TrajectoryATE", "ate_traj", "ate_traj_errors"]

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
