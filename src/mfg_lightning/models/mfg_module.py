"""The LightningModule that trains and evaluates MFG.

Training: ground-truth translational (ρ = 1) and rotational fields are built from each sample's
relative pose with :mod:`mfg_lightning.core.geometry`, and the network is fit with
``w_t L_t + w_ω L_ω + w_s L_s`` (:class:`mfg_lightning.models.losses.MFGLoss`). Validation and test:
the predicted fields are turned into ``(t̃, ω̃)`` in closed form and scored per frame.

Precision (``trainer.precision``, :func:`check_precision`): ``32-true``, ``bf16-mixed`` or
``16-mixed``. Under the mixed ones the encoder runs in the low precision and everything else
(fields, geometry, losses, object motion, metrics) in float32. ``16-mixed`` starts its GradScaler
at ``fp16_init_scale`` (:func:`fit_grad_scaler`) instead of torch's 65 536, which overflows fp16
in the first steps.

No host synchronisation in a training step outside the logging steps: counts (masked flow pixels,
skipped steps) stay tensors on the device and are read when they are logged; a non-finite loss is
skipped inside the fused optimiser's kernel (``found_inf``, as GradScaler does) instead of being
tested on the host. Evaluation batches have none either (the SVD of the per-frame errors may
wait for cuSOLVER's error check).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, NamedTuple

import lightning as L
import torch
from lightning.pytorch.plugins.precision import MixedPrecision, Precision
from torch import Tensor, nn
from torchmetrics import SumMetric

from mfg_lightning.core import geometry
from mfg_lightning.data.sample import sanitize_flow
from mfg_lightning.metrics.evaluator import EvaluationResult, TrajectoryEvaluator
from mfg_lightning.metrics.frame_errors import FiniteMean, constant_motion_errors, frame_errors
from mfg_lightning.metrics.object_motion import ObjectMotionScores
from mfg_lightning.models.losses import LossTerms, MFGLoss
from mfg_lightning.models.mfg import MFG, MFGOutput, validate_top_k
from mfg_lightning.motion.object_motion import (
    ObjectMotionConfig,
    extract_object_motion,
    threshold_baseline,
)

log = logging.getLogger(__name__)


class NonFiniteLossError(RuntimeError):
    """Training produced non-finite losses too many times in a row."""


#: ``trainer.precision`` values the module trains and evaluates under (Lightning's aliases
#: ``32``, ``bf16`` and ``16`` name the same).
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed")
_PRECISION_ALIASES = {"32": "32-true", "bf16": "bf16-mixed", "16": "16-mixed"}

#: The batch key under which :meth:`MFGLitModule.transfer_batch_to_device` keeps the batch's
#: intrinsics on the host, so that the closed-form recovery groups samples by intrinsics without
#: reading them back from the device.
HOST_INTRINSICS = "intrinsics_host"

#: The initial GradScaler scale under ``16-mixed``. Measured at the first step (fp16 autocast,
#: default network, 48 × 128, scale 1): the largest gradient of an fp16 tensor is 76–94 at batch
#: 16 (quick start, 3 seeds) and 332–1260 at batch 1 (the paper's, 6 samples), always on the
#: hidden units. torch's default 65 536 overflows fp16 (max 65 504) there, so the first 7
#: (batch 16) or 11 (batch 1) steps would be skipped while the scaler halves; 16 leaves 2.5×
#: headroom at batch 1 and 40× at batch 16, and the scaler grows from there.
FP16_INIT_SCALE = 16.0
_TORCH_DEFAULT_INIT_SCALE = 2.0**16


#: ``trainer.precision=auto`` (the default): the precision measured to be the faster one at
#: float32's accuracy where the hardware runs it natively (bench/results/precision.md: the quick
#: start under ``bf16-mixed``, 3 seeds, test ATE 0.0079 ± 0.0004 m against float32's
#: 0.0084 ± 0.0004 m, 1.16× faster on a CPU with AVX512-BF16), float32 elsewhere.
PRECISION_AUTO = "auto"


def cpu_has_native_bf16() -> bool:
    """Whether this CPU computes bfloat16 natively (AVX512-BF16 or AMX), as oneDNN uses it.

    torch exposes the check only as ``torch.cpu._is_avx512_bf16_supported`` /
    ``_is_amx_tile_supported`` (private, present since torch 2.1); without them the answer is
    False, so such a machine keeps float32.
    """
    checks = [getattr(torch.cpu, name, None) for name in
              ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]  # fmt: skip
    try:
        return any(bool(check()) for check in checks if check is not None)
    except Exception:  # an unexpected torch build: no native bf16 assumed
        return False


def resolve_precision(precision: Any, accelerator: Any = "auto") -> Any:
    """``trainer.precision`` with ``auto`` made concrete; any other value as it is.

    ``auto`` is ``bf16-mixed`` for a run on a CPU that computes bfloat16 natively
    (:func:`cpu_has_native_bf16`) and ``32-true`` otherwise, GPUs included (bf16 has been
    measured against float32 on a CPU only; ``trainer.precision=bf16-mixed`` chooses it there).

    Args:
        precision: the configured ``trainer.precision``.
        accelerator: the configured ``trainer.accelerator`` (``auto``: a GPU if CUDA has one).
    """
    if str(precision) != PRECISION_AUTO:
        return precision
    name = str(accelerator)
    on_cpu = name == "cpu" or (name == "auto" and not torch.cuda.is_available())
    return "bf16-mixed" if on_cpu and cpu_has_native_bf16() else "32-true"


def check_precision(precision: Any) -> str:
    """``trainer.precision`` in Lightning's spelling if the module supports it.

    Raises:
        ValueError: naming ``trainer.precision`` for anything else, in particular ``bf16-true``
            and ``16-true``, which cast the weights and, with them, every batch's poses,
            intrinsics and depth and the whole geometry to the low precision.
    """
    name = str(precision)
    name = _PRECISION_ALIASES.get(name, name)
    if name in PRECISIONS:
        return name
    if name.endswith("-true"):
        reason = (
            f"it casts the weights, every batch's poses, intrinsics and depth and the geometry "
            f"to {name.removesuffix('-true')} bits (recovering (t, ω) in bfloat16 errs by up to "
            "2e-3 m, a tenth of the measured ATE); use a -mixed precision, which runs the encoder "
            "in the low precision and the fields, geometry, losses and metrics in float32"
        )
    else:
        reason = "not a precision this model supports"
    raise ValueError(
        f"trainer.precision={precision} is refused: {reason}; choose one of {', '.join(PRECISIONS)}"
    )


def fit_grad_scaler(plugin: Precision, init_scale: float = FP16_INIT_SCALE) -> bool:
    """Start a ``16-mixed`` plugin's GradScaler at ``init_scale`` (:data:`FP16_INIT_SCALE`).

    Only a scaler that still has torch's default initial scale (the one Lightning creates) and
    has not run yet is replaced; one given explicitly is kept. Returns whether it was replaced.
    """
    scaler = getattr(plugin, "scaler", None)
    if not isinstance(plugin, MixedPrecision) or scaler is None:
        return False
    if not scaler.is_enabled() or scaler.get_scale() != _TORCH_DEFAULT_INIT_SCALE:
        return False
    plugin.scaler = torch.amp.GradScaler(plugin.device, init_scale=init_scale)
    return True


class StepFields(NamedTuple):
    """What a training or validation step hands to the figure callback
    (:class:`mfg_lightning.run.figures.TensorBoardFigures`) under its output's ``"fields"``
    key: the batch's fields as detached tensors on the model's device, ``(B, 2, H, W)`` pixels.

    Attributes:
        step: the global step the fields belong to.
        flow: the (masked) input flow.
        v_t, v_omega: the ground-truth translational (ρ = 1 m⁻¹) and rotational fields.
        v_t_pred, v_omega_pred: the predicted ones.
        hidden: ``(B, M)`` the hidden activations the prediction was decoded from.
    """

    step: int
    flow: Tensor
    v_t: Tensor
    v_omega: Tensor
    v_t_pred: Tensor
    v_omega_pred: Tensor
    hidden: Tensor


class _DeferredCounts:
    """Per-batch counts kept as device tensors beside their batch's sample ids, read back in
    one transfer when they are reported (a logging step, the end of an epoch)."""

    #: report anyway after this many batches, so that the list stays short
    LIMIT = 512

    def __init__(self) -> None:
        self._pending: list[tuple[Tensor, list]] = []

    def add(self, count: Tensor, batch: dict[str, Any]) -> bool:
        """Keep ``count`` (a 0-dim tensor); True when the list is full and should be read."""
        self._pending.append((count.detach(), list(batch.get("sample_id", []))))
        return len(self._pending) >= self.LIMIT

    def read(self) -> list[tuple[int, list]]:
        """``(count, sample ids)`` of every kept batch with a non-zero count; empties the list
        (one host synchronisation)."""
        if not self._pending:
            return []
        counts = torch.stack([c for c, _ in self._pending]).tolist()
        out = [(int(n), ids) for n, (_, ids) in zip(counts, self._pending, strict=True) if n]
        self._pending.clear()
        return out


class MFGLitModule(L.LightningModule):
    """MFG with its losses, optimiser and evaluation.

    Args:
        net: the :class:`MFG` network.
        loss: the :class:`MFGLoss`.
        optimizer: a partial optimiser constructor taking the parameters
            (paper: Adam, lr 1e-5, betas (0.99, 0.999)).
        scheduler: optional partial LR-scheduler constructor taking the optimiser.
        top_k: fraction of hidden units kept at evaluation (None: all); overrides ``net.top_k``.
        image_log_every_n_steps: every how many training steps the step hands its fields to
            the figure callback (:class:`mfg_lightning.run.figures.TensorBoardFigures`), which
            draws them; validation steps hand theirs at every validation. 0: never (no field or
            basis figures).
        max_consecutive_nonfinite: stop after this many non-finite losses in a row (checked at
            the logging steps and at the end of training).
        object_motion: object-motion filter parameters; when set, validation and test on
            batches that carry depth and a ground-truth object mask also score the extracted
            object motion (``<stage>/object/*``) and the plain-threshold baseline
            (``<stage>/object_baseline/*``). None disables it.
        fp16_init_scale: the initial GradScaler scale under ``trainer.precision=16-mixed``
            (:data:`FP16_INIT_SCALE`, measured).
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
        fp16_init_scale: float = FP16_INIT_SCALE,
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
        if not (fp16_init_scale > 0):
            raise ValueError(f"model.fp16_init_scale must be positive, got {fp16_init_scale}")
        self.fp16_init_scale = float(fp16_init_scale)
        self._consecutive_nonfinite = 0
        # The in-optimiser skip of a non-finite loss (see training_step): device tensors.
        self._nonfinite_run: Tensor | int = 0
        self._skipped_steps: Tensor | int = 0
        self._skipped_reported = 0
        self._window_finite: Tensor | None = None
        self._found_inf: Tensor | None = None
        self._flow_warnings = {s: _DeferredCounts() for s in ("train", "val", "test")}
        self._score_baseline: bool | None = None
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
                            name: FiniteMean()
                            for name in (
                                "trans_err",
                                "rot_err",
                                "loss",
                                "active_fraction",
                                "baseline_trans_err",
                                "baseline_rot_err",
                            )
                        },
                        # counts, never NaN: no NaN check (a device synchronisation per batch)
                        "nonfinite_flow_pixels": SumMetric(nan_strategy="disable"),
                    }
                )
                for stage in ("val", "test")
            }
        )
        #: non-finite input-flow pixels masked during training so far (this process): a tensor on
        #: the model's device once training has started
        self.nonfinite_flow_pixels: Tensor | int = 0
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

    def _prepare(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Masked input flow, ground-truth fields and intrinsics of a batch, and the number of
        non-finite flow pixels that were masked (a 0-dim tensor: nothing is read back)."""
        flow, _, n_bad = sanitize_flow(batch["flow"], batch["flow_valid"])
        K = batch["intrinsics"]
        height, width = flow.shape[-2:]
        t, w = geometry.pose_to_motion(batch["pose"].to(flow))
        v_t = geometry.translational_field(t, K, height, width)
        v_w = geometry.rotational_field(w, K, height, width)
        return flow, v_t, v_w, K, n_bad

    def _loss(self, out: MFGOutput, v_t: Tensor, v_w: Tensor) -> LossTerms:
        return self.loss_fn(out.v_t, out.v_omega, v_t, v_w, out.hidden)

    def _warn_masked_flow(self, stage: str) -> None:
        """Warn about the batches whose non-finite flow pixels were masked since the last report
        (one read-back of their counts)."""
        for n, ids in self._flow_warnings[stage].read():
            log.warning("masked %d non-finite flow pixels in %s", n, _ids({"sample_id": ids}))

    def transfer_batch_to_device(
        self, batch: Any, device: torch.device, dataloader_idx: int
    ) -> Any:
        """Lightning's batch transfer, skipped on a CPU: the batches are built on the CPU, so
        the transfer is a no-op whose recursive walk of the batch dict still costs ~0.35 ms per
        step, ~1.5 % of a batch-1 step (bench/results/throughput.md). On another device the
        batch's CPU intrinsics stay beside it under :data:`HOST_INTRINSICS`: the closed-form
        recovery groups samples by their intrinsics' values, which would otherwise be read back
        from the device in every evaluation batch."""
        if device.type == "cpu":
            return batch
        host = batch.get("intrinsics") if isinstance(batch, dict) else None
        moved = super().transfer_batch_to_device(batch, device, dataloader_idx)
        if isinstance(host, Tensor) and host.device.type == "cpu" and isinstance(moved, dict):
            moved[HOST_INTRINSICS] = host
        return moved

    def setup(self, stage: str) -> None:
        """Refuse a precision the module does not support and fit ``16-mixed``'s GradScaler
        (before a resumed run restores the scaler's state)."""
        trainer = self._trainer
        if trainer is None:
            return
        check_precision(trainer.precision)
        if fit_grad_scaler(trainer.precision_plugin, self.fp16_init_scale):
            log.info(
                "16-mixed: GradScaler starts at %g (model.fp16_init_scale)", self.fp16_init_scale
            )

    # -- training ----------------------------------------------------------------------------

    def _writes_logs_this_step(self) -> bool:
        """Whether the loggers write this training step's values (every
        ``trainer.log_every_n_steps``): the step-only diagnostics are logged just then, since
        each ``self.log`` costs Python time that shows at batch 1 (bench/results/throughput.md)
        and the values of the other steps would never be written. The deferred counts are read
        back from the device then too."""
        connector = getattr(self._trainer, "_logger_connector", None)
        return bool(getattr(connector, "should_update_logs", True))

    def _learning_rate(self) -> float:
        """The first parameter group's current learning rate (NaN outside a fit)."""
        trainer = self._trainer
        if trainer is None or not trainer.optimizers:
            return float("nan")
        return float(trainer.optimizers[0].param_groups[0]["lr"])

    def _skips_in_the_optimiser(self) -> bool:
        """Whether a non-finite loss can be skipped inside the optimiser's step: one fused
        optimiser (Adam, AdamW, SGD with ``fused=True``, the default config's), whose kernel
        leaves weights and state untouched when told ``found_inf``."""
        trainer = self._trainer
        if trainer is None or not self.automatic_optimization or len(trainer.optimizers) != 1:
            return False
        return bool(trainer.optimizers[0].defaults.get("fused"))

    def training_step(
        self, batch: dict[str, Any] | None, batch_idx: int
    ) -> Tensor | dict[str, Any] | None:
        if batch is None:  # every sample of the batch was skipped as unreadable
            return None
        flow, v_t, v_w, _, n_bad = self._prepare(batch)
        self.nonfinite_flow_pixels = self.nonfinite_flow_pixels + n_bad
        full = self._flow_warnings["train"].add(n_bad, batch)
        out = self(flow)
        terms = self._loss(out, v_t, v_w)
        if self._skips_in_the_optimiser():
            # No host check: the step's finiteness goes to the fused optimiser as found_inf
            # (on_before_optimizer_step), which skips the update on the device; the counts are
            # read at the logging steps (_report_nonfinite).
            finite = torch.isfinite(terms.total.detach())
            if self._trainer.world_size > 1:
                # One verdict for every process: their gradients are averaged, so one process's
                # NaN reaches all of them, and all must skip (and count) the step together.
                finite = _finite_on_every_process(finite, self._trainer.strategy)
            self._window_finite = (
                finite if self._window_finite is None else self._window_finite & finite
            )
            self._nonfinite_run = torch.where(finite, 0, self._nonfinite_run + 1)
            self._skipped_steps = self._skipped_steps + (~finite).long()
        elif not torch.isfinite(terms.total):
            # Any other optimiser: tested on the host (one synchronisation per step). Returning
            # None skips backward and the optimiser step: a NaN never reaches the weights.
            self._consecutive_nonfinite += 1
            log.warning("non-finite loss (%s) on %s: step skipped", terms.total.item(), _ids(batch))
            self.log("train/skipped_steps", float(self._consecutive_nonfinite), on_step=True)
            if self._consecutive_nonfinite >= self.max_consecutive_nonfinite:
                raise NonFiniteLossError(
                    f"{self._consecutive_nonfinite} consecutive non-finite losses; last samples: "
                    f"{_ids(batch)}"
                )
            return None
        else:
            self._consecutive_nonfinite = 0
        bs = flow.shape[0]
        if full:
            self._warn_masked_flow("train")
        if self._writes_logs_this_step():
            # Only on the steps the loggers write (the progress bar's loss refreshes then too):
            # a logged value costs ~0.7 ms, 2-3 % of a batch-1 step on a CPU (bench/throughput.py).
            self._warn_masked_flow("train")
            self._report_nonfinite(batch)
            self.log("train/loss", terms.total, prog_bar=True, batch_size=bs)
            values = {
                "train/l_t": terms.l_t.mean(),
                "train/l_omega": terms.l_omega.mean(),
                "train/l_s": terms.l_s.mean(),
                "train/w_t": terms.w_t.mean(),
                "train/w_omega": terms.w_omega.mean(),
                "train/active_fraction": _active_fraction(out.hidden),
                "train/nonfinite_flow_pixels": _as_float(self.nonfinite_flow_pixels),
                "train/lr": self._learning_rate(),
            }
            if isinstance(self._skipped_steps, Tensor):  # the in-optimiser skips so far
                values["train/skipped_steps"] = self._skipped_steps.float()
            self.log_dict(values, batch_size=bs)
        if self.image_log_every_n_steps and self.global_step % self.image_log_every_n_steps == 0:
            # The pictures are the figure callback's: it gets the fields from the step's output
            # (references, no copy and no host read here).
            return {"loss": terms.total, "fields": self._step_fields(flow, v_t, v_w, out)}
        return terms.total

    def _report_nonfinite(self, batch: dict[str, Any] | None) -> None:
        """Read the in-optimiser skip counts (a host synchronisation: logging steps and the end
        of training only), warn about new skips and stop a run that keeps producing them."""
        if not isinstance(self._skipped_steps, Tensor):
            return
        run, skipped = torch.stack([self._nonfinite_run, self._skipped_steps]).tolist()
        ids = _ids(batch) if batch is not None else "<end of training>"
        if skipped > self._skipped_reported:
            log.warning(
                "non-finite loss in %d step(s) since the last report: skipped in the optimiser "
                "(latest samples: %s)",
                skipped - self._skipped_reported,
                ids,
            )
        self._skipped_reported = skipped
        if run >= self.max_consecutive_nonfinite:
            raise NonFiniteLossError(f"{run} consecutive non-finite losses; last samples: {ids}")

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Hand the step's finiteness to the fused optimiser (``found_inf``: 1 skips the update
        of weights and state on the device). Under ``16-mixed`` the GradScaler sets its own
        ``found_inf``, which a non-finite loss trips as well (its gradients are non-finite)."""
        if self._window_finite is None:
            return
        if optimizer.defaults.get("fused"):
            self._found_inf = (~self._window_finite).to(torch.float32)
            optimizer.found_inf = self._found_inf
        self._window_finite = None

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        # found_inf is read by this step only; a stale one would skip later steps.
        if self._found_inf is not None:
            for optimizer in self.trainer.optimizers:
                if getattr(optimizer, "found_inf", None) is self._found_inf:
                    del optimizer.found_inf
            self._found_inf = None

    def on_train_end(self) -> None:
        self._warn_masked_flow("train")
        self._report_nonfinite(None)

    # -- evaluation --------------------------------------------------------------------------

    def _evaluate(self, batch: dict[str, Any] | None, stage: str) -> dict[str, Tensor] | None:
        if batch is None:
            return None
        flow, v_t, v_w, K, n_bad = self._prepare(batch)
        if self._flow_warnings[stage].add(n_bad, batch):
            self._warn_masked_flow(stage)
        out = self(flow)
        terms = self._loss(out, v_t, v_w)
        t, w = geometry.recover_motion(out.v_t, out.v_omega, batch.get(HOST_INTRINSICS, K))
        trans_err, rot_err = frame_errors(t, w, batch["pose"])
        m = self.eval_metrics[stage]
        m["trans_err"].update(trans_err)
        m["rot_err"].update(rot_err)
        # Weighted by batch size: per-sample means, whatever the batches (or DDP shards) are.
        bs = flow.shape[0]
        m["loss"].update(terms.total, weight=bs)
        m["active_fraction"].update(_active_fraction(out.hidden), weight=bs)
        m["nonfinite_flow_pixels"].update(n_bad)
        if self._score_baseline is None:  # outside an epoch (a direct call): read it now
            self._score_baseline = bool(self.has_mean_motion)
        if self._score_baseline:
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
        self._warn_masked_flow(stage)
        self._score_baseline = None
        # Which metrics any process updated, agreed on by all of them: compute() is a
        # collective under DDP, so a process that saw no batch (an evaluation split smaller than
        # the number of processes) must still take part, or the others wait for it forever.
        updated = self._updated_on_any_process(stage)
        for name, metric in self.eval_metrics[stage].items():
            if updated[name]:
                self.log(
                    f"{stage}/{name}", metric.compute(), prog_bar=name in ("trans_err", "rot_err")
                )
                nan = int(getattr(metric, "nan_count", 0))
                if nan:
                    log.warning("%d NaN values left out of %s/%s", nan, stage, name)
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
            if updated[f"{stage}_{method}"]:
                self.log_dict({f"{stage}/{method}/{k}": v for k, v in metric.compute().items()})
            metric.reset()

    def _updated_on_any_process(self, stage: str) -> dict[str, bool]:
        """``{metric name: updated by some process}`` for the stage's metrics (the object-motion
        scores under ``<stage>_<method>``): one ``all_reduce`` of their update counts at the end
        of an evaluation epoch, none in a single process."""
        metrics: dict[str, Any] = dict(self.eval_metrics[stage].items())
        for method in ("object", "object_baseline"):
            metrics[f"{stage}_{method}"] = self.object_scores[f"{stage}_{method}"]
        counts = [int(m.update_count) for m in metrics.values()]
        dist = torch.distributed
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            # On the module's device: NCCL reduces CUDA tensors only.
            total = torch.tensor(counts, dtype=torch.long, device=self.device)
            dist.all_reduce(total, op=dist.ReduceOp.SUM)
            counts = [int(c) for c in total.tolist()]
        return {name: count > 0 for name, count in zip(metrics, counts, strict=True)}

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

    def _start_eval_epoch(self) -> None:
        # Whether the mean-motion baseline is scored, read once per epoch, not once per batch.
        self._score_baseline = bool(self.has_mean_motion)

    def on_validation_epoch_start(self) -> None:
        self._start_eval_epoch()

    def on_test_epoch_start(self) -> None:
        self._start_eval_epoch()

    def validation_step(
        self, batch: dict[str, Any] | None, batch_idx: int
    ) -> dict[str, StepFields] | None:
        """Score the batch; hand its fields to the figure callback (the step's output)."""
        res = self._evaluate(batch, "val")
        if res is None or not self.image_log_every_n_steps:
            return None
        return {"fields": self._step_fields(res["flow"], res["v_t"], res["v_omega"], res["out"])}

    def on_validation_epoch_end(self) -> None:
        self._log_eval("val")

    def test_step(self, batch: dict[str, Any] | None, batch_idx: int) -> None:
        self._evaluate(batch, "test")

    def on_test_epoch_end(self) -> None:
        self._log_eval("test")

    # -- pictures ----------------------------------------------------------------------------

    def _step_fields(self, flow: Tensor, v_t: Tensor, v_w: Tensor, out: MFGOutput) -> StepFields:
        """The step's fields for :class:`StepFields` (detached views: no copy, no host read)."""
        return StepFields(
            self.global_step,
            flow.detach(),
            v_t.detach(),
            v_w.detach(),
            out.v_t.detach(),
            out.v_omega.detach(),
            out.hidden.detach(),
        )

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


def _finite_on_every_process(finite: Tensor, strategy: Any) -> Tensor:
    """Whether the step's loss was finite on every process: one ``all_reduce`` (MAX) of a
    one-element device tensor, queued on the device like the gradients' and never read on the
    host. Lightning's ``strategy.reduce`` would add a ``barrier()`` before it in every step
    (``_sync_ddp``); it is used only where torch.distributed is not what the strategy runs on."""
    bad = (~finite).to(torch.float32)
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.all_reduce(bad, op=torch.distributed.ReduceOp.MAX)
    else:
        bad = strategy.reduce(bad, reduce_op="max")
    return bad == 0


def _as_float(value: Tensor | float) -> Tensor | float:
    """A count to log: a float tensor (read back by the logger, at a logging step) or float."""
    return value.float() if isinstance(value, Tensor) else float(value)


def _active_fraction(hidden: Tensor) -> Tensor:
    """Mean fraction of hidden units with a non-zero activation per input."""
    return (hidden.detach() > 0).float().mean()


def _ids(batch: dict[str, Any], limit: int = 4) -> str:
    ids = list(batch.get("sample_id", []))
    more = f" (+{len(ids) - limit} more)" if len(ids) > limit else ""
    return ", ".join(map(str, ids[:limit])) + more
