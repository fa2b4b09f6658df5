"""The per-epoch trajectory evaluator: per-sample motion predictions → the trajectory metrics.

The network predicts one relative motion per sample; the published metrics compare trajectories.
:class:`TrajectoryEvaluator` collects the predictions of a validation or test epoch (across
processes under DDP), orders them by sequence and frame, forms snippets and full trajectories with
:mod:`mfg_lightning.trajectory.trajectories` and feeds them to the metrics of this package
(``docs/protocols.md``), one instance per sequence and one pooled over all of them:

* ``ate`` / ``ate_std`` / ``ate_rmse`` (:class:`~.ate.SnippetATE`): frame-by-frame snippets
  (Table 1's †) from the motions ``k → k+1``;
* ``ate_central`` / …: central-frame snippets (Table 1's *), when the split provides flows from
  each centre frame to the frames at offsets −2, −1, +1, +2 (``dataset.offsets``);
* ``rpe_trans`` / ``rpe_rot`` (+ ``_std``, ``_rmse``; :class:`~.rpe.RelativePoseError`): RPE
  with Δ = ``delta`` over the full trajectory composed from the motions ``k → k+1`` (Table 2);
* ``drift_t_err`` (%) / ``drift_r_err`` (deg / 100 m; :class:`~.drift.KittiDrift`): KITTI
  odometry drift, where a sequence is at least 100 m long;
* ``ate_traj`` / ``ate_traj_mean`` / ``ate_traj_std`` (:class:`~.ate_traj.TrajectoryATE`):
  whole-trajectory ATE of the same trajectories, not aligned (both start at the identity and the
  network predicts metric motion, as for RPE and drift).

Values are pooled over the snippets (pairs, segments, poses) of all sequences, and reported per
sequence under ``<sequence>/<name>``. A sequence with a gap (an unreadable sample skipped) is
scored run by run: no snippet, pair or segment spans the gap.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor
from torchmetrics import Metric

from mfg_lightning.core.geometry import float32_math
from mfg_lightning.metrics.ate import SnippetATE
from mfg_lightning.metrics.ate_traj import TrajectoryATE
from mfg_lightning.metrics.drift import KittiDrift
from mfg_lightning.metrics.rpe import RelativePoseError
from mfg_lightning.trajectory import trajectories

__all__ = ["EvaluationResult", "SequencePrediction", "TrajectoryEvaluator"]

#: The names reported per sequence (``<sequence>/<name>``); the pooled values report them all.
SEQUENCE_NAMES: tuple[str, ...] = (
    "ate",
    "ate_std",
    "ate_rmse",
    "ate_central",
    "ate_central_std",
    "rpe_trans",
    "rpe_rot",
    "drift_t_err",
    "drift_r_err",
    "ate_traj",
)

#: A record's key: (sequence, source frame, target frame).
_Key = tuple[str, int, int]


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
    """Metrics (plain floats, NaN where undefined) and the trajectories they were computed on.

    Attributes:
        metrics: pooled ``<name>`` and per-sequence ``<sequence>/<name>`` values.
        sequences: each sequence's longest run of consecutive frames, as trajectories.
        samples: the number of distinct samples scored (of every process under DDP).
    """

    metrics: dict[str, float] = field(default_factory=dict)
    sequences: dict[str, SequencePrediction] = field(default_factory=dict)
    samples: int = 0


class _Scores:
    """The trajectory metrics of one sequence, or pooled over several.

    Each is a torchmetrics :class:`~torchmetrics.Metric` with ``sync_on_compute=False``: it is fed
    whole sequences after :meth:`TrajectoryEvaluator.compute` gathered every process's records,
    so every process already holds everything, and a second sync would count each element once
    per process.
    """

    def __init__(self, snippet_length: int, delta: int) -> None:
        self.ate = SnippetATE(snippet_length, sync_on_compute=False)
        self.ate_central = SnippetATE(snippet_length, sync_on_compute=False)
        self.rpe = RelativePoseError(delta, sync_on_compute=False)
        self.drift = KittiDrift(sync_on_compute=False)
        self.ate_traj = TrajectoryATE("none", sync_on_compute=False)

    def values(self) -> dict[str, float]:
        """The published names → floats (NaN where undefined); ``ate_central*`` only if fed."""
        out: dict[str, float] = {}
        for metric in (self.ate, self.rpe, self.drift, self.ate_traj):
            out.update(_floats(metric))
        if self.ate_central.update_called:
            central = _floats(self.ate_central)
            out.update({k.replace("ate", "ate_central", 1): v for k, v in central.items()})
        return out


def _floats(metric: Metric) -> dict[str, float]:
    """``metric.compute()`` as floats; NaN under each of its names when it saw nothing (where
    ``compute`` would only warn that it was called before ``update``)."""
    if not metric.update_called:
        return dict.fromkeys(metric.names, float("nan"))
    return {k: float(v) for k, v in metric.compute().items()}


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
        self._records: dict[_Key, tuple[Tensor, Tensor]] = {}
        # Batches as they came, on their device: read into _records at once (one transfer).
        self._pending: list[tuple[list[str], Any, Any, Tensor, Tensor]] = []

    def __len__(self) -> int:
        """The number of distinct samples collected by this process."""
        return len(self._flushed())

    def update(
        self,
        sequences: list[str],
        frames: Tensor,
        targets: Tensor,
        pred: Tensor,
        gt: Tensor,
    ) -> None:
        """Add a batch.

        Nothing is read back from the device here: the batch is kept as it is (float64, on its
        device) and moved to the host when the records are first needed (:meth:`compute`,
        ``len``), so an evaluation on a GPU never waits for it batch by batch.

        Args:
            sequences: ``B`` sequence names.
            frames, targets: ``(B,)`` source and target frame indices.
            pred: ``(B, 4, 4)`` predicted relative poses ``T_src,tgt``.
            gt: ``(B, 4, 4)`` ground-truth relative poses.
        """
        pred = pred.detach().to(torch.float64)
        gt = gt.detach().to(torch.float64)
        frames = frames.detach() if isinstance(frames, Tensor) else list(frames)
        targets = targets.detach() if isinstance(targets, Tensor) else list(targets)
        self._pending.append((list(sequences), frames, targets, pred, gt))

    def _flushed(self) -> dict[_Key, tuple[Tensor, Tensor]]:
        """The records, after moving the pending batches to the host (in arrival order: a key
        seen twice, which DistributedSampler pads with, keeps its last prediction)."""
        for sequences, frames, targets, pred, gt in self._pending:
            pred = pred.to("cpu")
            gt = gt.to("cpu")
            frames = frames.tolist() if isinstance(frames, Tensor) else frames
            targets = targets.tolist() if isinstance(targets, Tensor) else targets
            for i, seq in enumerate(sequences):
                self._records[(str(seq), int(frames[i]), int(targets[i]))] = (pred[i], gt[i])
        self._pending.clear()
        return self._records

    def gathered(self) -> dict[_Key, tuple[Tensor, Tensor]]:
        """Every process's records under DDP (this process's otherwise); a collective call.

        The one gather of the trajectory metrics, and why it is not torchmetrics' own sync of the
        metrics' list states: those states hold per-snippet, per-pair and per-segment errors,
        which need whole sequences, but evaluation gives every sample to exactly one process and
        interleaves them (``data.base.UnpaddedDistributedSampler``: rank r gets samples r, r + W,
        …), so no process holds a whole sequence. The per-sample records must meet first, and they
        are keyed by sequence *names* (strings, which torchmetrics states cannot hold); and a
        process with no sample at all would send torchmetrics' empty float32 placeholder, which
        cannot be gathered with other processes' ``(n, 4, 4)`` float64 states. Gathering the
        records as objects expresses "every sample on exactly one process" exactly; the metrics
        then run on every process on the same whole sequences, with ``sync_on_compute=False``.
        """
        records = self._flushed()
        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
            return records
        parts: list[dict | None] = [None] * dist.get_world_size()
        dist.all_gather_object(parts, records)
        merged: dict[_Key, tuple[Tensor, Tensor]] = {}
        for part in parts:
            merged.update(part or {})
        return merged

    def compute(self) -> EvaluationResult:
        """Score everything collected since the last :meth:`reset` (by every process under DDP:
        a collective call, made by every process, which all get the same result). The metrics run
        in float64 on the host, outside any autocast."""
        with float32_math():
            return self._compute()

    def _compute(self) -> EvaluationResult:
        records = self.gathered()
        by_sequence: dict[str, dict[tuple[int, int], tuple[Tensor, Tensor]]] = {}
        for (seq, src, tgt), value in records.items():
            by_sequence.setdefault(seq, {})[(src, tgt)] = value
        result = EvaluationResult(samples=len(records))
        pooled = _Scores(self.snippet_length, self.delta)
        for seq, pairs in sorted(by_sequence.items()):
            scores = _Scores(self.snippet_length, self.delta)
            longest = self._score_runs(pairs, (scores, pooled))
            if longest is not None:
                result.sequences[seq] = longest
            self._score_central_frame(pairs, (scores, pooled))
            values = scores.values()
            result.metrics.update({f"{seq}/{k}": values[k] for k in SEQUENCE_NAMES if k in values})
        result.metrics.update(pooled.values())
        return result

    def _score_runs(
        self, pairs: dict[tuple[int, int], tuple[Tensor, Tensor]], into: tuple[_Scores, ...]
    ) -> SequencePrediction | None:
        """Feed the frame-by-frame snippets and the trajectories of each run of consecutive
        motions ``k → k+1``; return the longest run's trajectories."""
        L = self.snippet_length
        longest: SequencePrediction | None = None
        forward = sorted(src for src, tgt in pairs if tgt == src + 1)
        for run in _consecutive_runs(forward):
            pred_m = torch.stack([pairs[(k, k + 1)][0] for k in run])
            gt_m = torch.stack([pairs[(k, k + 1)][1] for k in run])
            pred_traj = trajectories.sequence_trajectory(pred_m)
            gt_traj = trajectories.sequence_trajectory(gt_m)
            if len(run) >= L - 1:
                pred_s = trajectories.snippets_from_motions(pred_m, L)
                gt_s = trajectories.snippets_from_motions(gt_m, L)
            for scores in into:
                if len(run) >= L - 1:
                    scores.ate.update(pred_s, gt_s)
                if len(run) >= self.delta:
                    scores.rpe.update(pred_traj, gt_traj)
                scores.drift.update(pred_traj, gt_traj)
                scores.ate_traj.update(pred_traj, gt_traj)
            if longest is None or len(run) + 1 > len(longest.frames):
                longest = SequencePrediction(torch.tensor([*run, run[-1] + 1]), pred_traj, gt_traj)
        return longest

    def _score_central_frame(
        self, pairs: dict[tuple[int, int], tuple[Tensor, Tensor]], into: tuple[_Scores, ...]
    ) -> None:
        """Feed the central-frame snippets: motions from each centre c to c−2, c−1, c+1, c+2."""
        half = self.snippet_length // 2
        offsets = [o for o in range(-half, half + 1) if o]
        centres = sorted({src for src, _ in pairs})
        full = [c for c in centres if all((c, c + o) in pairs for o in offsets)]
        if not full:
            return
        pred_c = torch.stack([torch.stack([pairs[(c, c + o)][0] for o in offsets]) for c in full])
        gt_c = torch.stack([torch.stack([pairs[(c, c + o)][1] for o in offsets]) for c in full])
        pred_s = trajectories.snippets_from_central_frame(pred_c)
        gt_s = trajectories.snippets_from_central_frame(gt_c)
        for scores in into:
            scores.ate_central.update(pred_s, gt_s)


def _consecutive_runs(frames: list[int]) -> list[list[int]]:
    """Split sorted frame indices into runs of consecutive integers."""
    runs: list[list[int]] = []
    for f in frames:
        if runs and f == runs[-1][-1] + 1:
            runs[-1].append(f)
        else:
            runs.append([f])
    return runs
