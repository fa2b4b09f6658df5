"""Images to egomotion trained end to end (``experiment=end_to_end``): the learned flow network
(:class:`~mfg_lightning.flow.pwc.PWCFlowNet`) and MFG fine-tuned together on MFG's loss.

A step: the image pair at the render size → the network's flow (every decoder level, and the
finest upsampled to the image, as :meth:`PWCFlowNet.estimate` gives it) → the flow MFG reads,
made exactly as ``flow=learned`` makes it for a two-stage MFG
(:func:`~mfg_lightning.flow.learned.model_input_flow`: area average to the model input, vectors
rescaled) → MFG's step, loss and evaluation, which are :class:`MFGLitModule`'s own (this module
only replaces the batch's flow by the network's, in :meth:`EndToEndLitModule._prepare`). The
pose loss's gradient reaches the flow network through that flow.

Options (``conf/model/end_to_end.yaml``): a flow term, PWC-Net's multi-scale end-point error
against the exact flow (:func:`~mfg_lightning.models.flow_module.multiscale_loss`, the flow
training's own loss) weighted by ``flow_loss_weight`` (0: none); the flow network's learning
rate ``flow_lr`` beside MFG's ``optimizer.lr`` (two parameter groups of one optimiser, one
schedule); a frozen warm-up of ``freeze_flow_steps`` optimiser steps in which the network runs
without gradients (its weights cannot change: no gradient, no Adam update); the start from the
shipped flow weights (or ``flow_weights``) and, optionally, from a trained MFG
(``mfg_checkpoint``).

Validation and test: MFG's pose metrics (``<stage>/ate``, ``trans_err``, …) and the flow's
quality against the exact flow at the render size, pooled pixel by pixel as ``train_flow``
scores it (:func:`~mfg_lightning.models.flow_module.score_flow`): ``<stage>/flow_epe`` (px),
``<stage>/flow_fl`` (%), ``<stage>/flow_epe/<region>``, ``<stage>/flow_epe_+1`` …, and on the
non-occluded pixels ``<stage>/flow_epe_noc`` … (KITTI's noc, where the pairs carry visibility).

Checkpoints carry the flow network's config under ``flow_net_config`` (and where its weights
are, ``flow_net_prefix``), so ``flow=learned flow.weights=<checkpoint>`` reads the fine-tuned
network as a flow estimator, and a stored model config that rebuilds the module without
reading any other file (``flow_net`` set, ``flow_weights`` and ``mfg_checkpoint`` null).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from mfg_lightning.data import sample as keys
from mfg_lightning.flow.learned import DEFAULT_WEIGHTS, load_weights, model_input_flow
from mfg_lightning.flow.pwc import PWCFlowNet, config_from
from mfg_lightning.metrics.flow_quality import PooledFlowQuality
from mfg_lightning.models.flow_module import (
    FlowLitModule,
    endpoint_error,
    flow_quality_metrics,
    multiscale_loss,
    quality_names,
    score_flow,
)
from mfg_lightning.models.losses import LossTerms
from mfg_lightning.models.mfg import MFGOutput
from mfg_lightning.models.mfg_module import STAGES, MFGLitModule, StepFields
from mfg_lightning.models.optim import optimizers

__all__ = ["EndToEndLitModule", "load_mfg_weights"]

#: The batch keys of :mod:`mfg_lightning.data.image_pairs` this module reads (the render-size
#: frames, exact flow, region and visibility codes, the offset), beside MFG's.
IMAGE0, IMAGE1, IMAGE_FLOW, REGION = "image0", "image1", "image_flow", "region"
VISIBILITY, OFFSET = "visibility", "offset"
#: Where the flow network's weights are in the module's state_dict.
FLOW_NET_PREFIX = "flow_net."


@dataclass
class _StepFlow:
    """The flow network's output of the current step, from :meth:`EndToEndLitModule._prepare`
    to the loss and the scores of the same step.

    Attributes:
        levels: every decoder level's flow, coarsest first, image pixels.
        full: ``(B, 2, H, W)`` the finest level upsampled to the image, image pixels.
        target: ``(B, 2, H, W)`` the exact flow, image pixels, NaN where unknown.
        loss: the flow term, once computed (None: not this step).
    """

    levels: list[Tensor]
    full: Tensor
    target: Tensor
    loss: Tensor | None = None


def load_mfg_weights(net: nn.Module, path: str | Path) -> None:
    """Load the MFG network of a ``train`` (or end-to-end) checkpoint into ``net``.

    Tensors and plain data only (``torch.load(weights_only=True)``: a checkpoint is never
    allowed to run code); only the network's weights (``net.*``) are read.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: unreadable, not an MFG checkpoint, or weights of another
            size than ``net``'s (``model.net`` must match the checkpoint's).
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"model.mfg_checkpoint: no such file: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # (torch raises several kinds for foreign or unsafe files)
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ValueError(f"model.mfg_checkpoint={path}: unreadable ({first})") from None
    state = ckpt.get("state_dict") if isinstance(ckpt, dict) else None
    weights = {k[4:]: v for k, v in (state or {}).items() if k.startswith("net.")}
    hparams = ckpt.get("hyper_parameters") or {}
    if not weights or ("model_config" not in hparams and "mfg_model_config" not in ckpt):
        raise ValueError(f"model.mfg_checkpoint={path}: not a checkpoint of an MFG training")
    try:
        net.load_state_dict(weights)
    except RuntimeError as err:
        last = str(err).strip().splitlines()[-1].strip()
        raise ValueError(
            f"model.mfg_checkpoint={path}: its MFG does not fit model.net (set model.net as the "
            f"checkpoint's: {last})"
        ) from None


class EndToEndLitModule(MFGLitModule):
    """The flow network and MFG trained together on MFG's loss.

    Args:
        flow_weights: the flow network's start, a weight file or ``train_flow`` checkpoint
            (None: the shipped weights, :data:`~mfg_lightning.flow.learned.DEFAULT_WEIGHTS`).
        flow_net: a :class:`~mfg_lightning.flow.pwc.PWCConfig`'s fields: a network of this
            shape with fresh weights instead (what a checkpoint's stored config sets: its
            weights follow from the checkpoint). None: ``flow_weights``.
        mfg_checkpoint: a ``train`` checkpoint whose MFG weights are the start (None: MFG's
            initialisation); ``net`` must be of its size.
        flow_lr: the flow network's learning rate.
        flow_loss_weight: the weight of the flow term (0: MFG's loss alone).
        level_weights: the flow term's weight per decoder level, coarsest first (as
            ``train_flow``'s ``model.level_weights``).
        freeze_flow_steps: optimiser steps at the start in which the flow network is not
            trained (it runs without gradients).
        kwargs: :class:`MFGLitModule`'s arguments: MFG's ``net``, ``loss``, ``optimizer``
            (``optimizer.lr`` is MFG's learning rate; the schedule scales both groups),
            ``scheduler``, ...
    """

    def __init__(
        self,
        flow_weights: str | None = None,
        flow_net: dict[str, Any] | None = None,
        mfg_checkpoint: str | None = None,
        flow_lr: float = 1e-5,
        flow_loss_weight: float = 0.0,
        level_weights: Sequence[float] = (0.25, 0.25, 0.5, 1.0),
        freeze_flow_steps: int = 0,
        **kwargs: Any,
    ) -> None:
        # plain values before MFGLitModule saves the arguments (this frame's among them) into
        # every checkpoint, which tensors-and-plain-data loading must read (no OmegaConf lists)
        level_weights = [float(w) for w in level_weights]
        flow_net = None if flow_net is None else config_from(flow_net).to_dict()
        super().__init__(**kwargs)
        if not flow_lr >= 0:
            raise ValueError(f"model.flow_lr must be non-negative, got {flow_lr}")
        if not flow_loss_weight >= 0:
            raise ValueError(f"model.flow_loss_weight must be non-negative, got {flow_loss_weight}")
        if isinstance(freeze_flow_steps, bool) or int(freeze_flow_steps) != freeze_flow_steps:
            raise ValueError(f"model.freeze_flow_steps must be an integer, got {freeze_flow_steps}")
        if freeze_flow_steps < 0:
            raise ValueError(f"model.freeze_flow_steps must be ≥ 0, got {freeze_flow_steps}")
        if flow_net is not None:
            self.flow_net = PWCFlowNet(config_from(flow_net))
            self.flow_provenance: dict[str, Any] = {}
        else:
            self.flow_net, self.flow_provenance = load_weights(flow_weights or DEFAULT_WEIGHTS)
            self.flow_net.train()  # (loaded in eval mode; Lightning sets the modes itself)
        if mfg_checkpoint:
            load_mfg_weights(self.net, mfg_checkpoint)
        cfg = self.flow_net.config
        levels = len(cfg.pyramid) - cfg.output_level + 1
        self.level_weights = tuple(float(w) for w in level_weights)
        if len(self.level_weights) != levels:
            raise ValueError(
                f"model.level_weights needs {levels} weights (the flow network's decoder levels "
                f"{len(cfg.pyramid)} … {cfg.output_level}), got {list(self.level_weights)}"
            )
        self.flow_lr = float(flow_lr)
        self.flow_loss_weight = float(flow_loss_weight)
        self.freeze_flow_steps = int(freeze_flow_steps)
        #: the flow's pooled scores of each evaluation stage (sums; reduced across processes)
        self.flow_quality = nn.ModuleDict({s: PooledFlowQuality(quality_names()) for s in STAGES})
        self._step_flow: _StepFlow | None = None

    # -- the flow MFG reads ------------------------------------------------------------------

    def flow_frozen(self) -> bool:
        """Whether this training step is in the frozen warm-up."""
        return self.global_step < self.freeze_flow_steps

    def estimate_flow(self, image0: Tensor, image1: Tensor) -> tuple[list[Tensor], Tensor, Tensor]:
        """Images → flow, with gradients unless in the frozen warm-up (or under no_grad).

        Args:
            image0, image1: ``(B, 3, H, W)`` RGB in [0, 1] at the render size.

        Returns:
            Every decoder level's flow (coarsest first) and the finest upsampled to the image
            ``(B, 2, H, W)``, both in image pixels; and MFG's input ``(B, 2, h, w)``, pixels of
            the model input (:func:`~mfg_lightning.flow.learned.model_input_flow`).
        """
        frozen = self.training and self.flow_frozen()
        with torch.set_grad_enabled(torch.is_grad_enabled() and not frozen):
            levels, full = self.flow_net.levels_and_estimate(image0, image1)
            flow = model_input_flow(full, self.net.height, self.net.width)
        return levels, full, flow

    def _prepare(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor, Any]:
        """MFG's ground-truth fields and inputs (:meth:`MFGLitModule._prepare`) with the batch's
        flow replaced by the network's, estimated on its frames (every pixel valid: the
        network's flow is finite). The network's output is kept for the step's flow term and
        scores."""
        image0, image1 = FlowLitModule.images({"image0": batch[IMAGE0], "image1": batch[IMAGE1]})
        levels, full, flow = self.estimate_flow(image0, image1)
        self._step_flow = _StepFlow(levels, full, batch[IMAGE_FLOW].float())
        estimated = {
            **batch,
            keys.FLOW: flow.to(batch[keys.FLOW].dtype),
            keys.FLOW_VALID: torch.ones_like(batch[keys.FLOW_VALID]),
        }
        return super()._prepare(estimated)

    def _loss(self, out: MFGOutput, v_t: Tensor, v_w: Tensor) -> LossTerms:
        """MFG's loss, plus ``flow_loss_weight`` × the flow term in a training step whose
        network has gradients."""
        terms = super()._loss(out, v_t, v_w)
        step = self._step_flow
        if (
            self.training
            and self.flow_loss_weight > 0
            and step is not None
            and step.levels[-1].requires_grad
        ):
            step.loss, _ = multiscale_loss(step.levels, step.target, self.level_weights)
            terms = terms._replace(total=terms.total + self.flow_loss_weight * step.loss)
        return terms

    # -- steps -------------------------------------------------------------------------------

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor | dict[str, Any]:
        result = super().training_step(batch, batch_idx)
        step, self._step_flow = self._step_flow, None
        if step is not None:
            values = {
                "train/flow_epe": _mean_epe(step.full.detach(), step.target),
                "train/flow_frozen": float(self.flow_frozen()),
                "train/flow_lr": float(self.trainer.optimizers[0].param_groups[1]["lr"]),
            }
            if step.loss is not None:
                values["train/flow_loss"] = step.loss.detach()
            self.log_dict(values, batch_size=step.full.shape[0])
        return result

    def _score_flow(self, batch: dict[str, Any] | None, stage: str) -> None:
        step, self._step_flow = self._step_flow, None
        if batch is not None and step is not None:
            score_flow(self.flow_quality[stage], step.full, step.target, batch[REGION],
                       batch[OFFSET], visibility=batch.get(VISIBILITY))  # fmt: skip

    def _log_flow_quality(self, stage: str) -> None:
        # every process's sums added up by the metric (a collective each process joins)
        for name, value in flow_quality_metrics(self.flow_quality[stage], f"{stage}/flow_").items():
            self.log(name, value, prog_bar=name == f"{stage}/flow_epe")
        self.flow_quality[stage].reset()

    def validation_step(
        self, batch: dict[str, Any] | None, batch_idx: int
    ) -> dict[str, StepFields] | None:
        result = super().validation_step(batch, batch_idx)
        self._score_flow(batch, "val")
        return result

    def on_validation_epoch_end(self) -> None:
        super().on_validation_epoch_end()
        self._log_flow_quality("val")

    def test_step(self, batch: dict[str, Any] | None, batch_idx: int) -> None:
        super().test_step(batch, batch_idx)
        self._score_flow(batch, "test")

    def on_test_epoch_end(self) -> None:
        super().on_test_epoch_end()
        self._log_flow_quality("test")

    # -- optimisation and checkpoints --------------------------------------------------------

    def setup(self, stage: str) -> None:
        """Refuse a frozen warm-up under several DDP processes that do not look for unused
        parameters: the flow network gets no gradient in the warm-up, and DDP's reducer would
        stop the run at its second step with an error that names neither setting. (A module's
        setup runs before the strategy wraps it.)"""
        super().setup(stage)
        from lightning.pytorch.strategies import DDPStrategy

        strategy = self._trainer.strategy if self._trainer is not None else None
        if (
            stage == "fit"
            and self.freeze_flow_steps > 0
            and isinstance(strategy, DDPStrategy)
            and strategy.num_processes * strategy.num_nodes > 1
            and not strategy._ddp_kwargs.get("find_unused_parameters", False)
        ):
            raise ValueError(
                f"model.freeze_flow_steps={self.freeze_flow_steps} under DDP needs "
                "trainer.strategy.find_unused_parameters=true (the flow network has no gradient "
                "in the warm-up), or model.freeze_flow_steps=0"
            )

    def configure_optimizers(self) -> Any:
        """One optimiser, two parameter groups: MFG's (and every other parameter) at the
        configured rate, the flow network's at ``flow_lr``."""
        flow = list(self.flow_net.parameters())
        ids = {id(p) for p in flow}
        rest = [p for p in self.parameters() if id(p) not in ids]
        groups = [{"params": rest}, {"params": flow, "lr": self.flow_lr}]
        return optimizers(self.optimizer_factory, self.scheduler_factory, groups)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        config = self.flow_net.config.to_dict()
        # flow.weights=<this checkpoint> reads the fine-tuned network (flow.learned.load_weights)
        checkpoint["flow_net_config"] = config
        checkpoint["flow_net_prefix"] = FLOW_NET_PREFIX
        hparams = checkpoint.get("hyper_parameters") or {}
        stored = hparams.get("model_config")
        if stored is not None:
            # rebuilt from the checkpoint alone: the network's shape, no start files to read
            stored = {**stored, "flow_net": config, "flow_weights": None, "mfg_checkpoint": None}
            checkpoint["hyper_parameters"] = {**hparams, "model_config": stored}


def _mean_epe(flow: Tensor, target: Tensor) -> Tensor:
    """Mean end-point error (px) over the pixels where ``target`` is known (NaN elsewhere)."""
    known = torch.isfinite(target).all(dim=1)
    epe = endpoint_error(flow, torch.nan_to_num(target))
    return (epe * known).sum() / known.sum().clamp_min(1)
