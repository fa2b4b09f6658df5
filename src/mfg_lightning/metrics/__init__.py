"""Evaluation metrics, each a :class:`torchmetrics.Metric` with a functional twin.

Trajectory metrics (``../shared/docs/protocols.md``):

* :mod:`.ate`: ATE over 5-frame snippets (Zhou et al. 2017; the paper's Table 1);
* :mod:`.ate_traj`: whole-trajectory ATE after an alignment (``evo_ape``, kitti-odom-eval);
* :mod:`.rpe`: relative pose error (Sturm et al. 2012; the paper's Table 2);
* :mod:`.drift`: KITTI odometry drift (Geiger et al. 2012), optionally after an alignment.

Shared parts: :mod:`.alignment` (none / SE(3) / Sim(3) Umeyama / kitti-odom-eval scale) and
:mod:`.stats` (mean, std and RMSE, computed once for every metric).
"""

from mfg_lightning.metrics.alignment import ALIGN_MODES, Alignment, align_trajectory, umeyama
from mfg_lightning.metrics.ate import SnippetATE, snippet_ate, snippet_ate_errors
from mfg_lightning.metrics.ate_traj import TrajectoryATE, ate_traj, ate_traj_errors
from mfg_lightning.metrics.drift import (
    KittiDrift,
    kitti_drift,
    kitti_drift_by_length,
    kitti_drift_from_segments,
    kitti_segment_errors,
)
from mfg_lightning.metrics.rpe import RelativePoseError, relative_pose_error, relative_pose_errors
from mfg_lightning.metrics.stats import summary

__all__ = [
    "ALIGN_MODES",
    "Alignment",
    "KittiDrift",
    "RelativePoseError",
    "SnippetATE",
    "TrajectoryATE",
    "align_trajectory",
    "ate_traj",
    "ate_traj_errors",
    "kitti_drift",
    "kitti_drift_by_length",
    "kitti_drift_from_segments",
    "kitti_segment_errors",
    "relative_pose_error",
    "relative_pose_errors",
    "snippet_ate",
    "snippet_ate_errors",
    "summary",
    "umeyama",
]
