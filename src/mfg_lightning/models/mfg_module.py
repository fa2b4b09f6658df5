"""The LightningModule that trains and evaluates MFG: the network, its loss and its step.

Training: ground-truth translational (ρ = 1) and rotational fields are built from each sample's
relative pose with :mod:`mfg_lightning.core.geometry`, and the network is fit with
``w_t L_t + w_ω L_ω + w_s L_s`` (:class:`mfg_lightning.models.losses.MFGLoss`). Validation and test:
the predicted fields are turned into ``(t̃, ω̃)`` in closed form and scored by one
:class:`mfg_lightning.metrics.motion_eval.MotionEvaluation` per stage.

Like Lightning's own examples, the module computes and logs; the run does the rest. The
precision rules (``trainer.precision``, the ``16-mixed`` GradScaler) are trainer settings
(:mod:`mfg_lightning.run.precision`). What a step skips (a non-finite loss, no usable sample),
the batch checks, and whether the run stops or fails are decided by every process together in
the run's :class:`mfg_lightning.run.agreed_steps.AgreedSteps` callback. The pictures are drawn
by the figure callback (:mod:`mfg_lightning.run.figures`) from the fields the steps hand out
(:class:`StepFields`).
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
from mfg_lightning.metrics.evaluator import EvaluationResult
from mfg_lightning.metrics.motion_eval import MotionEvaluation, ObjectInputs
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
from mfg_lightning.motion.object_motion import ObjectMotionConfig

__all__ = ["HOST_INTRINSICS", "MFGLitModule", "StepFields"]

log = logging.getLogger(__name__)

#: The batch key of the intrinsics kept on the host (declared in :mod:`mfg_lightning.data.sample`).
HOST_INTRINSICS = INTRINSICS_HOST
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
        object_motion: object-motion filter parameters; when set, validation and test on
            batches that carry depth and a ground-truth object mask also score the extracted
            object motion (``<stage>/object/*``) and the plain-threshold baseline
            (``<stage>/object_baseline/*``). None disables it.
        fp16_init_scale: the initial GradScaler scale under ``trainer.precision=16-mixed``, read
            by :class:`mfg_lightning.run.precision.PrecisionSetup`; None: its measured default.
        model_config: the resolved ``model`` config this module was built from (plain data),
            saved with the hyperparameters: a checkpoint records it, and
            :mod:`mfg_lightning.run.checkpoints` rebuilds the module from it without the run
            directory (:func:`mfg_lightning.run.runs.build_model` passes it).
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
        # Plain values only: the optimiser and scheduler partials would make every checkpoint
        # need more than tensors and plain data to unpickle (mfg_lightning.run.checkpoints).
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
        #: the top-k fractions each stage scores, and one evaluation of each (:meth:`test_at`)
        self.top_ks = {"val": (self.top_k,), "test": (self.top_k,)}
        self.evaluation = nn.ModuleDict(
            {s: nn.ModuleList([MotionEvaluation(object_motion)]) for s in STAGES}
        )
        #: the last epoch's trajectory evaluation per stage (evaluate.py writes its poses)
        self.last_evaluation: dict[str, EvaluationResult] = {}
        #: the last test's ``test/`` metrics and trajectory evaluation of each of its top_ks
        self.test_results: dict[float, tuple[dict[str, float], EvaluationResult | None]] = {}

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
        :attr:`test_results`."""
        self.top_ks["test"] = tuple(ks)
        evaluations = [MotionEvaluation(self.object_motion) for _ in ks]
        self.evaluation["test"] = nn.ModuleList(evaluations).to(self.device)

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
        # One float32 context for the three (each would otherwise turn a bf16-mixed step's
        # autocast off and on again itself: 514 against 472 µs for the three at batch 1 under
        # autocast, timeit, AMD EPYC).
        with geometry.float32_math():
            t, w = geometry.pose_to_motion(batch[keys.POSE].to(inputs.flow))
            v_t = geometry.translational_field(t, K, height, width)
            v_w = geometry.rotational_field(w, K, height, width)
        if int(inputs.n_bad):
            log.warning("masked %d non-finite flow pixels in %s", inputs.n_bad, _ids(batch))
        return v_t, v_w, K, inputs

    def _loss(self, out: MFGOutput, v_t: Tensor, v_w: Tensor) -> LossTerms:
        return self.loss_fn(out.v_t, out.v_omega, v_t, v_w, out.hidden)

    def transfer_batch_to_device(
        self, batch: Any, device: torch.device, dataloader_idx: int
    ) -> Any:
        """Lightning's batch transfer, skipped on a CPU (a no-op walk of the batch costing
        ~0.35 ms, ~1.5 % of a batch-1 step: bench/results/throughput.md). Elsewhere the CPU
        intrinsics stay beside the batch (``INTRINSICS_HOST``) for the closed-form recovery,
        which groups samples by their values, without reading them back from the device."""
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
        values = {f"train/{k}": getattr(terms, k).mean() for k in _TERMS}
        values["train/active_fraction"] = _active_fraction(out.hidden)
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
        v_t, v_w, K, inputs = self._prepare(batch)
        outs = self.fields(inputs.flow, self.top_ks[stage])
        baseline = (self.mean_t, self.mean_omega) if bool(self.has_mean_motion) else None
        ids = (batch[keys.SEQUENCE], batch[keys.FRAME], batch[keys.TARGET])
        for out, evaluation in zip(outs, self.evaluation[stage], strict=True):
            t, w = geometry.recover_motion(out.v_t, out.v_omega, batch.get(INTRINSICS_HOST, K))
            objects = None
            if keys.DEPTH in batch and keys.OBJECT_MASK in batch:
                objects = ObjectInputs(inputs.flow, out.v_t, out.v_omega, batch[keys.DEPTH],
                                       inputs.valid, batch[keys.OBJECT_MASK],
                                       batch.get(keys.OBJECT_FLOW))  # fmt: skip
            evaluation.update(t, w, batch[keys.POSE], ids, loss=self._loss(out, v_t, v_w).total,
                              active_fraction=_active_fraction(out.hidden), n_bad=inputs.n_bad,
                              baseline=baseline, objects=objects)  # fmt: skip
        return StepFields.of(self.global_step, inputs.flow, v_t, v_w, outs[0])

    def _log_eval(self, stage: str) -> None:
        for i, (k, evaluation) in enumerate(
            zip(self.top_ks[stage], self.evaluation[stage], strict=True)
        ):
            values = evaluation.compute(self.device)
            evaluation.reset()
            if stage == "test":
                metrics = {f"test/{name}": float(v) for name, v in values.items()}
                self.test_results[k] = (metrics, evaluation.last_result)
            if i == 0 and evaluation.last_result is not None:
                self.last_evaluation[stage] = evaluation.last_result
            for name, value in values.items() if i == 0 else ():
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


#: The loss terms logged by every training step (``train/<term>``, batch means).
_TERMS = ("l_t", "l_omega", "l_s", "w_t", "w_omega")


def _active_fraction(hidden: Tensor) -> Tensor:
    """Mean fraction of hidden units with a non-zero activation per input."""
    return (hidden.detach() > 0).float().mean()


def _ids(batch: dict[str, Any], limit: int = 4) -> str:
    ids = list(batch.get(keys.SAMPLE_ID, []))
    more = f" (+{len(ids) - limit} more)" if len(ids) > limit else ""
    return ", ".join(map(str, ids[:limit])) + more
