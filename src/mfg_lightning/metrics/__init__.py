"""Evaluation metrics, each a :class:`torchmetrics.Metric` with a functional twin.

Trajectory metrics (``../shared/docs/protocols.md``):

* :mod:`.ate`: ATE over 5-frame snippets (Zhou et al. 2017; the paper's Table 1);
* :mod:`.rpe`: relative pose error (Sturm et al. 2012; the paper's Table 2);
* :mod:`.drift`: KITTI odometry drift (Geiger et al. 2012).
"""

from mfg_lightning.metrics.ate import SnippetATE, snippet_ate, snippet_ate_errors
from mfg_lightning.metrics.drift import (
    KittiDrift,
    kitti_drift,
    kitti_drift_from_segments,
    kitti_segment_errors,
)
from mfg_lightning.metrics.rpe import RelativePoseError, relative_pose_error, relative_pose_errors

__all__ = [
    "KittiDrift",
    "RelativePoseError",
    "SnippetATE",
    "kitti_drift",
    "kitti_drift_from_segments",
    "kitti_segment_errors",
    "relative_pose_error",
    "relative_pose_errors",
    "snippet_ate",
    "snippet_ate_errors",
]
