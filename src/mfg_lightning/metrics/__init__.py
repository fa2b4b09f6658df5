"""Evaluation metrics, each a :class:`torchmetrics.Metric` with a functional twin.

Trajectory metrics (``docs/protocols.md``):

* :mod:`.ate`: ATE over 5-frame snippets (Zhou et al. 2017; the paper's Table 1);
* :mod:`.ate_traj`: whole-trajectory ATE after an alignment (``evo_ape``, kitti-odom-eval);
* :mod:`.rpe`: relative pose error (Sturm et al. 2012; the paper's Table 2);
* :mod:`.drift`: KITTI odometry drift (Geiger et al. 2012), optionally after an alignment.

Shared parts: :mod:`.alignment` (none / SE(3) / Sim(3) Umeyama / kitti-odom-eval's scale and
scale_7dof) and :mod:`.stats` (mean, std and RMSE, computed once for every metric; the published
names).

:mod:`.evaluator`: :class:`TrajectoryEvaluator`, which turns the per-sample motion predictions of
a validation or test epoch into whole sequences and feeds these metrics (training, evaluation).
Per-frame errors (:mod:`.frame_errors`) and object-motion scores (:mod:`.object_motion`) are used
by the LightningModule directly.

A new metric: a module here with the per-element errors, a functional twin and a ``Metric``
whose ``names`` are the keys ``compute()`` returns; feed it from :mod:`.evaluator` to have it
logged by training and evaluation.
"""

from mfg_lightning.metrics.alignment import ALIGN_MODES, Alignment, align_trajectory, umeyama
from mfg_lightning.metrics.ate import (
    ATE_NAMES,
    SnippetATE,
    snippet_ate,
    snippet_ate_errors,
    snippet_ate_from_errors,
)
from mfg_lightning.metrics.ate_traj import (
    ATE_TRAJ_NAMES,
    TrajectoryATE,
    aligned_trajectory_metrics,
    ate_traj,
    ate_traj_errors,
)
from mfg_lightning.metrics.drift import (
    DRIFT_NAMES,
    KittiDrift,
    kitti_drift,
    kitti_drift_by_length,
    kitti_drift_from_segments,
    kitti_segment_errors,
)
from mfg_lightning.metrics.evaluator import (
    EvaluationResult,
    SequencePrediction,
    TrajectoryEvaluator,
)
from mfg_lightning.metrics.rpe import (
    RPE_NAMES,
    RelativePoseError,
    relative_pose_error,
    relative_pose_errors,
)
from mfg_lightning.metrics.stats import STATISTICS, MetricValues, statistics, summary

__all__ = [
    "ALIGN_MODES",
    "ATE_NAMES",
    "ATE_TRAJ_NAMES",
    "DRIFT_NAMES",
    "RPE_NAMES",
    "STATISTICS",
    "Alignment",
    "EvaluationResult",
    "KittiDrift",
    "MetricValues",
    "RelativePoseError",
    "SequencePrediction",
    "SnippetATE",
    "TrajectoryATE",
    "TrajectoryEvaluator",
    "align_trajectory",
    "aligned_trajectory_metrics",
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
    "snippet_ate_from_errors",
    "statistics",
    "summary",
    "umeyama",
]
