"""The LightningModule that trains and evaluates MFG.

Training: ground-truth translational (ρ = 1) and rotational fields are built from each sample's
relative pose with :mod:`mfg_lightning.core.geometry`, and the network is fit with
``w_t L_t + w_ω L_ω + w_s L_s`` (:class:`mfg_lightning.models.losses.MFGLoss`). Validation and test:
the predicted fields are turned into ``(t̃, ω̃)`` in closed form and scored per frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import lightning as L
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor, nn
from torchmetrics import MeanMetric, SumMetric

from mfg_lightning.core import geometry
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.metrics.evaluator import EvaluationResult, TrajectoryEvaluator
from mfg_lightning.metrics.frame_errors import constant_motion_errors, frame_errors
from mfg_lightning.metrics.object_motion import ObjectMotionScores
from mfg_lightning.models.losses import LossTerms, MFGLoss
from mfg_lightning.models.mfg import MFG, MFGOutput, validate_top_k
from mfg_lightning.motion.object_motion import (
    ObjectMotionConfig,
    extract_object_motion,
    threshold_baseline,
)
from mfg_lightning.pictures.colours import activation_map, flows_to_rgb

log = logging.getLogger(__name__)


class NonFiniteLossError(RuntimeError):
    """Training produced non-finite losses too many times in a row."""


class MFGLitModule(L.LightningModule):
    """MFG with its losses, optimiser and evaluation.

    Args:
        net: the :class:`MFG` network.
        loss: the :class:`MFGLoss`.
        optimizer: a partial optimiser constructor taking the parameters
            (paper: Adam, lr 1e-5, betas (0.99, 0.999)).
        scheduler: optional partial LR-scheduler constructor taking the optimiser.
        top_k: fraction of hidden units kept at evaluation (None: all); overrides ``net.top_k``.
        image_log_every_n_steps: how often fields are drawn to TensorBoard (0: never).
        max_consecutive_nonfinite: stop after this many non-finite losses in a row.
        object_motion: object-motion filter parameters; when set, validation and test on
            batches that carry depth and a ground-truth object mask also score the extracted
            object motion (``<stage>/object/*``) and the plain-threshold baseline
            (``<stage>/object_baseline/*``). None disables it.
    """

    def __init__(
        self,
        net: MFG,
        loss: MFGLoss,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        top_k: float | None = None,
        image_log_every_n_steps: int = 200,
        max_consecutive_nonfinite: int = 20,
        object_motion: ObjectMotionConfig | None = None,
    ) -> None:
        super().__init__()
        # Plain values only: the optimiser and scheduler partials would make every checkpoint
        # need more than tensors and plain data to unpickle (mfg_lightning.run.checkpoints).
        self.save_hyperparameters(
            ignore=["net", "loss", "object_motion", "optimizer", "scheduler"], logger=False
        )
        if net.top_k is not None:
            # One knob: the module's top_k is what evaluation, sweeps and checkpoints use.
            raise ValueError(
                f"model.net.top_k={net.top_k} is not a setting of the training module: set "
                "model.top_k instead (it applies to the network at evaluation)"
            )
        self.net = net
        self.loss_fn = loss
        self.net.top_k = validate_top_k(top_k)
        self.optimizer_factory = optimizer
        self.scheduler_factory = _checked_scheduler(scheduler)
        self.image_log_every_n_steps = image_log_every_n_steps
        self.max_consecutive_nonfinite = max_consecutive_nonfinite
        self._consecutive_nonfinite = 0
        #: the model's config, set by the entry point and stored in checkpoints so that
        #: :mod:`mfg_lightning.run.checkpoints` can rebuild the network without the run directory.
        self.model_config: dict | None = None
        #: the training dataset's config, stored in checkpoints for evaluation defaults
        self.dataset_config: dict | None = None
        # The training set's mean motion, the 'always predict the mean' baseline.
        self.register_buffer("mean_t", torch.zeros(3))
        self.register_buffer("mean_omega", torch.zeros(3))
        self.register_buffer("has_mean_motion", torch.tensor(False))
        self.eval_metrics = nn.ModuleDict(
            {
                stage: nn.ModuleDict(
                    {
                        **{
                            name: MeanMetric()
                            for name in (
                                "trans_err",
                                "rot_err",
                                "loss",
                                "active_fraction",
                                "baseline_trans_err",
                                "baseline_rot_err",
                            )
                        },
                        "nonfinite_flow_pixels": SumMetric(),
                    }
                )
                for stage in ("val", "test")
            }
        )
        #: non-finite input-flow pixels masked during training so far (this process)
        self.nonfinite_flow_pixels = 0
        self.object_motion = object_motion
        # Trajectory metrics (ATE over snippets, RPE, drift, whole-trajectory ATE) need whole
        # sequences: collected over an epoch, scored at its end by the metrics they feed.
        self.trajectory_evaluators = {s: TrajectoryEvaluator() for s in ("val", "test")}
        #: the last epoch's trajectory evaluation per stage (evaluate.py writes its poses)
        self.last_evaluation: dict[str, EvaluationResult] = {}
        self.object_scores = nn.ModuleDict(
            {
                f"{stage}_{method}": ObjectMotionScores()
                for stage in ("val", "test")
                for method in ("object", "object_baseline")
            }
        )

    # -- model -------------------------------------------------------------------------------

    def forward(self, flow: Tensor, top_k: float | None = None) -> MFGOutput:
        """Flow ``(B, 2, H, W)`` pixels → :class:`MFGOutput`."""
        return self.net(flow, top_k=top_k)

    def predict_motion(
        self, flow: Tensor, intrinsics: Tensor, top_k: float | None = None
    ) -> tuple[Tensor, Tensor, MFGOutput]:
        """Flow → egomotion ``(t̃, ω̃)`` ``(B, 3)`` each, plus the raw network output."""
        out = self(flow, top_k=top_k)
        t, w = geometry.recover_motion(out.v_t, out.v_omega, intrinsics)
        return t, w, out

    # -- shared step -------------------------------------------------------------------------

    def _prepare(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor, Tensor, int]:
        """Masked input flow, ground-truth fields and intrinsics of a batch, and the number of
        non-finite flow pixels that were masked."""
        flow, _, n_bad = sanitize_flow(batch["flow"], batch["flow_valid"])
        if n_bad:
            log.warning("masked %d non-finite flow pixels in %s", n_bad, _ids(batch))
        K = batch["intrinsics"]
        height, width = flow.shape[-2:]
        t, w = geometry.pose_to_motion(batch["pose"].to(flow))
        v_t = geometry.translational_field(t, K, height, width)
        v_w = geometry.rotational_field(w, K, height, width)
        return flow, v_t, v_w, K, n_bad

    def _loss(self, out: MFGOutput, v_t: Tensor, v_w: Tensor) -> LossTerms:
        return self.loss_fn(out.v_t, out.v_omega, v_t, v_w, out.hidden)

    def transfer_batch_to_device(
        self, batch: Any, device: torch.device, dataloader_idx: int
    ) -> Any:
        """Lightning's batch transfer, skipped on a CPU: the batches are built on the CPU, so
        the transfer is a no-op whose recursive walk of the batch dict still costs ~0.35 ms per
        step, ~1.5 % of a batch-1 step (bench/results/throughput.md)."""
        if device.type == "cpu":
            return batch
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    # -- training ----------------------------------------------------------------------------

    def _writes_logs_this_step(self) -> bool:
        """Whether the loggers write this training step's values (every
        ``trainer.log_every_n_steps``): the step-only diagnostics are logged just then, since
        each ``self.log`` costs Python time that shows at batch 1 (bench/results/throughput.md)
        and the values of the other steps would never be written."""
        connector = getattr(self._trainer, "_logger_connector", None)
        return bool(getattr(connector, "should_update_logs", True))

    def _learning_rate(self) -> float:
        """The first parameter group's current learning rate (NaN outside a fit)."""
        trainer = self._trainer
        if trainer is None or not trainer.optimizers:
            return float("nan")
        return float(trainer.optimizers[0].param_groups[0]["lr"])

    def training_step(self, batch: dict[str, Any] | None, batch_idx: int) -> Tensor | None:
        if batch is None:  # every sample of the batch was skipped as unreadable
            return None
        flow, v_t, v_w, _, n_bad = self._prepare(batch)
        self.nonfinite_flow_pixels += n_bad
        out = self(flow)
        terms = self._loss(out, v_t, v_w)
        if not torch.isfinite(terms.total):
            # Returning None skips backward and the optimiser step: a NaN never reaches weights.
            self._consecutive_nonfinite += 1
            log.warning("non-finite loss (%s) on %s: step skipped", terms.total.item(), _ids(batch))
            self.log("train/skipped_steps", float(self._consecutive_nonfinite), on_step=True)
            if self._consecutive_nonfinite >= self.max_consecutive_nonfinite:
                raise NonFiniteLossError(
                    f"{self._consecutive_nonfinite} consecutive non-finite losses; last samples: "
                    f"{_ids(batch)}"
                )
            return None
        self._consecutive_nonfinite = 0
        bs = flow.shape[0]
        if self._writes_logs_this_step():
            # Only on the steps the loggers write (the progress bar's loss refreshes then too):
            # a logged value costs ~0.7 ms, 2-3 % of a batch-1 step on a CPU (bench/throughput.py).
            self.log("train/loss", terms.total, prog_bar=True, batch_size=bs)
            self.log_dict(
                {
                    "train/l_t": terms.l_t.mean(),
                    "train/l_omega": terms.l_omega.mean(),
                    "train/l_s": terms.l_s.mean(),
                    "train/w_t": terms.w_t.mean(),
                    "train/w_omega": terms.w_omega.mean(),
                    "train/active_fraction": _active_fraction(out.hidden),
                    "train/nonfinite_flow_pixels": float(self.nonfinite_flow_pixels),
                    "train/lr": self._learning_rate(),
                },
                batch_size=bs,
            )
        if self.image_log_every_n_steps and self.global_step % self.image_log_every_n_steps == 0:
            self._log_images("train", flow, v_t, v_w, out)
        return terms.total

    # -- evaluation --------------------------------------------------------------------------

    def _evaluate(self, batch: dict[str, Any] | None, stage: str) -> dict[str, Tensor] | None:
        if batch is None:
            return None
        flow, v_t, v_w, K, n_bad = self._prepare(batch)
        out = self(flow)
        terms = self._loss(out, v_t, v_w)
        t, w = geometry.recover_motion(out.v_t, out.v_omega, K)
        trans_err, rot_err = frame_errors(t, w, batch["pose"])
        m = self.eval_metrics[stage]
        m["trans_err"].update(trans_err)
        m["rot_err"].update(rot_err)
        # Weighted by batch size: per-sample means, whatever the batches (or DDP shards) are.
        bs = flow.shape[0]
        m["loss"].update(terms.total, weight=bs)
        m["active_fraction"].update(_active_fraction(out.hidden), weight=bs)
        m["nonfinite_flow_pixels"].update(n_bad)
        if bool(self.has_mean_motion):
            b_t, b_r = constant_motion_errors(self.mean_t, self.mean_omega, batch["pose"])
            m["baseline_trans_err"].update(b_t)
            m["baseline_rot_err"].update(b_r)
        self._score_object_motion(batch, flow, out, stage)
        self.trajectory_evaluators[stage].update(
            batch["sequence"],
            batch["frame"],
            batch["target"],
            geometry.motion_to_pose(t.double(), w.double()),
            batch["pose"],
        )
        return {"t": t, "omega": w, "out": out, "flow": flow, "v_t": v_t, "v_omega": v_w}

    def _score_object_motion(
        self, batch: dict[str, Any], flow: Tensor, out: MFGOutput, stage: str
    ) -> None:
        """Object motion from the predicted fields and depth, against the ground truth."""
        cfg = self.object_motion
        if cfg is None or "depth" not in batch or "object_mask" not in batch:
            return
        depth, valid = batch["depth"], batch["flow_valid"]
        res = extract_object_motion(flow, out.v_t, out.v_omega, depth, cfg, valid=valid)
        gt_mask, gt_flow = batch["object_mask"], batch.get("object_flow")
        self.object_scores[f"{stage}_object"].update(
            res.mask, res.object_flow, gt_mask, gt_flow, depth, res.valid
        )
        base = threshold_baseline(res.residual, cfg.baseline_threshold, res.valid)
        self.object_scores[f"{stage}_object_baseline"].update(
            base, res.residual * base[:, None], gt_mask, gt_flow, depth, res.valid
        )

    def _log_eval(self, stage: str) -> None:
        for name, metric in self.eval_metrics[stage].items():
            if metric.update_count:
                self.log(
                    f"{stage}/{name}", metric.compute(), prog_bar=name in ("trans_err", "rot_err")
                )
            metric.reset()
        evaluator = self.trajectory_evaluators[stage]
        # Every process computes (the evaluator gathers all processes' samples, a collective
        # call), even one that saw no sample; the numbers are the same on every process.
        res = evaluator.compute()
        evaluator.reset()
        if res.samples:
            self.last_evaluation[stage] = res
            metrics = {f"{stage}/{k}": v for k, v in res.metrics.items()}
            self.log(f"{stage}/ate", metrics.pop(f"{stage}/ate"), prog_bar=True)
            self.log_dict(metrics)
        for method in ("object", "object_baseline"):
            metric = self.object_scores[f"{stage}_{method}"]
            if metric.update_count:
                self.log_dict({f"{stage}/{method}/{k}": v for k, v in metric.compute().items()})
            metric.reset()

    def on_fit_start(self) -> None:
        self._set_mean_motion()

    def on_test_start(self) -> None:
        self._set_mean_motion()

    def _set_mean_motion(self) -> None:
        dm = getattr(self.trainer, "datamodule", None)
        if dm is None or not hasattr(dm, "mean_motion") or bool(self.has_mean_motion):
            return
        try:
            t, w = dm.mean_motion("train")
        except Exception as err:  # a test-only datamodule may have no training split
            log.info("no training split for the mean-motion baseline: %s", err)
            return
        self.mean_t.copy_(t)
        self.mean_omega.copy_(w)
        self.has_mean_motion.fill_(True)

    def validation_step(self, batch: dict[str, Any] | None, batch_idx: int) -> None:
        res = self._evaluate(batch, "val")
        if res is not None and batch_idx == 0 and self.image_log_every_n_steps:
            self._log_images("val", res["flow"], res["v_t"], res["v_omega"], res["out"])

    def on_validation_epoch_end(self) -> None:
        self._log_eval("val")

    def test_step(self, batch: dict[str, Any] | None, batch_idx: int) -> None:
        self._evaluate(batch, "test")

    def on_test_epoch_end(self) -> None:
        self._log_eval("test")

    # -- pictures ----------------------------------------------------------------------------

    def _log_images(
        self, stage: str, flow: Tensor, v_t: Tensor, v_w: Tensor, out: MFGOutput
    ) -> None:
        """Input flow, GT and predicted fields (Middlebury colours) and the hidden activations."""
        logger = self.logger
        if not isinstance(logger, TensorBoardLogger) or self.trainer.sanity_checking:
            return
        n = min(4, flow.shape[0])
        exp = logger.experiment
        step = self.global_step
        exp.add_images(f"{stage}/flow", flows_to_rgb(flow[:n]), step, dataformats="NCHW")
        for name, gt, pred in (("v_t", v_t, out.v_t), ("v_omega", v_w, out.v_omega)):
            both = torch.cat([gt[:n], pred[:n].detach().to(gt)], dim=0)
            rgb = flows_to_rgb(both)  # shared normalisation: GT and prediction comparable
            exp.add_images(f"{stage}/{name}_gt", rgb[:n], step, dataformats="NCHW")
            exp.add_images(f"{stage}/{name}_pred", rgb[n:], step, dataformats="NCHW")
        maps = [torch.from_numpy(activation_map(h)).permute(2, 0, 1) for h in out.hidden[:n]]
        exp.add_images(f"{stage}/hidden_activations", torch.stack(maps), step, dataformats="NCHW")

    # -- optimisation ------------------------------------------------------------------------

    def configure_optimizers(self) -> Any:
        optimizer = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.model_config is not None:
            checkpoint["mfg_model_config"] = self.model_config
        if self.dataset_config is not None:
            checkpoint["mfg_dataset_config"] = self.dataset_config

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.model_config = checkpoint.get("mfg_model_config", self.model_config)
        self.dataset_config = checkpoint.get("mfg_dataset_config", self.dataset_config)


def _checked_scheduler(scheduler: Callable[..., Any] | None) -> Callable[..., Any] | None:
    """``scheduler`` unchanged, after refusing a schedule length that is not positive: the
    default cosine schedule's ``T_max`` follows ``trainer.max_steps``, which is -1 in a run that
    counts epochs, and a non-positive length would silently drive the rate to nonsense."""
    keywords = getattr(scheduler, "keywords", None) or {}
    t_max = keywords.get("T_max")
    if t_max is not None and t_max <= 0:
        raise ValueError(
            f"model.scheduler.T_max must be a positive number of steps, got {t_max} (it follows "
            "trainer.max_steps); set model.scheduler.T_max=<steps>, or model.scheduler=null for "
            "a constant learning rate"
        )
    return scheduler


def _active_fraction(hidden: Tensor) -> Tensor:
    """Mean fraction of hidden units with a non-zero activation per input."""
    return (hidden.detach() > 0).float().mean()


def _ids(batch: dict[str, Any], limit: int = 4) -> str:
    ids = list(batch.get("sample_id", []))
    more = f" (+{len(ids) - limit} more)" if len(ids) > limit else ""
    return ", ".join(map(str, ids[:limit])) + more
