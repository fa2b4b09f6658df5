"""Every error of estimated trajectories against ground truth, as ``mfg-eval-poses`` reports them:
the snippet ATE, the whole-trajectory ATE, RPE, KITTI drift, and evo's APE and RPE under any of its
pose relations, per sequence and pooled over sequences.

The definitions are those of ``docs/evaluate_poses.md``. Two parts follow evo (``evo_ape``,
``evo_rpe``, version 1.x) to the letter, since they are spelt with its flags:

* **pose relations** (``-r``) of the error pose ``E``: ``trans_part`` ``‖t(E)‖``, ``rot_part``
  ``‖R(E) − I‖_F``, ``angle_rad`` / ``angle_deg`` the angle of ``R(E)``, ``full`` ``‖E − I‖_F``
  (4 × 4), ``point_distance`` (APE: ``‖p − q‖``; RPE: ``|‖q_j − q_i‖ − ‖p_j − p_i‖|``). APE's
  ``E_k = P_k^-1 · Q_k``, RPE's ``E_ij = (Q_i^-1 · Q_j)^-1 · (P_i^-1 · P_j)``.
* **RPE pairs** (``--delta``, ``--delta_unit``, ``--all_pairs``): in frames, ``(0, Δ), (Δ, 2Δ),
  …`` (every ``(i, i + Δ)`` with ``--all_pairs``); in metres, along the path of the aligned
  estimate (the ground truth's with ``--pairs_from_reference``): the next pose once the path since
  the last one reaches Δ (with ``--all_pairs``: for every ``i`` the pose whose path distance from
  ``i`` is nearest Δ, kept within ``delta_tol · Δ``).

:class:`~mfg_lightning.trajectory.pairs.RpeOptions` holds these choices and
:func:`~mfg_lightning.trajectory.pairs.rpe_pairs` picks the pairs (numpy only, so the command line
checks its options before torch is imported).

The translation and rotation RPE (``rpe_trans``, ``rpe_rot``) use the same pairs, so with Δ = 1
(the default) they are kitti-odom-eval's ``compute_RPE`` and the paper's Table 2 RPE.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mfg_lightning.core import geometry
from mfg_lightning.core.tables import finite_or_none
from mfg_lightning.metrics.alignment import Alignment, align_trajectory
from mfg_lightning.metrics.ate import snippet_ate_errors, snippet_ate_from_errors
from mfg_lightning.metrics.ate_traj import ate_traj_errors
from mfg_lightning.metrics.drift import kitti_drift_from_segments, kitti_segment_errors
from mfg_lightning.metrics.rpe import relative_error_poses
from mfg_lightning.metrics.stats import statistics, summary
from mfg_lightning.trajectory.pairs import POSE_RELATIONS, RpeOptions, rpe_pairs
from mfg_lightning.trajectory.trajectories import (
    consecutive_windows,
    evaluation_poses,
    relative_poses,
    snippets_from_poses,
)

__all__ = [
    "POSE_RELATIONS",
    "UNITS",
    "RpeOptions",
    "SequenceErrors",
    "element_statistics",
    "evaluate_trajectory",
    "pose_relation_errors",
    "rotation_angle_atan2",
    "rpe_pairs",
    "sequence_errors",
    "summarise",
]

#: The flat metrics of :func:`summarise` → their unit.
UNITS: dict[str, str] = {
    "ate": "m",
    "ate_std": "m",
    "ate_rmse": "m",
    "ate_traj": "m",
    "ate_traj_mean": "m",
    "ate_traj_std": "m",
    "ate_traj_scale": "1",
    "rpe_trans": "m",
    "rpe_trans_std": "m",
    "rpe_trans_rmse": "m",
    "rpe_rot": "rad",
    "rpe_rot_std": "rad",
    "rpe_rot_rmse": "rad",
    "drift_t_err": "%",
    "drift_r_err": "deg/100m",
}


def pose_relation_errors(E: Tensor, relation: str) -> Tensor:
    """evo's error of each error pose ``E`` ``(K, 4, 4)`` under ``relation`` (not
    ``point_distance``, which needs the poses): ``(K,)`` float64."""
    if relation == "trans_part":
        return E[:, :3, 3].norm(dim=-1)
    if relation == "rot_part":
        eye = torch.eye(3, dtype=E.dtype, device=E.device)
        return (E[:, :3, :3] - eye).flatten(1).norm(dim=-1)
    if relation == "full":
        eye = torch.eye(4, dtype=E.dtype, device=E.device)
        return (E - eye).flatten(1).norm(dim=-1)
    angle = rotation_angle_atan2(E[:, :3, :3])
    return torch.rad2deg(angle) if relation == "angle_deg" else angle


def rotation_angle_atan2(R: Tensor) -> Tensor:
    """Angle of rotation matrices ``(..., 3, 3)`` in radians, ``atan2(sin θ, cos θ)`` with
    ``sin θ = ‖vee(R − Rᵀ)‖ / 2`` and ``cos θ = (tr R − 1) / 2``.

    evo's angle (scipy's rotation vector): accurate down to 0, where the arccos of the trace
    (:func:`mfg_lightning.core.geometry.rotation_angle`, kitti-odom-eval's) has a floor of
    ~1e-8 rad from float64 rounding. Used for evo's ``angle_rad`` / ``angle_deg`` relations.
    """
    axis = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2
    return torch.atan2(axis.norm(dim=-1) / 2, cos)


@dataclass(frozen=True)
class SequenceErrors:
    """The per-element errors of one method on one sequence, and its alignment.

    Attributes:
        snippet_ate, snippet_ate_rmse: ``(S,)`` the ATE of every snippet of matched consecutive
            frames (:func:`mfg_lightning.metrics.snippet_ate_errors`, m).
        rpe_trans, rpe_rot: ``(K,)`` RPE per pose pair (m, rad), after alignment.
        ape, rpe: ``(M,)`` and ``(K,)`` evo's APE per pose and RPE per pair under the pose
            relation of the options (unit :data:`POSE_RELATIONS`), after alignment.
        pairs: ``(K, 2)`` the rows of the matched poses each RPE compares.
        drift_t, drift_r, drift_length: ``(G,)`` KITTI segment errors (per metre; rad per metre)
            and lengths (m), after alignment.
        traj: ``(M,)`` per-pose position errors after alignment (m).
        aligned: the alignment (aligned matched trajectories and fitted transform).
        frames: ``(M,)`` the ground-truth row of every matched pose.
        reference: ``(N, 4, 4)`` the whole ground truth (float64).
    """

    snippet_ate: Tensor
    snippet_ate_rmse: Tensor
    rpe_trans: Tensor
    rpe_rot: Tensor
    ape: Tensor
    rpe: Tensor
    pairs: Tensor
    drift_t: Tensor
    drift_r: Tensor
    drift_length: Tensor
    traj: Tensor
    aligned: Alignment
    frames: Tensor
    reference: Tensor

    @property
    def num_poses(self) -> int:
        return int(self.traj.numel())


def _relation_errors(
    aligned: Alignment, options: RpeOptions, project: bool
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``(rpe_trans, rpe_rot, ape, rpe, pairs)`` of an aligned trajectory (module docstring)."""
    P, Q = aligned.pred, aligned.target
    on = (Q if options.pairs_from_reference else P)[:, :3, 3].cpu().numpy()
    first, second = (torch.from_numpy(a) for a in rpe_pairs(on, options))
    E = relative_error_poses(P, Q, first, second, project)
    relation = options.pose_relation
    if relation == "point_distance":
        ape = (P[:, :3, 3] - Q[:, :3, 3]).norm(dim=-1)
        moved = [(T[second, :3, 3] - T[first, :3, 3]).norm(dim=-1) for T in (Q, P)]
        rpe = (moved[0] - moved[1]).abs()
    else:
        ape = pose_relation_errors(relative_poses(P, Q, project), relation)
        rpe = pose_relation_errors(E, relation)
    pairs = torch.stack([first, second], dim=-1)
    return E[:, :3, 3].norm(dim=-1), geometry.rotation_angle(E[:, :3, :3]), ape, rpe, pairs


def sequence_errors(
    gt: np.ndarray,
    pred: np.ndarray,
    rpe: RpeOptions | None = None,
    snippet_length: int = 5,
    align: str = "none",
    n_to_align: int | None = None,
    *,
    frames: np.ndarray | None = None,
    align_origin: bool = False,
    project: bool = True,
) -> SequenceErrors:
    """Every per-element error of one estimated trajectory (module docstring).

    Args:
        gt: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), every frame in order.
        pred: ``(M, 4, 4)`` estimated camera-to-world poses of the matched frames, any world
            frame, in order.
        rpe: the RPE's pairs and the pose relation (default: Δ = 1 frame, ``trans_part``).
        snippet_length: frames per ATE snippet.
        align, n_to_align: alignment for the whole-trajectory ATE, APE, RPE and drift.
        frames: ``(M,)`` the ground-truth row of each estimated pose (non-decreasing); None:
            ``M == N`` and pose k is frame k.
        align_origin: put the estimate's first pose on the ground truth's first (evo's
            ``--align_origin``) before aligning.
        project: rotation blocks onto SO(3) first (default); ``False``: as written, with general
            inverses (kitti-odom-eval's arithmetic) for the ATE, RPE and drift.
    """
    rpe = rpe or RpeOptions()
    gt_t = torch.from_numpy(np.asarray(gt, dtype=np.float64))
    pred_t = torch.from_numpy(np.asarray(pred, dtype=np.float64))
    if frames is None:
        if pred_t.shape != gt_t.shape:
            raise ValueError(
                f"gt and pred must be (N, 4, 4) alike, got {gt.shape} and {pred.shape}"
            )
        rows = torch.arange(gt_t.shape[0])
    else:
        rows = torch.from_numpy(np.asarray(frames, dtype=np.int64))
    if pred_t.dim() != 3 or tuple(pred_t.shape[1:]) != (4, 4) or rows.shape != pred_t.shape[:1]:
        raise ValueError(f"pred must be (M, 4, 4) with M frames, got {tuple(pred_t.shape)}")
    Q_all = evaluation_poses(gt_t, project)
    aligned = align_trajectory(
        pred_t, Q_all[rows], align, n_to_align, align_origin=align_origin, project=project
    )
    rpe_trans, rpe_rot, ape, rpe_errors, pairs = _relation_errors(aligned, rpe, project)
    drift_t, drift_r, drift_length = kitti_segment_errors(
        aligned.pred, aligned.target, frames=rows, reference=Q_all, project=project
    )
    # The snippet ATE is not kitti-odom-eval's: its snippets always use projected rotations.
    windows = consecutive_windows(rows, snippet_length)
    P = evaluation_poses(pred_t)
    Q = Q_all[rows] if project else evaluation_poses(gt_t)[rows]
    ate, ate_rmse = snippet_ate_errors(
        snippets_from_poses(P, snippet_length)[windows],
        snippets_from_poses(Q, snippet_length)[windows],
    )
    # Positional, in the order of the fields (SequenceErrors' docstring).
    return SequenceErrors(ate, ate_rmse, rpe_trans, rpe_rot, ape, rpe_errors, pairs, drift_t,
                          drift_r, drift_length, ate_traj_errors(aligned), aligned, rows,
                          Q_all)  # fmt: skip


def _cat(errors: Sequence[SequenceErrors], name: str) -> Tensor:
    return torch.cat([getattr(e, name) for e in errors])


#: The element sets :func:`element_statistics` describes: name → (errors field, what an element
#: is, for tables).
ELEMENTS: dict[str, tuple[str, str]] = {
    "ate": ("snippet_ate", "snippets"),
    "ate_rmse": ("snippet_ate_rmse", "snippets"),
    "ate_traj": ("traj", "poses"),
    "ape": ("ape", "poses"),
    "rpe": ("rpe", "pairs"),
    "rpe_trans": ("rpe_trans", "pairs"),
    "rpe_rot": ("rpe_rot", "pairs"),
}


def element_statistics(errors: Sequence[SequenceErrors]) -> dict[str, dict[str, float | None]]:
    """evo's seven statistics (:data:`~mfg_lightning.metrics.stats.STATISTICS`) of every set of
    per-element errors, pooled over ``errors``' sequences.

    Returns:
        ``{set: {stat: value}}`` for the sets of :data:`ELEMENTS`: ``ate`` (per-snippet ATE,
        ``sqrt(Σ‖·‖²)/L``), ``ate_rmse`` (per-snippet RMSE), ``ate_traj`` (per-pose position
        error), ``ape`` and ``rpe`` (evo's, under the pose relation), ``rpe_trans`` and
        ``rpe_rot``; None where a set is empty.
    """
    return {
        name: {k: finite_or_none(v) for k, v in statistics(_cat(errors, field)).items()}
        for name, (field, _) in ELEMENTS.items()
    }


def summarise(errors: Sequence[SequenceErrors]) -> dict[str, Any]:
    """The metrics of one sequence, or pooled over several (elements of all sequences together).

    Returns:
        Flat dict: ``ate``, ``ate_std``, ``ate_rmse`` (the mean per-snippet RMSE), ``ate_traj``
        (the RMSE over poses), ``ate_traj_mean``, ``ate_traj_std``, ``ate_traj_scale`` (of one
        sequence; None pooled), ``rpe_trans``, ``rpe_trans_std``, ``rpe_trans_rmse``,
        ``rpe_rot``, ``rpe_rot_std``, ``rpe_rot_rmse``, ``drift_t_err``, ``drift_r_err`` (units
        in :data:`UNITS`; None where undefined, e.g. fewer frames than a snippet or a path
        shorter than 100 m), the counts ``num_poses``, ``num_snippets``, ``num_pairs``,
        ``num_segments``, and ``statistics``, evo's seven statistics of every element set
        (:func:`element_statistics`).
    """
    ate = snippet_ate_from_errors(_cat(errors, "snippet_ate"), _cat(errors, "snippet_ate_rmse"))
    traj = summary(_cat(errors, "traj"))
    drift = kitti_drift_from_segments(_cat(errors, "drift_t"), _cat(errors, "drift_r"))
    out: dict[str, Any] = {
        "num_poses": sum(e.num_poses for e in errors),
        "num_snippets": sum(int(e.snippet_ate.numel()) for e in errors),
        "num_pairs": sum(int(e.rpe_trans.numel()) for e in errors),
        "num_segments": sum(int(e.drift_t.numel()) for e in errors),
    }
    out.update({key: finite_or_none(v) for key, v in ate.items()})
    out["ate_traj"] = finite_or_none(traj["rmse"])
    out["ate_traj_mean"] = finite_or_none(traj["mean"])
    out["ate_traj_std"] = finite_or_none(traj["std"])
    out["ate_traj_scale"] = finite_or_none(errors[0].aligned.scale) if len(errors) == 1 else None
    for part in ("trans", "rot"):
        stats = summary(_cat(errors, f"rpe_{part}"))
        out[f"rpe_{part}"] = finite_or_none(stats["mean"])
        out[f"rpe_{part}_std"] = finite_or_none(stats["std"])
        out[f"rpe_{part}_rmse"] = finite_or_none(stats["rmse"])
    out.update({f"drift_{key}": finite_or_none(v) for key, v in drift.items()})
    out["statistics"] = element_statistics(errors)
    return out


def evaluate_trajectory(gt: np.ndarray, pred: np.ndarray, **options: Any) -> dict[str, Any]:
    """ATE over snippets, whole-trajectory ATE, RPE and KITTI drift of one estimated trajectory.

    Args:
        gt: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), every frame in order.
        pred: ``(M, 4, 4)`` estimated camera-to-world poses, any world frame, of the frames
            ``options["frames"]`` (default: the same N frames).
        options: ``rpe``, ``snippet_length``, ``align``, ``n_to_align``, ``frames``,
            ``align_origin``, ``project`` as :func:`sequence_errors` takes them (``delta``, a
            number of frames, is still taken for ``rpe=RpeOptions(delta)``).

    Returns:
        The flat dict of :func:`summarise`.
    """
    if "delta" in options:
        options["rpe"] = RpeOptions(options.pop("delta"))
    return summarise([sequence_errors(gt, pred, **options)])
