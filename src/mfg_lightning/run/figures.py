"""What a researcher looks at in TensorBoard while a model trains: labelled figures.

:class:`TensorBoardFigures` draws, from what the steps of
:class:`~mfg_lightning.models.mfg_module.MFGLitModule` hand out (their output's ``"fields"``, a
:class:`~mfg_lightning.models.mfg_module.StepFields`) and from the validation's trajectories:

* ``<stage>/fields`` (``train`` at the module's ``image_log_every_n_steps``, ``val`` at every
  validation): :func:`mfg_lightning.pictures.fields.field_figure`, a row per sample with the
  input flow, ground-truth and predicted ``v_t`` and ``v_ω``, and the residual of the predicted
  egomotion (object-motion mask outlined where the module extracts one). Validation draws the
  same samples every time, spread over the validation split, so that epochs compare.
* ``val/basis``: :func:`mfg_lightning.pictures.fields.basis_figure` for the first of them: its
  sorted hidden activations with the top-k cut, and the fields of its most active units.
* ``val/trajectory`` and ``val/drift``: one validation sequence's x–z trajectory over its ground
  truth and its drift per segment length, drawn by
  :func:`mfg_lightning.pictures.plots.sequence_figures`, as ``evaluate`` draws them.
* with ``legacy_images``, the earlier image strips as well: ``<stage>/flow``, ``v_t_gt``,
  ``v_t_pred``, ``v_omega_gt``, ``v_omega_pred`` and ``hidden_activations``.

Figures go to the run's TensorBoard logger (``add_figure``) on the global-rank-zero process;
without one the callback does nothing. The training step is not slowed: it hands out
references, and the copies to the host happen here, on the drawing steps only.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import lightning as L
import numpy as np
import torch
from torch import Tensor

from mfg_lightning.models.mfg_module import MFGLitModule, StepFields
from mfg_lightning.motion.object_motion import (
    egomotion_field,
    extract_object_motion,
    residual,
)
from mfg_lightning.pictures import plots
from mfg_lightning.pictures.colours import activation_map, flows_to_rgb
from mfg_lightning.pictures.fields import FieldRow, basis_figure, field_figure
from mfg_lightning.run.runs import tensorboard_writer

log = logging.getLogger(__name__)

__all__ = ["FlowFigures", "TensorBoardFigures", "sample_plan"]

#: The trajectory figures logged at each validation, of :data:`plots.SEQUENCE_FIGURES`.
TRAJECTORY_FIGURES = ("trajectory", "drift")


@dataclass
class _Sample:
    """One sample's fields on the host, with what its residual needs."""

    label: str
    fields: dict[str, Tensor]  # flow, v_t, v_omega, v_t_pred, v_omega_pred: (2, H, W)
    hidden: Tensor  # (M,) after top-k
    valid: Tensor | None  # (H, W) flow validity
    depth: Tensor | None  # (H, W) metres


def sample_plan(n_samples: int, n_total: int, batch_size: int) -> dict[int, list[int]]:
    """``{batch index: rows}`` of ``n_samples`` samples spread evenly over ``n_total`` samples
    seen in batches of ``batch_size`` (the validation order, which is fixed): the same samples
    at every validation."""
    if n_samples <= 0 or n_total <= 0 or batch_size <= 0:
        return {}
    count = min(n_samples, n_total)
    picks = [i * n_total // count for i in range(count)]  # distinct: n_total / count >= 1
    plan: dict[int, list[int]] = {}
    for index in picks:
        plan.setdefault(index // batch_size, []).append(index % batch_size)
    return plan


def _short_label(sample_id: Any) -> str:
    """A row label: the last two parts of a sample id (sequence, frames) on two lines, frame
    numbers without their leading zeros (``train00/000009->000010``: ``train00``, ``9→10``)."""
    parts = str(sample_id).strip("/").split("/")
    frames = re.sub(r"(?<![0-9])0+(?=[0-9])", "", parts[-1]).replace("->", "→")
    return "\n".join([*parts[-2:-1], frames])


class TensorBoardFigures(L.Callback):
    """Labelled field, basis and trajectory figures in TensorBoard (module docstring).

    Args:
        num_samples: the rows of the field figures (0: no field or basis figures).
        basis_units: how many of the most active units the basis figure shows (0: none).
        trajectory: log the trajectory and drift figures of a validation sequence.
        trajectory_sequence: which validation sequence (None: the longest, ties by name).
        trajectory_align: its alignment before it is drawn, as ``evaluate``'s ``eval.align``
            (``none``: as predicted).
        legacy_images: also log the earlier image strips (``<stage>/flow``, ``<stage>/v_t_gt``,
            ..., ``<stage>/hidden_activations``) for readers of those tags.
    """

    def __init__(
        self,
        num_samples: int = 4,
        basis_units: int = 5,
        trajectory: bool = True,
        trajectory_sequence: str | None = None,
        trajectory_align: str = "none",
        legacy_images: bool = False,
    ) -> None:
        from mfg_lightning.metrics.alignment import configured_align

        if num_samples < 0 or basis_units < 0:
            raise ValueError(
                "callbacks.figures.num_samples and basis_units must be >= 0, got "
                f"{num_samples} and {basis_units}"
            )
        self.num_samples = int(num_samples)
        self.basis_units = int(basis_units)
        self.trajectory = bool(trajectory)
        self.trajectory_sequence = None if trajectory_sequence is None else str(trajectory_sequence)
        self.trajectory_align = configured_align(
            trajectory_align, "callbacks.figures.trajectory_align"
        )
        self.legacy_images = bool(legacy_images)
        self._plan: dict[int, list[int]] = {}
        self._samples: list[_Sample] = []
        self._drawn_evaluation: Any = None

    # -- where and when ------------------------------------------------------------------

    @staticmethod
    def _writer(trainer: L.Trainer) -> Any | None:
        if not trainer.is_global_zero or trainer.sanity_checking:
            return None
        return tensorboard_writer(trainer)

    @staticmethod
    def _scalar_step(trainer: L.Trainer) -> int:
        """The step Lightning gives the scalars logged now (``val/*`` of this validation: the
        training steps done less one, as ``train/*`` counts from 0), so that a figure and the
        numbers it belongs to share TensorBoard's step slider."""
        loop = getattr(trainer.fit_loop, "epoch_loop", None)
        return int(getattr(loop, "_batches_that_stepped", trainer.global_step))

    @staticmethod
    def _validation_plan(trainer: L.Trainer, n_samples: int) -> dict[int, list[int]]:
        """Where the fixed validation samples are: spread over the batches validated (a
        ``limit_val_batches`` counts), or the first rows of the first batch when the loader
        has no length."""
        loaders = trainer.val_dataloaders
        loader = loaders[0] if isinstance(loaders, list | tuple) else loaders
        batch_size = getattr(loader, "batch_size", None)
        batches = trainer.num_val_batches[0] if trainer.num_val_batches else 0
        try:
            total = min(len(loader.dataset), int(batches) * int(batch_size))
        except (TypeError, AttributeError, OverflowError, ValueError):
            return {0: list(range(n_samples))}
        return sample_plan(n_samples, total, int(batch_size))

    # -- training ------------------------------------------------------------------------

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, *_: Any
    ) -> None:
        fields = _step_fields(outputs)
        if fields is None or not self.num_samples or (writer := self._writer(trainer)) is None:
            return
        samples = _host_samples(fields, batch, range(self.num_samples))
        self._log_fields(writer, pl_module, "train", samples, fields.step, f"step {fields.step}")

    # -- validation ----------------------------------------------------------------------

    def on_validation_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._samples = []
        wanted = self.num_samples if self._writer(trainer) is not None else 0
        self._plan = self._validation_plan(trainer, wanted) if wanted else {}

    def on_validation_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        rows = self._plan.get(batch_idx) if dataloader_idx == 0 else None
        fields = _step_fields(outputs)
        if rows and fields is not None:
            self._samples += _host_samples(fields, batch, rows)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # After the module's on_validation_epoch_end: its trajectory evaluation is complete.
        writer = self._writer(trainer)
        if writer is None:
            return
        step, done = self._scalar_step(trainer), f"after {trainer.global_step} steps"
        if self._samples:
            self._log_fields(writer, pl_module, "val", self._samples, step, done)
            if self.basis_units and isinstance(pl_module, MFGLitModule):
                self._log_basis(writer, pl_module, self._samples[0], step, done)
        if self.trajectory:
            self._log_trajectory(writer, pl_module, step)
        self._samples = []

    # -- drawing -------------------------------------------------------------------------

    def _log_fields(
        self,
        writer: Any,
        pl_module: L.LightningModule,
        stage: str,
        samples: list[_Sample],
        step: int,
        when: str,
    ) -> None:
        config = getattr(pl_module, "object_motion", None)
        rows, title = _field_rows(samples, config)
        figure = field_figure(rows, title, f"{stage} fields, {when} (pixels per frame)")
        writer.add_figure(f"{stage}/fields", figure, step)
        if self.legacy_images:
            _log_legacy_images(writer, stage, samples, step)

    @torch.no_grad()
    def _log_basis(
        self, writer: Any, pl_module: MFGLitModule, sample: _Sample, step: int, when: str
    ) -> None:
        """The basis figure of one validation sample: its activations before top-k (encoded
        again: the step's are after it) and its most active units' contributions."""
        net = pl_module.net
        weight = net.decoder_t.weight
        flow = sample.fields["flow"][None].to(weight.device, weight.dtype)
        hidden = net.encode(flow)[0][0].float()
        k = min(self.basis_units, int(hidden.numel()))
        values, units = hidden.topk(k)
        one_hot = torch.zeros(k, hidden.numel(), device=hidden.device)
        one_hot[torch.arange(k, device=hidden.device), units] = 1.0
        basis_t, basis_w = net.decode(one_hot)  # each unit's basis fields (activation 1)
        scale = values[:, None, None, None]
        top_k = pl_module.top_k
        kept = None if top_k >= 1 else max(1, round(top_k * hidden.numel()))
        fig = basis_figure(
            hidden.cpu().numpy(),
            units.tolist(),
            list((scale * basis_t).cpu()),
            list((scale * basis_w).cpu()),
            kept=kept,
            title=f"val sample {sample.label.replace(chr(10), ' ')}, {when}\n"
            f"its {k} most active units: activation × basis field",
        )
        writer.add_figure("val/basis", fig, step)

    def _log_trajectory(self, writer: Any, pl_module: L.LightningModule, step: int) -> None:
        """The validation trajectory and its drift, as ``evaluate`` draws them."""
        stages = getattr(pl_module, "evaluation", {})
        evaluation = stages["val"].last_result if "val" in stages else None
        if evaluation is None or evaluation is self._drawn_evaluation or not evaluation.sequences:
            return
        self._drawn_evaluation = evaluation
        sequences = evaluation.sequences
        name = self.trajectory_sequence
        if name not in sequences:
            if name is not None:
                log.warning(
                    "callbacks.figures.trajectory_sequence=%s is not a validation sequence "
                    "(%s): drawing the longest",
                    name,
                    ", ".join(sorted(sequences)),
                )
                self.trajectory_sequence = None
            name = max(sorted(sequences), key=lambda s: len(sequences[s].frames))
        poses = sequences[name]
        curves = plots.trajectory_curves(poses.pred, poses.gt, self.trajectory_align)
        figures = plots.sequence_figures(
            name, {"MFG": curves}, self.trajectory_align, kinds=TRAJECTORY_FIGURES
        )
        for kind, fig in figures.items():
            writer.add_figure(f"val/{kind}", fig, step)


def _step_fields(outputs: Any) -> StepFields | None:
    """The fields a training or validation step handed out (None: it handed none out)."""
    fields = outputs.get("fields") if isinstance(outputs, dict) else None
    return fields if isinstance(fields, StepFields) else None


def _host_samples(fields: StepFields, batch: Any, rows: Iterable[int]) -> list[_Sample]:
    """Those of ``rows`` that the step's batch has, copied to the host."""
    n = int(fields.flow.shape[0])
    return [_host_sample(fields, batch, r) for r in rows if r < n]


def _host_sample(fields: StepFields, batch: Any, row: int) -> _Sample:
    """Row ``row`` of a step's fields and batch, copied to the host."""
    batch = batch if isinstance(batch, dict) else {}
    ids = batch.get("sample_id")
    label = _short_label(ids[row]) if ids is not None and row < len(ids) else f"sample {row}"

    def host(x: Any) -> Tensor | None:
        return x[row].detach().float().cpu() if isinstance(x, Tensor) else None

    names = ("flow", "v_t", "v_omega", "v_t_pred", "v_omega_pred")
    return _Sample(
        label,
        {name: host(getattr(fields, name)) for name in names},
        host(fields.hidden),
        host(batch.get("flow_valid")),
        host(batch.get("depth")),
    )


def _field_rows(samples: list[_Sample], config: Any) -> tuple[list[FieldRow], str]:
    """The rows of the field figure and the title of its residual column.

    With depth, the residual is ``flow − ṽ`` with ``ṽ = ρ ṽ_t + ṽ_ω`` (paper §4), and the
    module's object-motion filters (when it has them) give the mask. Without depth no ``ρ`` is
    known: the residual is then the part of ``flow − ṽ_ω`` across ``ṽ_t``, which no depth
    explains."""
    with_depth = all(s.depth is not None for s in samples)
    rows = []
    for s in samples:
        f = s.fields
        mask = None
        if with_depth:
            args = (f["flow"][None], f["v_t_pred"][None], f["v_omega_pred"][None], s.depth[None])
            if config is not None:
                valid = None if s.valid is None else s.valid[None]
                extracted = extract_object_motion(*args, config, valid=valid)
                r, mask = extracted.residual[0], extracted.mask[0].numpy()
            else:
                r = residual(args[0], egomotion_field(*args[1:]))[0]
        else:
            r = _across_translation(f["flow"] - f["v_omega_pred"], f["v_t_pred"])
        rows.append(FieldRow(s.label, f["flow"], f["v_t"], f["v_t_pred"], f["v_omega"],
                             f["v_omega_pred"], r.numpy(), mask))  # fmt: skip
    if not with_depth:
        return rows, "residual\n⊥ v_t (no depth)"
    return rows, "residual, mask\noutlined" if config is not None else "residual\nflow − ṽ"


def _across_translation(rest: Tensor, v_t: Tensor) -> Tensor:
    """``rest`` less its component along ``v_t`` per pixel: what no inverse depth ρ in
    ``rest = ρ v_t`` can explain. ``(2, H, W)`` each."""
    norm2 = (v_t * v_t).sum(0, keepdim=True)
    along = (rest * v_t).sum(0, keepdim=True) / norm2.clamp_min(1e-12)
    return rest - torch.where(norm2 > 0, along, 0.0) * v_t


def _log_legacy_images(writer: Any, stage: str, samples: list[_Sample], step: int) -> None:
    """The earlier image strips: the flow, ground-truth and predicted fields (Middlebury
    colours, ground truth and prediction normalised together) and the hidden activations."""

    def stack(name: str) -> Tensor:
        return torch.stack([s.fields[name] for s in samples])

    n = len(samples)
    writer.add_images(f"{stage}/flow", flows_to_rgb(stack("flow")), step, dataformats="NCHW")
    for name in ("v_t", "v_omega"):
        rgb = flows_to_rgb(torch.cat([stack(name), stack(f"{name}_pred")]))
        writer.add_images(f"{stage}/{name}_gt", rgb[:n], step, dataformats="NCHW")
        writer.add_images(f"{stage}/{name}_pred", rgb[n:], step, dataformats="NCHW")
    maps = np.stack([activation_map(s.hidden) for s in samples]).transpose(0, 3, 1, 2)
    writer.add_images(f"{stage}/hidden_activations", maps, step, dataformats="NCHW")


class FlowFigures(L.Callback):
    """The learned flow's figures (``python -m mfg_lightning.train_flow``): ``<stage>/flow``,
    :func:`mfg_lightning.pictures.fields.flow_estimate_figure` of the first ``num_samples``
    pairs of a batch (both frames, the exact and the estimated flow, the error), from what
    :class:`~mfg_lightning.models.flow_module.FlowLitModule`'s steps hand out: a training
    step every ``model.image_log_every_n_steps``, the first validation batch at every
    validation (the same pairs every time). Nothing without a TensorBoard logger.
    """

    def __init__(self, num_samples: int = 3) -> None:
        self.num_samples = int(num_samples)

    def _draw(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        from mfg_lightning.pictures.fields import flow_estimate_figure

        batch = getattr(pl_module, "figure_batch", None)
        pl_module.figure_batch = None  # type: ignore[assignment]
        writer = tensorboard_writer(trainer)
        if batch is None or writer is None or not trainer.is_global_zero or self.num_samples < 1:
            return
        n = min(self.num_samples, batch["flow"].shape[0])

        def rgb(images: Tensor) -> list[np.ndarray]:
            return list(
                (images[:n].float().clamp(0, 1) * 255).byte().permute(0, 2, 3, 1).cpu().numpy()
            )

        figure = flow_estimate_figure(
            rgb(batch["image0"]),
            rgb(batch["image1"]),
            list(batch["flow"][:n].float().cpu().numpy()),
            list(batch["pred"][:n].float().cpu().numpy()),
            (batch.get("labels") or [f"pair {i}" for i in range(n)])[:n],
            title=f"{batch['stage']}, step {trainer.global_step}",
        )
        writer.add_figure(f"{batch['stage']}/flow", figure, trainer.global_step, close=True)

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any
    ) -> None:
        if getattr(pl_module, "figure_batch", None) is not None:
            self._draw(trainer, pl_module)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.sanity_checking:
            self._draw(trainer, pl_module)
