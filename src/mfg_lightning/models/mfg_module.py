"""The LightningModule that trains and evaluates MFG: the network, its loss and its step.

Training fits the network to each sample's ground-truth translational (ρ = 1) and rotational
fields with ``w_t L_t + w_ω L_ω + w_s L_s`` (:class:`mfg_lightning.models.losses.MFGLoss`).
Validation and test turn the predicted fields into ``(t̃, ω̃)`` in closed form and score them
(:class:`mfg_lightning.models.stage_evaluation.StageEvaluation`).

Like Lightning's own examples, the module computes and logs; the run does the rest: the batch
checks and the skipped steps (:class:`mfg_lightning.run.agreed_steps.AgreedSteps`), the
precision (:mod:`mfg_lightning.run.precision`) and the pictures (:mod:`mfg_lightning.run.figures`,
from the :class:`StepFields` the steps return).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from mfg_lightning.core import geometry
from mfg_lightning.data import sample as keys
from mfg_lightning.data.sample import INTRINSICS_HOST, model_inputs
from mfg_lightning.models.epoch_logs import reduced_epoch_logs
from mfg_lightning.models.losses import LossTerms, MFGLoss
from mfg_lightning.models.mfg import (
    ALL_UNITS,
    MFGOutput,
    MotionFieldNetwork,
    StepFields,
    fields_at_each_k,
    validate_top_k,
)
from mfg_lightning.models.optim import checked_scheduler, optimizers
from mfg_lightning.models.stage_evaluation import StageEvaluation, active_fraction
from mfg_lightning.motion.object_motion import ObjectMotionConfig

__all__ = ["MFGLitModule", "StepFields"]

log = logging.getLogger(__name__)

STAGES = ("val", "test")


class MFGLitModule(L.LightningModule):
    """MFG with its loss, optimiser and evaluation.

    Args:
        net: the network (:class:`mfg_lightning.models.mfg.MotionFieldNetwork`, e.g. ``MFG``).
        loss: the :class:`MFGLoss`.
        optimizer: a partial optimiser constructor taking the parameters
            (paper: Adam, lr 1e-5, betas (0.99, 0.999)).
        scheduler: optional partial LR-scheduler constructor taking the optimiser.
        top_k: the fraction of hidden units kept at validation and test (``model.top_k``;
            1.0: all). Training uses every unit.
        image_log_every_n_steps: every how many training steps the step hands its fields to
            the figure callback; validation steps hand theirs at every validation. 0: never.
        max_consecutive_nonfinite: stop after this many non-finite losses in a row; read by
            the run's :class:`~mfg_lightning.run.agreed_steps.AgreedSteps`.
        object_motion: object-motion filter parameters: where batches carry depth and an object
            mask, evaluation also scores ``<stage>/object/*`` and ``<stage>/object_baseline/*``.
        fp16_init_scale: the initial GradScaler scale under ``trainer.precision=16-mixed``, read
            by :class:`mfg_lightning.run.precision.PrecisionSetup`; None: its measured default.
        model_config: the resolved ``model`` config this module was built from (plain data): a
            checkpoint records it, and :mod:`mfg_lightning.run.checkpoints` rebuilds from it.
    """

    def __init__(
        self,
        net: MotionFieldNetwork,
        loss: MFGLoss,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        top_k: float = ALL_UNITS,
        image_log_every_n_steps: int = 200,
        max_consecutive_nonfinite: int = 20,
        object_motion: ObjectMotionConfig | None = None,
        fp16_init_scale: float | None = None,
        model_config: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        # plain values only: a checkpoint must unpickle as tensors and plain data (run.checkpoints)
        self.save_hyperparameters(
            ignore=["net", "loss", "object_motion", "optimizer", "scheduler"], logger=False
        )
        if fp16_init_scale is not None and not (fp16_init_scale > 0):
            raise ValueError(f"model.fp16_init_scale must be positive, got {fp16_init_scale}")
        self.net = net
        self.loss_fn = loss
        self.top_k = validate_top_k(top_k)
        self.optimizer_factory = optimizer
        self.scheduler_factory = checked_scheduler(scheduler)
        self.image_log_every_n_steps = image_log_every_n_steps
        self.object_motion = object_motion
        #: non-finite input-flow pixels masked in training so far (this process's)
        self.masked_flow_pixels = 0
        #: the training dataset's config, stored in checkpoints for evaluation defaults
        self.dataset_config: dict | None = None
        # The training set's mean motion, the 'always predict the mean' baseline
        # (set_mean_motion); buffers, so that checkpoints carry it.
        self.register_buffer("mean_t", torch.zeros(3))
        self.register_buffer("mean_omega", torch.zeros(3))
        self.register_buffer("has_mean_motion", torch.tensor(False))
        #: what each stage scores, at ``top_k`` (``test`` at more fractions: :meth:`test_at`)
        self.evaluation = nn.ModuleDict(
            {s: StageEvaluation((self.top_k,), object_motion) for s in STAGES}
        )

    def forward(self, flow: Tensor) -> MFGOutput:
        """Flow ``(B, 2, H, W)`` pixels → :class:`MFGOutput`: every unit in training, the
        ``top_k`` most active in evaluation."""
        return self.net(flow) if self.training else self.fields(flow)[0]

    def fields(self, flow: Tensor, ks: tuple[float, ...] | None = None) -> list[MFGOutput]:
        """The fields at every top-k fraction of ``ks`` (None: ``(top_k,)``), one pass of the
        encoder (:func:`~mfg_lightning.models.mfg.fields_at_each_k`)."""
        return fields_at_each_k(self.net, flow, (self.top_k,) if ks is None else ks)

    def predict_motion(
        self, flow: Tensor, intrinsics: Tensor, top_k: float | None = None
    ) -> tuple[Tensor, Tensor, MFGOutput]:
        """Flow → egomotion ``(t̃, ω̃)`` ``(B, 3)`` each at ``top_k`` (None: the module's), plus
        the network output."""
        (out,) = self.fields(flow, None if top_k is None else (top_k,))
        t, w = geometry.recover_motion(out.v_t, out.v_omega, intrinsics)
        return t, w, out

    def test_at(self, ks: list[float]) -> None:
        """Score every top-k fraction of ``ks`` (validated) in the next tests, all from one pass
        of the encoder: the first one's metrics are logged, every one's kept in
        ``evaluation["test"].results``."""
        self.evaluation["test"] = StageEvaluation(ks, self.object_motion).to(self.device)

    def set_mean_motion(self, t: Tensor, omega: Tensor) -> None:
        """The baseline evaluation scores besides the model: always predicting the training
        set's mean motion ``t`` (m per frame) and ``omega`` (rad per frame), ``(3,)`` each."""
        self.mean_t.copy_(t)
        self.mean_omega.copy_(omega)
        self.has_mean_motion.fill_(True)

    def _prepare(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor, Any]:
        """Ground-truth fields ``(B, 2, H, W)`` of a batch, and its model inputs."""
        inputs = model_inputs(batch)
        K = batch[keys.INTRINSICS]
        height, width = inputs.flow.shape[-2:]
        with geometry.float32_math():
            t, w = geometry.pose_to_motion(batch[keys.POSE].to(inputs.flow))
            v_t = geometry.translational_field(t, K, height, width)
            v_w = geometry.rotational_field(w, K, height, width)
        if int(inputs.n_bad):
            ids = list(batch.get(keys.SAMPLE_ID, []))
            log.warning("masked %d non-finite flow pixels in a batch of %d: %s", inputs.n_bad,
                        len(ids), ", ".join(map(str, ids[:4])))  # fmt: skip
        return v_t, v_w, K, inputs

    def _loss(self, out: MFGOutput, v_t: Tensor, v_w: Tensor) -> LossTerms:
        return self.loss_fn(out.v_t, out.v_omega, v_t, v_w, out.hidden)

    def transfer_batch_to_device(
        self, batch: Any, device: torch.device, dataloader_idx: int
    ) -> Any:
        """Skipped on a CPU (~1.5 % of a batch-1 step: bench/results/throughput.md). Elsewhere
        the intrinsics stay on the host too (``INTRINSICS_HOST``), for the closed-form recovery."""
        if device.type == "cpu" and batch is not None:
            return batch
        host = batch.get(keys.INTRINSICS) if isinstance(batch, dict) else None
        moved = super().transfer_batch_to_device(batch, device, dataloader_idx)
        if isinstance(host, Tensor) and host.device.type == "cpu" and isinstance(moved, dict):
            moved[INTRINSICS_HOST] = host
        return moved

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor | dict[str, Any]:
        v_t, v_w, _, inputs = self._prepare(batch)
        self.masked_flow_pixels += int(inputs.n_bad)
        out = self(inputs.flow)
        terms = self._loss(out, v_t, v_w)
        bs = inputs.flow.shape[0]
        # not prog_bar: the run's progress bar shows the logged loss (run.progress)
        self.log("train/loss", terms.total, batch_size=bs)
        # every term of the loss (a new one is logged too), batch means
        values = {f"train/{k}": v.mean() for k, v in terms._asdict().items() if k != "total"}
        values["train/active_fraction"] = active_fraction(out.hidden)
        values["train/nonfinite_flow_pixels"] = float(self.masked_flow_pixels)
        values["train/lr"] = float(self.trainer.optimizers[0].param_groups[0]["lr"])
        self.log_dict(values, batch_size=bs)
        if self.image_log_every_n_steps and self.global_step % self.image_log_every_n_steps == 0:
            # the figure callback draws them from the step's output (references, no copy)
            return {
                "loss": terms.total,
                "fields": StepFields.of(self.global_step, inputs.flow, v_t, v_w, out),
            }
        return terms.total

    def _evaluate(self, batch: dict[str, Any] | None, stage: str) -> StepFields | None:
        """Score the batch at each of the stage's top-k fractions; the first one's fields."""
        if batch is None:  # a DDP process without an evaluation sample
            return None
        v_t, v_w, _, inputs = self._prepare(batch)
        outs = self.fields(inputs.flow, self.evaluation[stage].ks)
        baseline = (self.mean_t, self.mean_omega) if bool(self.has_mean_motion) else None
        losses = [self._loss(out, v_t, v_w).total for out in outs]
        self.evaluation[stage].update(batch, inputs, outs, losses, baseline)
        return StepFields.of(self.global_step, inputs.flow, v_t, v_w, outs[0])

    def _log_eval(self, stage: str) -> None:
        values = self.evaluation[stage].compute(self.device, stage)
        for name, value in values.items():
            self.log(f"{stage}/{name}", value, prog_bar=name in ("trans_err", "rot_err", "ate"))

    def validation_step(
        self, batch: dict[str, Any] | None, batch_idx: int
    ) -> dict[str, StepFields] | None:
        """Score the batch; hand its fields to the figure callback (the step's output)."""
        fields = self._evaluate(batch, "val")
        return {"fields": fields} if fields is not None and self.image_log_every_n_steps else None

    def on_validation_epoch_end(self) -> None:
        self._log_eval("val")

    def test_step(self, batch: dict[str, Any] | None, batch_idx: int) -> None:
        self._evaluate(batch, "test")

    def on_test_epoch_end(self) -> None:
        self._log_eval("test")

    def setup(self, stage: str) -> None:
        super().setup(stage)
        # the evaluation's values are every process's already (MotionEvaluation gathers them)
        reduced_epoch_logs("val/", "test/")

    def configure_optimizers(self) -> Any:
        return optimizers(self.optimizer_factory, self.scheduler_factory, self.parameters())

    @property
    def model_config(self) -> dict[str, Any] | None:
        """The resolved ``model`` config this module was built from (a constructor argument)."""
        return self.hparams.get("model_config")

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.dataset_config is not None:
            checkpoint["mfg_dataset_config"] = self.dataset_config

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.dataset_config = checkpoint.get("mfg_dataset_config", self.dataset_config)
