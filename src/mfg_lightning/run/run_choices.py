"""A training run's timing-dependent settings made concrete before anything is built, recorded
with the run, and the same in every process.

``trainer.precision=auto`` and ``model.net.conv_impl=auto`` become a precision and a list of
convolution implementations (one per layer, in module order) by :func:`resolve_run_choices`,
which the run writes into its ``config.yaml``; :class:`RunChoicesRecord` writes them into every
checkpoint as ``mfg_run_choices``. Where they come from, first match wins:

1. the first process of a DDP run that starts its own processes (Lightning's launcher starts the
   others with the same command line): its choices reach them in ``$MFG_RUN_CHOICES``;
2. the checkpoint a run resumes from: a resumed run computes as it began, whatever the machine
   or its load now;
3. on a CPU, this machine's measurement (:mod:`mfg_lightning.run.machine_profile`: read, or made
   once under a file lock); on a GPU ``32-true`` and ``native`` (cuDNN chooses its own
   algorithms: ``trainer.benchmark``).

A rerun from a run's ``config.yaml`` reads concrete values and measures nothing. Under DDP
:class:`RunChoicesRecord` also makes every process take the first process's kernels at setup
(processes started by torchrun or SLURM resolve on their own, from the same file where they
share a cache) and logs once which kernels ran.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from mfg_lightning.core.host_memory import freed_memory_kept
from mfg_lightning.models.conv import AUTO, per_layer_impls, switchable_layers
from mfg_lightning.run.machine_profile import (
    Profile,
    describe,
    machine_profile,
    needs_bf16,
    profile_key,
    profile_path,
)
from mfg_lightning.run.precision import PRECISION_AUTO, cpu_has_native_bf16

log = logging.getLogger(__name__)

#: The environment variable in which the first process hands its choices to those it starts.
CHOICES_VARIABLE = "MFG_RUN_CHOICES"
#: The checkpoint key of the choices a run trained with.
CHECKPOINT_KEY = "mfg_run_choices"


def training_processes(trainer_cfg: DictConfig) -> int:
    """Training processes per node that ``trainer_cfg`` starts on a CPU (``devices``)."""
    devices = trainer_cfg.get("devices", "auto")
    if isinstance(devices, int):
        return max(1, devices)
    if isinstance(devices, str) and devices.isdigit():
        return max(1, int(devices))
    if OmegaConf.is_list(devices) or isinstance(devices, list):
        return max(1, len(devices))
    return 1  # "auto" on a CPU: one process


def training_threads(processes: int) -> int:
    """The torch threads each training process will run with: Lightning gives each of several
    processes ``usable cores // processes`` unless ``OMP_NUM_THREADS`` is set (which it then
    sets); one process keeps this process's count."""
    if processes > 1 and "OMP_NUM_THREADS" not in os.environ:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        return max(1, (cores or 1) // processes)
    return torch.get_num_threads()


def _on_cpu(trainer_cfg: DictConfig) -> bool:
    accelerator = str(trainer_cfg.get("accelerator", "auto"))
    return accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available())


def _recorded(ckpt: dict[str, Any] | None) -> dict[str, Any] | None:
    """The choices recorded in the checkpoint a run resumes from (None: none, or no resume)."""
    found = None if ckpt is None else ckpt.get(CHECKPOINT_KEY)
    return dict(found) if isinstance(found, dict) and found.get("conv_impl") is not None else None


def _handed_down(output_dir: Path) -> dict[str, Any] | None:
    """The choices the first process of this run handed down (:data:`CHOICES_VARIABLE`)."""
    raw = os.environ.get(CHOICES_VARIABLE)
    # Only a process Lightning's launcher started (local rank > 0) was handed anything: the
    # first process itself, or a later run in it, measures or reads on its own.
    if not raw or int(os.environ.get("LOCAL_RANK") or 0) == 0:
        return None
    found = json.loads(raw)
    return found if found.get("run") == str(output_dir) else None


def resolve_run_choices(
    cfg: DictConfig, ckpt: dict[str, Any] | None = None
) -> dict[str, Any] | None:
    """Make ``trainer.precision`` and ``model.net.conv_impl`` concrete in ``cfg`` where they are
    ``auto`` (module docstring: from the first process, the checkpoint, or this machine's
    measurement) and return what was chosen, ``{"precision", "conv_impl", "source"}``; None when
    neither is ``auto``. Hands the choices down to the processes this one starts.

    Args:
        cfg: the run's config, changed in place.
        ckpt: the checkpoint the run resumes from (:func:`~mfg_lightning.run.checkpoints.
            peek_checkpoint`), None for a fresh start.
    """
    trainer_cfg, net_cfg = cfg.trainer, cfg.model.get("net")
    conv_auto = net_cfg is not None and net_cfg.get("conv_impl") == AUTO
    precision_auto = str(trainer_cfg.get("precision")) == PRECISION_AUTO
    if not (conv_auto or precision_auto):
        return None
    output_dir = Path(cfg.paths.output_dir)
    found = _handed_down(output_dir)
    source = "the first process"
    if found is None:
        found, source = _recorded(ckpt), "the checkpoint resumed from"
    if found is None:
        found, source = _measured(cfg, conv_auto, precision_auto), "this machine's measurement"
    with open_dict(cfg):
        if precision_auto:
            cfg.trainer.precision = found["precision"]
        if conv_auto:
            cfg.model.net.conv_impl = list(found["conv_impl"])
    chosen = {
        "precision": str(cfg.trainer.precision),
        "conv_impl": None if net_cfg is None else _as_list(cfg.model.net),
        "source": source,
    }
    log.info("trainer.precision=%s, model.net.conv_impl=%s (%s)", chosen["precision"],
             chosen["conv_impl"], source)  # fmt: skip
    os.environ[CHOICES_VARIABLE] = json.dumps({**chosen, "run": str(output_dir)})
    return chosen


def _as_list(net_cfg: DictConfig) -> list[str] | str:
    value = net_cfg.get("conv_impl", "native")
    return value if isinstance(value, str) else [str(v) for v in value]


def _measured(cfg: DictConfig, conv_auto: bool, precision_auto: bool) -> dict[str, Any]:
    """The choices of this machine's profile (or the GPU's fixed ones) for ``cfg``."""
    net_cfg = cfg.model.get("net")
    given = str(cfg.trainer.precision)
    if not _on_cpu(cfg.trainer) or net_cfg is None or "conv_impl" not in net_cfg:
        # A GPU (cuDNN picks its algorithms), or a network without switchable convolutions:
        # nothing is measured; auto is float32.
        conv = "native" if net_cfg is None or not conv_auto else _native_list(cfg)
        return {"precision": "32-true" if precision_auto else given, "conv_impl": conv}
    profile, _ = measure_machine(cfg)
    precision = profile.precision if precision_auto else given
    dtype = "bfloat16" if needs_bf16(precision) else "float32"
    if dtype not in profile.conv:  # defensive: the dtype measured is the one that computes
        dtype = next(iter(profile.conv))
    return {"precision": precision, "conv_impl": profile.kernels(dtype)}


def measure_machine(
    cfg: DictConfig, again: bool = False, progress: Callable[[str], None] | None = None
) -> tuple[Profile, Path | None]:
    """This machine's profile for the training run ``cfg`` describes (its network, batch and
    thread count; both dtypes where ``trainer.precision=auto`` can choose bfloat16): read from
    ``paths.cache_dir`` or measured once (``again``: measured and replaced). Returns it and its
    file (None without a cache directory). Logged."""
    from hydra.utils import instantiate

    given = str(cfg.trainer.precision)
    native_bf16 = cpu_has_native_bf16()
    if given == PRECISION_AUTO:
        dtypes = ["float32", "bfloat16"] if native_bf16 else ["float32"]
    else:
        dtypes = ["bfloat16"] if needs_bf16(given, native_bf16) else ["float32"]
    plain = OmegaConf.to_container(cfg.model.net, resolve=True)
    threads = training_threads(training_processes(cfg.trainer))
    key = profile_key(plain, int(cfg.dataset.batch_size), threads)

    def build_net(conv_impl: str | list[str]) -> torch.nn.Module:
        return instantiate({**plain, "conv_impl": conv_impl})

    cache_dir = cfg.paths.get("cache_dir")
    # timed as training runs (mfg_lightning.core.host_memory): without it a round may or may
    # not page-fault its gradients back, and its time with it; set back afterwards
    with freed_memory_kept(bool(cfg.get("keep_freed_memory", True))):
        profile, read = machine_profile(cache_dir, key, dtypes, build_net, again, progress)
    log.info(describe(profile, read, given))
    return profile, None if cache_dir is None else profile_path(cache_dir, key)


def _native_list(cfg: DictConfig) -> list[str]:
    from hydra.utils import instantiate

    plain = OmegaConf.to_container(cfg.model.net, resolve=True)
    net = instantiate({**plain, "conv_impl": "native"})
    return ["native" for _ in switchable_layers(net)]


class RunChoicesRecord(L.Callback):
    """Write the run's precision and kernels into every checkpoint (``mfg_run_choices``), make
    every DDP process compute with the first process's kernels, and log once which ran."""

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        net = getattr(pl_module, "net", None)
        layers = dict(switchable_layers(net)) if isinstance(net, torch.nn.Module) else {}
        impls = [layer.impl for layer in layers.values()]
        mine = {"precision": str(trainer.precision), "conv_impl": impls}
        first = trainer.strategy.broadcast(mine, src=0) if trainer.world_size > 1 else mine
        if first["precision"] != mine["precision"]:
            raise RuntimeError(
                f"trainer.precision: process {trainer.global_rank} resolved {mine['precision']}, "
                f"the first process {first['precision']}: set trainer.precision explicitly"
            )
        if first["conv_impl"] != mine["conv_impl"]:
            log.warning("process %d takes the first process's kernels %s (it resolved %s)",
                        trainer.global_rank, first["conv_impl"], mine["conv_impl"])  # fmt: skip
            for layer, impl in zip(
                layers.values(), per_layer_impls(first["conv_impl"], len(layers)), strict=True
            ):
                layer.impl = impl
        self.choices = first
        if trainer.is_global_zero and stage == "fit" and layers:
            log.info(
                "kernels of all %d processes, %d threads each: precision %s; %s",
                trainer.world_size, torch.get_num_threads(), first["precision"],
                ", ".join(f"{n} {i}" for n, i in zip(layers, first["conv_impl"], strict=True)),
            )  # fmt: skip

    def on_save_checkpoint(
        self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]
    ) -> None:
        checkpoint[CHECKPOINT_KEY] = dict(getattr(self, "choices", {}))
