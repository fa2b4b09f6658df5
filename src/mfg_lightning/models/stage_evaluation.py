"""What validation or test scores, at each top-k fraction it is asked for: one
:class:`~mfg_lightning.metrics.motion_eval.MotionEvaluation` per fraction, fed from one pass of the
encoder (:meth:`mfg_lightning.models.mfg_module.MFGLitModule.fields`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from mfg_lightning.core import geometry
from mfg_lightning.data import sample as keys
from mfg_lightning.data.sample import INTRINSICS_HOST, ModelInputs
from mfg_lightning.metrics.evaluator import EvaluationResult
from mfg_lightning.metrics.motion_eval import MotionEvaluation, ObjectInputs
from mfg_lightning.models.mfg import MFGOutput
from mfg_lightning.motion.object_motion import ObjectMotionConfig


def active_fraction(hidden: Tensor) -> Tensor:
    """Mean fraction of the hidden units ``(B, M)`` with a non-zero activation per input."""
    return (hidden.detach() > 0).float().mean()


class StageEvaluation(nn.Module):
    """The evaluation of one stage (``val`` or ``test``) at every top-k fraction of ``ks``.

    Attributes:
        ks: the fractions of hidden units kept, in (0, 1]; the first one's metrics are logged.
        metrics: one evaluation per fraction, in the order of ``ks``.
        results: after :meth:`compute`, per fraction its ``<stage>/`` metrics and trajectory
            evaluation (``evaluate`` writes them).
    """

    def __init__(self, ks: Sequence[float], object_motion: ObjectMotionConfig | None) -> None:
        super().__init__()
        self.ks = tuple(ks)
        self.metrics = nn.ModuleList([MotionEvaluation(object_motion) for _ in self.ks])
        self.results: dict[float, tuple[dict[str, float], EvaluationResult | None]] = {}

    def update(
        self,
        batch: dict[str, Any],
        inputs: ModelInputs,
        outs: Sequence[MFGOutput],
        losses: Sequence[Tensor],
        baseline: tuple[Tensor, Tensor] | None,
    ) -> None:
        """Score a batch at each fraction: ``outs`` the network's fields at each
        (:meth:`~mfg_lightning.models.mfg_module.MFGLitModule.fields`), ``losses`` their total
        losses, ``baseline`` the training set's mean motion ``(t, ω)`` or None."""
        K = batch.get(INTRINSICS_HOST, batch[keys.INTRINSICS])
        ids = (batch[keys.SEQUENCE], batch[keys.FRAME], batch[keys.TARGET])
        with_objects = keys.DEPTH in batch and keys.OBJECT_MASK in batch
        for out, loss, evaluation in zip(outs, losses, self.metrics, strict=True):
            t, w = geometry.recover_motion(out.v_t, out.v_omega, K)
            objects = None
            if with_objects:
                objects = ObjectInputs(inputs.flow, out.v_t, out.v_omega, batch[keys.DEPTH],
                                       inputs.valid, batch[keys.OBJECT_MASK],
                                       batch.get(keys.OBJECT_FLOW))  # fmt: skip
            evaluation.update(t, w, batch[keys.POSE], ids, loss=loss,
                              active_fraction=active_fraction(out.hidden), n_bad=inputs.n_bad,
                              baseline=baseline, objects=objects)  # fmt: skip

    def compute(self, device: torch.device, stage: str) -> dict[str, torch.Tensor]:
        """Every fraction's epoch metrics (gathered across processes), kept in
        :attr:`results`; the evaluations reset. Returns the first fraction's, to log."""
        first: dict[str, torch.Tensor] = {}
        for k, evaluation in zip(self.ks, self.metrics, strict=True):
            values = evaluation.compute(device)
            evaluation.reset()
            metrics = {f"{stage}/{name}": float(v) for name, v in values.items()}
            self.results[k] = (metrics, evaluation.last_result)
            first = first or values
        return first

    @property
    def last_result(self) -> EvaluationResult | None:
        """The first fraction's trajectory evaluation of the last epoch (None before one)."""
        return self.results[self.ks[0]][1] if self.ks[0] in self.results else None
