"""Trajectory evaluation of per-frame predictions: ATE over snippets, RPE and KITTI drift.

The network predicts one relative motion per sample; the published metrics compare trajectories.
:class:`TrajectoryEvaluator` collects the predictions of a validation or test epoch (across
processes under DDP), orders them by sequence and frame, forms snippets and full trajectories with
:mod:`mfg_lightning.trajectories` and scores them with :mod:`mfg_lightning.metrics`
(``../shared/docs/protocols.md``):

* ``ate`` / ``ate_std`` / ``ate_rmse``: frame-by-frame snippets (Table 1's †) from the motions
  ``k → k+1``;
* ``ate_central`` / …: central-frame snippets (Table 1's *), when the split provides flows from
  each centre frame to the frames at offsets −2, −1, +1, +2 (``dataset.test_offsets``);
* ``rpe_trans`` / ``rpe_rot`` (+ ``_std``, ``_rmse``): RPE with Δ = ``delta`` over the full
  trajectory composed from the motions ``k → k+1`` (Table 2);
* ``drift_t_err`` (%) / ``drift_r_err`` (deg / 100 m): KITTI odometry drift, where a sequence is
  at least 100 m long.

Values are pooled over the snippets (pairs, segments) of all sequences, and reported per sequence
under ``<sequence>/<name>``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.distributed as dist
from torch import Tensor

from mfg_lightning import trajectories
from mfg_lightning.metrics import (
    kitti_drift_from_segments,
    kitti_segment_errors,
    relative_pose_errors,
    snippet_ate_errors,
)


@dataclass
class SequencePrediction:
    """The predicted and true trajectory of one sequence (frames with consecutive motions).

    Attributes:
        frames: ``(N,)`` frame indices.
        pred: ``(N, 4, 4)`` predicted camera-to-world poses, starting at the identity.
        gt: ``(N, 4, 4)`` ground-truth poses composed from the true relative motions.
    """

    frames: Tensor
    pred: Tensor
    gt: Tensor


@dataclass
class EvaluationResult:
    """Metrics (plain floats, NaN where undefined) and the trajectories they were computed on."""

    metrics: dict[str, float] = field(default_factory=dict)
    sequences: dict[str, SequencePrediction] = field(default_factory=dict)


def _summaries(prefix: str, values: Tensor) -> dict[str, float]:
    """Mean, population std and RMSE of a 1-D tensor (NaN when empty)."""
    if values.numel() == 0:
        nan = float("nan")
        return {prefix: nan, f"{prefix}_std": nan, f"{prefix}_rmse": nan}
    v = values.double()
    return {
        prefix: float(v.mean()),
        f"{prefix}_std": float(v.std(unbiased=False)),
        f"{prefix}_rmse": float(v.square().mean().sqrt()),
    }


class TrajectoryEvaluator:
    """Collects per-sample relative-pose predictions and scores them as trajectories.

    Args:
        snippet_length: frames per ATE snippet (paper: 5).
        delta: RPE frame gap Δ (paper: 1).
    """

    def __init__(self, snippet_length: int = 5, delta: int = 1) -> None:
        if snippet_length < 2 or snippet_length % 2 == 0:
            raise ValueError(f"snippet_length must be odd and ≥ 3, got {snippet_length}")
        self.snippet_length = snippet_length
        self.delta = delta
        self.reset()

    def reset(self) -> None:
        self._records: dict[tuple[str, int, int], tuple[Tensor, Tensor]] = {}

    def __len__(self) -> int:
        return len(self._records)

    def update(
        self,
        sequences: list[str],
        frames: Tensor,
        targets: Tensor,
        pred: Tensor,
        gt: Tensor,
    ) -> None:
        """Add a batch.

        Args:
            sequences: ``B`` sequence names.
            frames, targets: ``(B,)`` source and target frame indices.
            pred: ``(B, 4, 4)`` predicted relative poses ``T_src,tgt``.
            gt: ``(B, 4, 4)`` ground-truth relative poses.
        """
        pred = pred.detach().to("cpu", torch.float64)
        gt = gt.detach().to("cpu", torch.float64)
        for i, seq in enumerate(sequences):
            # A key seen twice (DistributedSampler pads with repeats) is stored once.
            self._records[(str(seq), int(frames[i]), int(targets[i]))] = (pred[i], gt[i])

    def sync(self) -> None:
        """Gather every process's records (DDP), so every rank computes the same numbers."""
        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
            return
        gathered: list[dict | None] = [None] * dist.get_world_size()
        dist.all_gather_object(gathered, self._records)
        merged: dict[tuple[str, int, int], tuple[Tensor, Tensor]] = {}
        for part in gathered:
            merged.update(part or {})
        self._records = merged

    def _by_sequence(self) -> dict[str, dict[tuple[int, int], tuple[Tensor, Tensor]]]:
        seqs: dict[str, dict[tuple[int, int], tuple[Tensor, Tensor]]] = {}
        for (seq, src, tgt), value in self._records.items():
            seqs.setdefault(seq, {})[(src, tgt)] = value
        return dict(sorted(seqs.items()))

    def compute(self) -> EvaluationResult:
        """Score everything collected since the last :meth:`reset`."""
        result = EvaluationResult()
        pooled: dict[str, list[Tensor]] = {
            k: []
            for k in (
                "ate",
                "ate_rmse",
                "ate_central",
                "ate_central_rmse",
                "rpe_trans",
                "rpe_rot",
                "drift_t",
                "drift_r",
            )
        }
        L = self.snippet_length
        half = L // 2
        for seq, pairs in self._by_sequence().items():
            per: dict[str, Tensor] = {}
            # Frame by frame: runs of consecutive motions k → k+1.
            forward = sorted(src for src, tgt in pairs if tgt == src + 1)
            for run in _consecutive_runs(forward):
                pred_m = torch.stack([pairs[(k, k + 1)][0] for k in run])
                gt_m = torch.stack([pairs[(k, k + 1)][1] for k in run])
                if len(run) >= L - 1:
                    a, r = snippet_ate_errors(
                        trajectories.snippets_from_motions(pred_m, L),
                        trajectories.snippets_from_motions(gt_m, L),
                    )
                    _append(per, "ate", a)
                    _append(per, "ate_rmse", r)
                pred_traj = trajectories.sequence_trajectory(pred_m)
                gt_traj = trajectories.sequence_trajectory(gt_m)
                if len(run) >= self.delta:
                    t, rot = relative_pose_errors(pred_traj, gt_traj, self.delta)
                    _append(per, "rpe_trans", t)
                    _append(per, "rpe_rot", rot)
                t_seg, r_seg, _ = kitti_segment_errors(pred_traj, gt_traj)
                _append(per, "drift_t", t_seg)
                _append(per, "drift_r", r_seg)
                if seq not in result.sequences or len(run) + 1 > len(result.sequences[seq].frames):
                    frames = torch.tensor([*run, run[-1] + 1])
                    result.sequences[seq] = SequencePrediction(frames, pred_traj, gt_traj)
            # Central frame: motions from each centre c to c−2, c−1, c+1, c+2.
            offsets = [o for o in range(-half, half + 1) if o]
            centres = sorted({src for src, _ in pairs})
            full = [c for c in centres if all((c, c + o) in pairs for o in offsets)]
            if full:
                pred_c = torch.stack(
                    [torch.stack([pairs[(c, c + o)][0] for o in offsets]) for c in full]
                )
                gt_c = torch.stack(
                    [torch.stack([pairs[(c, c + o)][1] for o in offsets]) for c in full]
                )
                a, r = snippet_ate_errors(
                    trajectories.snippets_from_central_frame(pred_c),
                    trajectories.snippets_from_central_frame(gt_c),
                )
                _append(per, "ate_central", a)
                _append(per, "ate_central_rmse", r)
            for key, values in per.items():
                pooled[key].append(values)
            result.metrics.update(_sequence_metrics(seq, per))
        cat = {
            k: torch.cat(v) if v else torch.zeros(0, dtype=torch.float64) for k, v in pooled.items()
        }
        result.metrics.update(_metrics(cat))
        return result


def _append(per: dict[str, Tensor], key: str, values: Tensor) -> None:
    per[key] = torch.cat([per[key], values]) if key in per else values


def _metrics(v: dict[str, Tensor]) -> dict[str, float]:
    """Pooled values → the published names."""
    empty = torch.zeros(0, dtype=torch.float64)
    out: dict[str, float] = {}
    out.update(_summaries("ate", v.get("ate", empty)))
    rmse = v.get("ate_rmse", empty)
    out["ate_rmse"] = float(rmse.mean()) if rmse.numel() else float("nan")
    if v.get("ate_central", empty).numel():
        out.update(_summaries("ate_central", v["ate_central"]))
        out["ate_central_rmse"] = float(v["ate_central_rmse"].mean())
    out.update(_summaries("rpe_trans", v.get("rpe_trans", empty)))
    out.update(_summaries("rpe_rot", v.get("rpe_rot", empty)))
    drift = kitti_drift_from_segments(v.get("drift_t", empty), v.get("drift_r", empty))
    out["drift_t_err"] = float(drift["t_err"])
    out["drift_r_err"] = float(drift["r_err"])
    return out


def _sequence_metrics(seq: str, per: dict[str, Tensor]) -> dict[str, float]:
    m = _metrics(per)
    keep = (
        "ate",
        "ate_std",
        "ate_rmse",
        "ate_central",
        "ate_central_std",
        "rpe_trans",
        "rpe_rot",
        "drift_t_err",
        "drift_r_err",
    )
    return {f"{seq}/{k}": m[k] for k in keep if k in m}


def _consecutive_runs(frames: list[int]) -> list[list[int]]:
    """Split sorted frame indices into runs of consecutive integers."""
    runs: list[list[int]] = []
    for f in frames:
        if runs and f == runs[-1][-1] + 1:
            runs[-1].append(f)
        else:
            runs.append([f])
    return runs
