"""The learned flow's LightningModule: :class:`~mfg_lightning.flow.pwc.PWCFlowNet` trained on
rendered pairs with their exact flow (``python -m mfg_lightning.train_flow``).

Loss: PWC-Net's multi-scale one, the mean end-point error of every decoder level's flow against
the exact flow averaged down to that level (over the pixels where it is known), weighted per
level (``level_weights``, coarsest first). Augmentation: a random crop of the batch (``crop``:
the same window for every pair of a step, a new one each step) and a random left-right flip of
a pair (its flow's ``u`` negated), per sample. Its draws come from a generator derived from the
run's seed, the process's rank and the step (:meth:`FlowLitModule.augmentation_generator`), not
from torch's global one: a run resumed from a checkpoint draws what the uninterrupted run drew
(nothing to save: the step is in the checkpoint), and each DDP process draws its own.

Faults (a non-finite loss, SIGTERM, Ctrl-C) are handled as for ``train``'s module, by every DDP
process together: the run's :class:`~mfg_lightning.run.agreed_steps.AgreedSteps` callback.

Validation: the flow at the input size (:meth:`PWCFlowNet.estimate`: the finest level upsampled)
against the exact flow, pooled pixel by pixel over the split, by offset and by region:
``val/epe`` (px, all pixels, every offset), ``val/epe_+1`` …, ``val/epe/<region>``, ``val/fl``
and ``val/fl/<region>`` (KITTI's outlier rate, %), and on the non-occluded pixels alone
(KITTI's ``noc``: the pairs' visibility codes) ``val/epe_noc``, ``val/fl_noc``,
``val/epe_noc/<region>``, ``val/fl_noc/<region>``: a
:class:`~mfg_lightning.metrics.flow_quality.PooledFlowQuality`, whose sums torchmetrics adds up
across DDP processes once per validation.
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F

from mfg_lightning.flow.pwc import PWCConfig, PWCFlowNet, config_from
from mfg_lightning.metrics.flow_quality import (
    QUALITY_REGIONS,
    VISIBLE,
    PooledFlowQuality,
    region_codes,
)
from mfg_lightning.models.epoch_logs import reduced_epoch_logs

__all__ = [
    "MAX_OFFSET",
    "FlowLitModule",
    "downsample_flow",
    "endpoint_error",
    "flow_quality_metrics",
    "multiscale_loss",
    "score_flow",
]

#: Validation scores per offset up to this many frames apart (larger offsets count in "all").
MAX_OFFSET = 8


def downsample_flow(flow: torch.Tensor, factor: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean of the known vectors of each ``factor × factor`` block.

    Args:
        flow: ``(B, 2, H, W)`` pixels of the input, NaN where unknown.
        factor: the block side (``H`` and ``W`` multiples of it).

    Returns:
        ``(B, 2, H / f, W / f)`` (still input pixels; 0 where no vector of the block is known)
        and ``(B, H / f, W / f)`` bool, where some vector is known.
    """
    known = torch.isfinite(flow).all(dim=1, keepdim=True)
    if factor == 1:
        return torch.where(known, flow, 0.0), known[:, 0]
    values = F.avg_pool2d(torch.where(known, flow, 0.0), factor)
    share = F.avg_pool2d(known.float(), factor)
    mean = values / share.clamp_min(1e-6)
    return torch.where(share > 0, mean, 0.0), share[:, 0] > 0


def pair_labels(batch: dict[str, Any]) -> list[str]:
    """``"00: 1045 → 1047"`` for each pair of a batch (its sequence, source and target frame)."""
    labels = []
    for sid in batch.get("sample_id", []):
        seq, frames = str(sid).split("/")[-2:]
        src, tgt = (int(f) for f in frames.split("->"))
        labels.append(f"{seq}: {src} → {tgt}")
    return labels


def endpoint_error(flow: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` end-point errors of ``(B, 2, H, W)`` flows (same units)."""
    return torch.linalg.vector_norm(flow.float() - target.float(), dim=1)


class FlowLitModule(L.LightningModule):
    """Trains a :class:`PWCFlowNet`.

    Args:
        net: the network's :class:`~mfg_lightning.flow.pwc.PWCConfig` fields.
        optimizer: a partial optimiser (``params`` missing).
        scheduler: a partial per-step LR scheduler, or None.
        level_weights: the loss weight of each decoder level, coarsest first (as many as the
            network has decoder levels).
        crop: ``[height, width]`` of the random training crop (multiples of the network's
            divisor; None: whole frames). Validation always sees whole frames.
        flip: probability of a left-right flip of a training pair.
        image_log_every_n_steps: how often a training step hands its pairs to the figures
            callback (0: never).
        seed: the run's seed, from which the augmentation's draws are derived.
        max_consecutive_nonfinite: stop after this many non-finite losses in a row; read by
            the run's :class:`~mfg_lightning.run.agreed_steps.AgreedSteps`.
        model_config: the resolved ``model`` config this module was built from (plain data,
            saved with the hyperparameters; :func:`mfg_lightning.run.runs.build_model`).
    """

    def __init__(
        self,
        net: dict[str, Any] | None = None,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: Callable[..., Any] | None = None,
        level_weights: Sequence[float] = (0.25, 0.25, 0.5, 1.0),
        crop: Sequence[int] | None = None,
        flip: float = 0.5,
        image_log_every_n_steps: int = 500,
        seed: int = 0,
        max_consecutive_nonfinite: int = 20,
        model_config: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters("max_consecutive_nonfinite", "model_config", logger=False)
        self.seed = int(seed)
        self.config: PWCConfig = config_from(net)
        self.net = PWCFlowNet(self.config)
        levels = len(self.config.pyramid) - self.config.output_level + 1
        self.level_weights = tuple(float(w) for w in level_weights)
        if len(self.level_weights) != levels:
            raise ValueError(
                f"model.level_weights needs {levels} weights (decoder levels "
                f"{len(self.config.pyramid)} … {self.config.output_level}), got "
                f"{list(self.level_weights)}"
            )
        if not 0.0 <= flip <= 1.0:
            raise ValueError(f"model.flip must be a probability, got {flip}")
        self.flip = float(flip)
        self.crop = None if crop is None else tuple(int(v) for v in crop)
        d = self.config.divisor
        if self.crop is not None and (
            len(self.crop) != 2 or min(self.crop) < d or self.crop[0] % d or self.crop[1] % d
        ):
            raise ValueError(
                f"model.crop must be [height, width], multiples of {d}, got {list(crop)}"
            )  # fmt: skip
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.image_log_every_n_steps = int(image_log_every_n_steps)
        #: what the figures callback draws (set by the steps, consumed by the callback)
        self.figure_batch: dict[str, torch.Tensor] | None = None
        #: the validation's pooled EPE and outliers (sums; reduced across processes by compute)
        self.val_quality = PooledFlowQuality(quality_names())

    # -- steps --------------------------------------------------------------------------------

    @staticmethod
    def images(batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """The batch's ``(B, 3, H, W)`` uint8 frames as float in [0, 1]."""
        return batch["image0"].float() / 255.0, batch["image1"].float() / 255.0

    def augmentation_generator(self, batch_idx: int) -> torch.Generator:
        """The generator of a training batch's crop and flips: seeded from the run's seed, the
        process's rank, the global step and the batch's index in the epoch.

        Derived, not kept: a run resumed mid-epoch restores the step and the batch index (both in
        Lightning's checkpointed loop state), so it draws what the uninterrupted run drew with no
        generator state in the checkpoint; under DDP each process has its own draws, and they
        come back to the same rank however the processes are restarted. The batch index keeps
        the batches of one optimiser step apart under ``accumulate_grad_batches``. A CPU
        generator: the crop's corner is needed on the host, and the flips are 1 byte a pair."""
        key = (self.seed, self.global_rank, self.global_step, int(batch_idx))
        digest = hashlib.blake2b(repr(key).encode(), digest_size=8).digest()
        return torch.Generator().manual_seed(int.from_bytes(digest, "little"))

    def _augmented(
        self, batch: dict[str, Any], generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The batch's frames and exact flow, cropped and flipped with ``generator``'s draws."""
        image0, image1 = self.images(batch)
        flow = batch["flow"].float()
        if self.crop is not None:
            h, w = flow.shape[-2:]
            ch, cw = min(self.crop[0], h), min(self.crop[1], w)
            y = int(torch.randint(0, h - ch + 1, (), generator=generator))
            x = int(torch.randint(0, w - cw + 1, (), generator=generator))
            window = (..., slice(y, y + ch), slice(x, x + cw))
            image0, image1, flow = image0[window], image1[window], flow[window]
        if self.flip > 0:
            flip = (torch.rand(flow.shape[0], generator=generator) < self.flip).to(flow.device)
            f = flip.view(-1, 1, 1, 1)
            image0 = torch.where(f, image0.flip(-1), image0)
            image1 = torch.where(f, image1.flip(-1), image1)
            mirrored = flow.flip(-1) * torch.tensor([-1.0, 1.0], device=flow.device).view(
                1, 2, 1, 1
            )
            flow = torch.where(f, mirrored, flow)
        return image0, image1, flow

    def multiscale_loss(
        self, flows: Sequence[torch.Tensor], target: torch.Tensor
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """:func:`multiscale_loss` with this module's level weights."""
        return multiscale_loss(flows, target, self.level_weights)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        image0, image1, flow = self._augmented(batch, self.augmentation_generator(batch_idx))
        flows = self.net(image0, image1)
        loss, per_level = self.multiscale_loss(flows, flow)
        # this process's values, not reduced (a reduction would be a collective every step)
        self.log("train/loss", loss, prog_bar=False)
        self.log("train/epe", per_level[-1])
        every = self.image_log_every_n_steps
        if every and self.global_step % every == 0:
            size = flow.shape[-2:]
            pred = F.interpolate(flows[-1].detach().float(), size=size, mode="bilinear")
            self.figure_batch = {"stage": "train", "image0": image0, "image1": image1,
                                 "flow": flow, "pred": pred,
                                 "labels": pair_labels(batch)}  # fmt: skip
        return loss

    def on_validation_epoch_start(self) -> None:
        self.val_quality.reset()

    def validation_step(self, batch: dict[str, Any] | None, batch_idx: int) -> None:
        if batch is None:  # a DDP process with no validation pair (FlowPairsDataModule)
            return
        image0, image1 = self.images(batch)
        target = batch["flow"].float()
        pred = self.net.estimate(image0, image1)
        score_flow(self.val_quality, pred, target, batch["region"], batch["offset"],
                   visibility=batch.get("visibility"))  # fmt: skip
        if batch_idx == 0:
            self.figure_batch = {"stage": "val", "image0": image0, "image1": image1,
                                 "flow": target, "pred": pred,
                                 "labels": pair_labels(batch)}  # fmt: skip

    def on_validation_epoch_end(self) -> None:
        for name, value in flow_quality_metrics(self.val_quality, "val/").items():
            self.log(name, value, prog_bar=name == "val/epe")

    def setup(self, stage: str) -> None:
        super().setup(stage)
        reduced_epoch_logs("val/")  # the pooled quality adds up every process's sums

    # -- optimisation and checkpoints ---------------------------------------------------------

    def configure_optimizers(self) -> Any:
        if self.optimizer_factory is None:
            return torch.optim.Adam(self.parameters(), lr=1e-4)
        optimizer = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # what flow.weights=<this .ckpt> needs to rebuild the network
        checkpoint["flow_net_config"] = self.config.to_dict()


def multiscale_loss(
    flows: Sequence[torch.Tensor], target: torch.Tensor, level_weights: Sequence[float]
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """PWC-Net's multi-scale loss: ``Σ_l w_l · mean EPE_l`` (input px) over the known pixels of
    each level, and the per-level mean EPEs (coarsest first).

    Args:
        flows: every decoder level's ``(B, 2, H / 2^l, W / 2^l)`` flow, input pixels, coarsest
            first (:meth:`PWCFlowNet.forward`).
        target: ``(B, 2, H, W)`` the exact flow, input pixels, NaN where unknown.
        level_weights: one weight per level, coarsest first.
    """
    height = target.shape[-2]
    total = target.new_zeros(())
    per_level = []
    for weight, flow in zip(level_weights, flows, strict=True):
        gt, known = downsample_flow(target, height // flow.shape[-2])
        epe = endpoint_error(flow, gt)
        mean = (epe * known).sum() / known.sum().clamp_min(1)
        per_level.append(mean)
        total = total + weight * mean
    return total, per_level


def score_flow(
    quality: PooledFlowQuality,
    pred: torch.Tensor,
    target: torch.Tensor,
    region: torch.Tensor,
    offset: torch.Tensor,
    visibility: torch.Tensor | None = None,
) -> None:
    """Add a batch's end-point errors and KITTI outliers (EPE > 3 px and > 5 % of the exact
    flow's length) to ``quality``, pixel by pixel, for all known pixels, each region and each
    offset, and for the non-occluded pixels of each region (:func:`quality_names`).

    Args:
        quality: the pooled sums (:func:`quality_names`' sets).
        pred: ``(B, 2, H, W)`` the estimated flow, input pixels.
        target: ``(B, 2, H, W)`` the exact flow, input pixels, NaN where unknown.
        region: ``(B, H, W)`` the renderer's region codes.
        offset: ``(B,)`` target − source frame.
        visibility: ``(B, H, W)`` uint8 visibility codes
            (:func:`~mfg_lightning.metrics.flow_quality.visibility_codes`); the ``noc/…`` sets
            are its :data:`~mfg_lightning.metrics.flow_quality.VISIBLE` pixels. None: no
            ``noc`` set is scored (they stay empty and :func:`flow_quality_metrics` leaves
            them out).
    """
    known = torch.isfinite(target).all(dim=1)
    epe = torch.where(known, endpoint_error(pred, torch.nan_to_num(target)), 0.0)
    magnitude = torch.linalg.vector_norm(torch.nan_to_num(target), dim=1)
    outlier = (epe > 3.0) & (epe > 0.05 * magnitude) & known
    offsets = offset.view(-1, 1, 1)
    masks = {"all": known}
    for name, code in region_codes():
        if code is not None:
            masks[name] = known & (region == code)
    if visibility is not None:
        noc = visibility == VISIBLE
        masks.update({f"noc/{name}": mask & noc for name, mask in list(masks.items())})
    for off in torch.unique(offset).tolist():
        masks[f"{int(off):+d}"] = known & (offsets == off)
    quality.update(epe, outlier, masks)


def flow_quality_metrics(quality: PooledFlowQuality, prefix: str) -> dict[str, torch.Tensor]:
    """The pooled scores by name: ``<prefix>epe`` (px) and ``<prefix>fl`` (%) of all known
    pixels, ``<prefix>epe_+1`` … per offset, ``<prefix>epe/<region>`` and ``<prefix>fl/<region>``
    per region, and the same on the non-occluded pixels: ``<prefix>epe_noc``,
    ``<prefix>fl_noc``, ``<prefix>epe_noc/<region>``, ``<prefix>fl_noc/<region>`` (only where
    a set had pixels). Every DDP process's sums are added up first (a collective: every process
    calls it)."""
    with warnings.catch_warnings():
        # a process given no validation pair (FlowPairsDataModule) still takes part
        warnings.filterwarnings("ignore", message=".*was called before the ``update``")
        pooled = quality.compute()
    values = {}
    for name, (epe, fl) in pooled.items():
        noc, region = ("_noc", name[4:]) if name.startswith("noc/") else ("", name)
        if region == "all":
            values[f"{prefix}epe{noc}"] = epe
            values[f"{prefix}fl{noc}"] = fl
        elif region[0] in "+-":
            values[f"{prefix}epe_{region}"] = epe
        else:
            values[f"{prefix}epe{noc}/{region}"] = epe
            values[f"{prefix}fl{noc}/{region}"] = fl
    return values


def quality_names() -> list[str]:
    """The sets of validation pixels scored: every region of
    :data:`~mfg_lightning.metrics.flow_quality.QUALITY_REGIONS` (``all`` among them), the same
    on the non-occluded pixels (``noc/road``, …, ``noc/all``) and each offset up to
    :data:`MAX_OFFSET` frames (``+1``, ``-1``, …)."""
    return [
        *QUALITY_REGIONS,
        *(f"noc/{r}" for r in QUALITY_REGIONS),
        *(f"{o:+d}" for o in range(-MAX_OFFSET, MAX_OFFSET + 1) if o),
    ]
