"""One evaluation stage (validation or test) of the egomotion model: every score it logs, as one
object with ``update``, ``compute`` and ``reset``.

It holds

- the per-frame means (:mod:`.frame_errors`): translation error (m) and rotation error (rad) of
  the predicted motion, the loss and the fraction of active hidden units (weighted by batch size,
  so per-sample means whatever the batches or processes), and the mean-motion baseline's errors
  when a baseline is given;
- the count of non-finite input-flow pixels that were masked;
- the object-motion scores (:class:`.object_motion.ObjectMotionScores`) of the extracted object
  motion (``object/*``) and of the plain-threshold baseline (``object_baseline/*``);
- the trajectory metrics over whole sequences (:class:`.evaluator.TrajectoryEvaluator`: ATE over
  snippets, RPE, drift, whole-trajectory ATE).

Every state is reduced across processes by :meth:`MotionEvaluation.compute`, which is a
collective: every process calls it, also one that saw no batch.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import torch
from torch import Tensor, nn
from torchmetrics import Metric, SumMetric

from mfg_lightning.core import geometry
from mfg_lightning.metrics.evaluator import EvaluationResult, TrajectoryEvaluator
from mfg_lightning.metrics.frame_errors import FiniteMean, constant_motion_errors, frame_errors
from mfg_lightning.metrics.object_motion import ObjectMotionScores
from mfg_lightning.motion.object_motion import (
    ObjectMotionConfig,
    extract_object_motion,
    threshold_baseline,
)

log = logging.getLogger(__name__)

#: The per-frame means, by logged name (``<stage>/<name>``).
MEANS = (
    "trans_err",
    "rot_err",
    "loss",
    "active_fraction",
    "baseline_trans_err",
    "baseline_rot_err",
)
#: The object-motion scores, by logged prefix (``<stage>/<method>/<score>``).
OBJECT_METHODS = ("object", "object_baseline")


class ObjectInputs(NamedTuple):
    """What object motion is extracted from and scored against, one batch.

    Attributes:
        flow: ``(B, 2, H, W)`` the masked input flow, pixels.
        v_t, v_omega: ``(B, 2, H, W)`` the predicted translational (ρ = 1 m⁻¹) and rotational
            fields, pixels.
        depth: ``(B, H, W)`` depth of the source frame, metres (0: unknown).
        valid: ``(B, H, W)`` bool, the flow's validity with its non-finite pixels cleared.
        gt_mask: ``(B, H, W)`` bool, the ground-truth independently moving pixels.
        gt_flow: ``(B, 2, H, W)`` the ground-truth object flow, pixels, or None.
    """

    flow: Tensor
    v_t: Tensor
    v_omega: Tensor
    depth: Tensor
    valid: Tensor
    gt_mask: Tensor
    gt_flow: Tensor | None


class MotionEvaluation(nn.Module):
    """The scores of one evaluation stage (see the module's docstring).

    Args:
        object_motion: the object-motion filter parameters; None: no object scores.
    """

    def __init__(self, object_motion: ObjectMotionConfig | None = None) -> None:
        super().__init__()
        self.object_motion = object_motion
        self.means = nn.ModuleDict(
            {
                **{name: FiniteMean() for name in MEANS},
                # a count, never NaN: no NaN check (a device synchronisation per batch)
                "nonfinite_flow_pixels": SumMetric(nan_strategy="disable"),
            }
        )
        self.objects = nn.ModuleDict({m: ObjectMotionScores() for m in OBJECT_METHODS})
        # Trajectories need whole sequences: collected over the stage, scored at its end.
        self.trajectories = TrajectoryEvaluator()
        #: the trajectory evaluation of the last :meth:`compute` that had samples
        self.last_result: EvaluationResult | None = None

    def update(
        self,
        t: Tensor,
        omega: Tensor,
        pose: Tensor,
        ids: tuple[list[str], Tensor, Tensor],
        loss: Tensor,
        active_fraction: Tensor,
        n_bad: Tensor,
        baseline: tuple[Tensor, Tensor] | None = None,
        objects: ObjectInputs | None = None,
    ) -> None:
        """Add one batch. No host synchronisation (the trajectories keep device tensors).

        Args:
            t, omega: ``(B, 3)`` the predicted translation (m per frame) and rotation vector
                (rad per frame).
            pose: ``(B, 4, 4)`` the ground-truth relative pose ``T_src,tgt``.
            ids: the batch's sequence names, source frames ``(B,)`` and target frames ``(B,)``.
            loss: the batch's mean loss (0-dim).
            active_fraction: the batch's mean fraction of active hidden units (0-dim).
            n_bad: the batch's count of masked non-finite flow pixels (0-dim int).
            baseline: the mean motion ``(t, ω)`` ``(3,)`` each, scored as a constant prediction;
                None: not scored.
            objects: what object motion is scored on; None (or no ``object_motion``): not scored.
        """
        trans_err, rot_err = frame_errors(t, omega, pose)
        m = self.means
        m["trans_err"].update(trans_err)
        m["rot_err"].update(rot_err)
        bs = t.shape[0]
        m["loss"].update(loss, weight=bs)
        m["active_fraction"].update(active_fraction, weight=bs)
        m["nonfinite_flow_pixels"].update(n_bad)
        if baseline is not None:
            b_t, b_r = constant_motion_errors(baseline[0], baseline[1], pose)
            m["baseline_trans_err"].update(b_t)
            m["baseline_rot_err"].update(b_r)
        if objects is not None and self.object_motion is not None:
            self._update_objects(objects)
        sequence, frame, target = ids
        poses = geometry.motion_to_pose(t.double(), omega.double())
        self.trajectories.update(sequence, frame, target, poses, pose)

    def _update_objects(self, o: ObjectInputs) -> None:
        """Object motion from the predicted fields and depth, against the ground truth."""
        cfg = self.object_motion
        res = extract_object_motion(o.flow, o.v_t, o.v_omega, o.depth, cfg, valid=o.valid)
        self.objects["object"].update(
            res.mask, res.object_flow, o.gt_mask, o.gt_flow, o.depth, res.valid
        )
        base = threshold_baseline(res.residual, cfg.baseline_threshold, res.valid)
        self.objects["object_baseline"].update(
            base, res.residual * base[:, None], o.gt_mask, o.gt_flow, o.depth, res.valid
        )

    def compute(self, device: torch.device | None = None) -> dict[str, Tensor]:
        """Every score of the stage by logged name (without the ``<stage>/`` prefix); the
        scores no process updated are left out. A collective under DDP: every process calls it.

        Args:
            device: where the update counts are reduced (NCCL reduces CUDA tensors only);
                None: the CPU.
        """
        updated = self._updated_on_any_process(device)
        out: dict[str, Tensor] = {}
        for name, metric in self.means.items():
            if updated[name]:
                out[name] = metric.compute()
                nan = int(getattr(metric, "nan_count", 0))
                if nan:
                    log.warning("%d NaN values left out of %s", nan, name)
        # Every process computes (the evaluator gathers all processes' samples), even one that
        # saw no sample; the numbers are the same on every process.
        res = self.trajectories.compute()
        if res.samples:
            self.last_result = res
            out.update(res.metrics)
        for method, metric in self.objects.items():
            if updated[method]:
                out.update({f"{method}/{k}": v for k, v in metric.compute().items()})
        return out

    def reset(self) -> None:
        for metric in [*self.means.values(), *self.objects.values()]:
            metric.reset()
        self.trajectories.reset()

    def _updated_on_any_process(self, device: torch.device | None) -> dict[str, bool]:
        """``{metric name: updated by some process}``: one ``all_reduce`` of the update counts,
        none in a single process. ``compute()`` is a collective under DDP, so a process that
        saw no batch (a split smaller than the number of processes) must still take part, or
        the others wait for it forever."""
        metrics: dict[str, Metric] = {**self.means, **self.objects}
        counts = [int(m.update_count) for m in metrics.values()]
        dist = torch.distributed
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            total = torch.tensor(counts, dtype=torch.long, device=device)
            dist.all_reduce(total, op=dist.ReduceOp.SUM)
            counts = [int(c) for c in total.tolist()]
        return {name: count > 0 for name, count in zip(metrics, counts, strict=True)}
