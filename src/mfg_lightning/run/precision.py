"""``trainer.precision``: which values a run accepts, what ``auto`` means on this machine, and
the ``16-mixed`` GradScaler's first scale. Trainer settings, beside the others in :mod:`.runs`
and :mod:`.training`.

Accepted: ``32-true``, ``bf16-mixed`` or ``16-mixed`` (Lightning's aliases ``32``, ``bf16``,
``16`` name the same). Under the mixed ones the encoder runs in the low precision and everything
else (fields, geometry, losses, object motion, metrics) in float32
(:mod:`mfg_lightning.models.mfg`).
``16-mixed`` starts its GradScaler at :data:`FP16_INIT_SCALE` instead of torch's 65 536, which
overflows fp16 in the first steps. :class:`PrecisionSetup` applies both rules to a Trainer;
:func:`mfg_lightning.run.runs.build_trainer` adds it to every Trainer a run builds.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import lightning as L
import torch
from lightning.pytorch.plugins.precision import MixedPrecision, Precision

log = logging.getLogger(__name__)

#: ``trainer.precision`` values the module trains and evaluates under (Lightning's aliases
#: ``32``, ``bf16`` and ``16`` name the same).
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed")
_PRECISION_ALIASES = {"32": "32-true", "bf16": "bf16-mixed", "16": "16-mixed"}

#: The initial GradScaler scale under ``16-mixed``. Measured at the first step (fp16 autocast,
#: default network, 48 × 128, scale 1): the largest gradient of an fp16 tensor is 76–94 at batch
#: 16 (quick start, 3 seeds) and 332–1260 at batch 1 (the paper's, 6 samples), always on the
#: hidden units. torch's default 65 536 overflows fp16 (max 65 504) there, so the first 7
#: (batch 16) or 11 (batch 1) steps would be skipped while the scaler halves; 16 leaves 2.5×
#: headroom at batch 1 and 40× at batch 16, and the scaler grows from there.
FP16_INIT_SCALE = 16.0
_TORCH_DEFAULT_INIT_SCALE = 2.0**16

#: ``trainer.precision=auto`` (the default): ``bf16-mixed`` where the CPU kind's row of
#: ``conf/cpu_defaults.yaml`` says so (:mod:`mfg_lightning.run.run_choices`) on a CPU that runs
#: it natively, at float32's accuracy (bench/results/precision.md: the quick start under
#: ``bf16-mixed``, 3 seeds, test ATE 0.0079 ± 0.0004 m against float32's 0.0084 ± 0.0004 m),
#: float32 elsewhere.
PRECISION_AUTO = "auto"


#: oneDNN's instruction-set caps (``ONEDNN_MAX_CPU_ISA``) that still include native bfloat16.
_BF16_ISAS = frozenset(
    {"ALL", "DEFAULT", "AVX512_CORE_BF16", "AVX512_CORE_FP16", "AVX512_CORE_AMX",
     "AVX512_CORE_AMX_FP16", "AVX10_1_512", "AVX10_1_512_AMX", "AVX10_1_512_AMX_FP16"}
)  # fmt: skip


def cpu_has_native_bf16() -> bool:
    """Whether this CPU computes bfloat16 natively (AVX512-BF16 or AMX), as oneDNN uses it.

    torch exposes the check only as ``torch.cpu._is_avx512_bf16_supported`` /
    ``_is_amx_tile_supported`` (private, present since torch 2.1); without them the answer is
    False, so such a machine keeps float32. ``ONEDNN_MAX_CPU_ISA`` (or ``DNNL_MAX_CPU_ISA``)
    set below ``AVX512_CORE_BF16`` counts as no: oneDNN then emulates bfloat16 (how an AVX2
    machine is imitated on an AVX-512 one: docs/precision.md).
    """
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA") or os.environ.get("DNNL_MAX_CPU_ISA")
    if cap and cap.strip().upper() not in _BF16_ISAS:
        return False
    checks = [getattr(torch.cpu, name, None) for name in
              ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]  # fmt: skip
    try:
        return any(bool(check()) for check in checks if check is not None)
    except Exception:  # an unexpected torch build: no native bf16 assumed
        return False


def resolve_precision(precision: Any, accelerator: Any = "auto") -> Any:
    """``trainer.precision`` with ``auto`` made concrete without measuring: ``32-true``; any
    other value as it is.

    A training run resolves ``auto`` from its CPU kind's row instead
    (:mod:`mfg_lightning.run.run_choices`: ``bf16-mixed`` only on a CPU with native bfloat16
    where it measured clearly faster); elsewhere (evaluation, prediction, the flow network's
    training) float32 is the safe answer.

    Args:
        precision: the configured ``trainer.precision``.
        accelerator: the configured ``trainer.accelerator`` (kept for callers; float32 on any).
    """
    del accelerator  # the unmeasured answer is float32 on every device
    if str(precision) != PRECISION_AUTO:
        return precision
    return "32-true"


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


class PrecisionSetup(L.Callback):
    """Refuse a precision the model does not support and fit ``16-mixed``'s GradScaler, at
    setup (before a resumed run restores the scaler's state).

    Args:
        init_scale: the GradScaler's first scale; None: the module's ``fp16_init_scale``
            hyperparameter (``model.fp16_init_scale``), else :data:`FP16_INIT_SCALE`.
    """

    def __init__(self, init_scale: float | None = None) -> None:
        self.init_scale = init_scale

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        check_precision(trainer.precision)
        scale = self.init_scale
        if scale is None:
            scale = pl_module.hparams.get("fp16_init_scale") or FP16_INIT_SCALE
        if fit_grad_scaler(trainer.precision_plugin, scale):
            log.info("16-mixed: GradScaler starts at %g (model.fp16_init_scale)", scale)


def with_precision_setup(callbacks: list[Any]) -> list[Any]:
    """``callbacks`` with a :class:`PrecisionSetup` appended unless one is there."""
    if any(isinstance(cb, PrecisionSetup) for cb in callbacks):
        return list(callbacks)
    return [*callbacks, PrecisionSetup()]
