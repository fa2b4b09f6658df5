"""``model.net.conv_impl=auto`` in a training run: the hook that measures and picks each
convolution's implementation (:func:`mfg_lightning.models.conv.choose_conv_impls`) once the
Trainer knows the device, the precision and the thread count.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import lightning as L
import torch

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.models.conv import (
    AUTO,
    BUSY_CPU_SHARE,
    CONV_IMPLS,
    choose_conv_impls,
    switchable_layers,
)
from mfg_lightning.run.precision import cpu_has_native_bf16

log = logging.getLogger(__name__)


def measured_dtype(precision: object) -> torch.dtype:
    """The dtype the encoder's convolutions compute in under ``trainer.precision`` on a CPU,
    for measuring them: bfloat16 under a mixed precision (Lightning runs ``16-mixed`` as
    ``bf16-mixed`` on a CPU) where the CPU computes it natively, float32 otherwise: without
    AVX512-BF16 or AMX, bfloat16 convolutions are emulated and not what a machine that trains
    in bfloat16 would run, so the choice is made (and logged as made) for float32 only."""
    if not str(precision).endswith("-mixed"):
        return torch.float32
    if cpu_has_native_bf16():
        return torch.bfloat16
    log.info(
        "model.net.conv_impl=auto: this CPU lacks native bfloat16 (no AVX512-BF16 or AMX): the "
        "convolutions are measured and chosen for float32 only, although training runs %s",
        precision,
    )
    return torch.float32


class ConvolutionChoice(L.Callback):
    """At the start of fitting, give every ``auto`` convolution of the module's ``net`` its
    fastest implementation on this machine (measured once per machine, then read from
    ``<cache_dir>/conv_impl/``; logged). Networks without ``auto`` layers are left alone, and
    nothing is measured then.

    On a GPU ``auto`` is ``native`` (cuDNN chooses its own algorithms: ``trainer.benchmark``).
    Under DDP every process measures with its own thread count (Lightning has set it by then).

    With a ``record`` file (a run directory's ``conv_impl.json``) the choice is written there,
    and a run that finds one (a resumed run) takes it as it is instead of choosing again: a
    resume on another machine, or on a busy one, then computes as the run began, and only a
    deleted record is measured again.

    Args:
        batch_size: the training batch per process (``dataset.batch_size``).
        cache_dir: ``paths.cache_dir``; None: measure every time, cache nothing.
        repeats: timed repeats per implementation and layer (after one warm-up).
        min_cpu_share: below this share of its threads' CPU time while timing, the machine
            counts as busy and the layers keep native (:func:`choose_conv_impls`).
        record: the JSON file of the run's choice ``{"layers": {name: implementation}}``;
            None: nothing recorded.
    """

    def __init__(
        self,
        batch_size: int,
        cache_dir: str | Path | None = None,
        repeats: int = 3,
        min_cpu_share: float = BUSY_CPU_SHARE,
        record: str | Path | None = None,
    ) -> None:
        self.batch_size = int(batch_size)
        self.cache_dir = cache_dir
        self.repeats = int(repeats)
        self.min_cpu_share = float(min_cpu_share)
        self.record = None if record is None else Path(record)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        net = getattr(pl_module, "net", None)
        if stage != "fit" or not isinstance(net, torch.nn.Module):
            return
        pending = [layer for _, layer in switchable_layers(net) if layer.impl == AUTO]
        if not pending:
            return
        device = trainer.strategy.root_device
        if device.type != "cpu":
            for layer in pending:
                layer.impl = "native"
            log.info("model.net.conv_impl=auto: native on %s (measured on CPUs only)", device)
            return
        if self._apply_record(net):
            return
        shape = (self.batch_size, 2, int(net.height), int(net.width))
        dtype = measured_dtype(trainer.precision)
        choose_conv_impls(net, shape, dtype, self.cache_dir, self.repeats, self.min_cpu_share)
        if self.record is not None and trainer.is_global_zero:
            layers = {name: layer.impl for name, layer in switchable_layers(net)}
            atomic_write_text(self.record, json.dumps({"layers": layers}, indent=1) + "\n")

    def _apply_record(self, net: torch.nn.Module) -> bool:
        """Give ``net``'s layers the implementations in :attr:`record`; whether it held one for
        every layer (else nothing is changed, and a record that is unusable says why)."""
        if self.record is None or not self.record.is_file():
            return False
        layers = dict(switchable_layers(net))
        try:
            recorded = json.loads(self.record.read_text())["layers"]
        except (ValueError, KeyError, TypeError, OSError) as err:
            log.warning("%s: unreadable (%s): the convolutions are chosen again", self.record, err)
            return False
        if not (
            isinstance(recorded, dict)
            and set(recorded) == set(layers)
            and set(recorded.values()) <= set(CONV_IMPLS)
        ):
            log.warning(
                "%s records other layers or implementations than this network's: the "
                "convolutions are chosen again", self.record,
            )  # fmt: skip
            return False
        for name, layer in layers.items():
            if layer.impl == AUTO:
                layer.impl = recorded[name]
        log.info("model.net.conv_impl=auto: the run's recorded choice (%s)", self.record)
        return True
