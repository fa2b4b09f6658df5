"""``trainer.precision=auto`` and ``model.net.conv_impl=auto`` made concrete once, before a run
builds anything, from a table committed with the code.

The table, ``conf/cpu_defaults.yaml``, has one row per CPU kind
(:func:`mfg_lightning.core.machine.cpu_kind`), measured by ``python -m mfg_lightning.measure``.
Nothing is timed when a run starts, so two runs of one config on machines of one kind compute
alike, whatever the load. Where the values come from, first match wins:

1. the ``config.yaml`` of the run a resumed checkpoint belongs to: a resume computes as it began;
2. on a GPU, ``32-true`` and ``native`` (cuDNN picks its own algorithms: ``trainer.benchmark``);
3. this CPU kind's row in ``conf/local/cpu_defaults.yaml`` (git-ignored; the measure command
   writes it), then in ``conf/cpu_defaults.yaml``;
4. a kind in neither, or a model without ``model.net.conv_impl`` (the rows were measured on
   MFG's network): ``32-true`` and ``native``.

A row's precision is ``bf16-mixed`` only where the CPU computes bfloat16 natively. Its kernels
apply to the network it was measured on (``net``); another network computes ``native``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
import yaml
from omegaconf import DictConfig, OmegaConf, open_dict

from mfg_lightning.core.config import config_dir
from mfg_lightning.core.machine import cpu_kind
from mfg_lightning.models.conv import AUTO
from mfg_lightning.run.precision import PRECISION_AUTO, cpu_has_native_bf16

log = logging.getLogger(__name__)

#: The table's file name, in the config directory and in its ``local/`` folder.
TABLE = "cpu_defaults.yaml"
#: The keys of ``model.net`` a row's kernels were measured on (with the run's input size).
NET_GEOMETRY = ("height", "width", "hidden_units", "channels", "kernels", "strides",
                "double_blocks", "decoder_scale")  # fmt: skip


def table_files() -> list[Path]:
    """The tables, the one that wins first: the local one, then the committed one."""
    return [config_dir() / "local" / TABLE, config_dir() / TABLE]


def read_table(path: Path) -> dict[str, Any]:
    """The rows of one table file by CPU kind (empty where the file does not exist)."""
    if not path.is_file():
        return {}
    rows = yaml.safe_load(path.read_text()) or {}
    if not isinstance(rows, dict):
        raise ValueError(f"{path}: expected one mapping of CPU kinds to rows")
    return rows


def cpu_row(kind: str | None = None) -> tuple[dict[str, Any] | None, str]:
    """This CPU kind's row and where it was read (``"plain defaults"`` where no table has one)."""
    kind = kind or cpu_kind()
    for path in table_files():
        row = read_table(path).get(kind)
        if row is not None:
            return row, f"{path.parent.name}/{path.name} row {kind}"
    return None, f"plain defaults (no row for {kind})"


def net_geometry(net_cfg: Any) -> dict[str, Any]:
    """The geometry keys of ``model.net`` as plain values (what a row's ``net`` holds)."""
    plain = net_cfg
    if OmegaConf.is_config(net_cfg):
        plain = OmegaConf.to_container(net_cfg, resolve=True)
    return {k: plain[k] for k in NET_GEOMETRY if k in plain}


def on_cpu(trainer_cfg: Any) -> bool:
    """Whether the configured trainer computes on the CPU."""
    accelerator = str(trainer_cfg.get("accelerator", "auto"))
    return accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available())


def needs_bf16(precision: str) -> bool:
    """Whether a run under ``precision`` computes its convolutions in bfloat16 on this CPU: a
    mixed precision where bfloat16 is native (elsewhere it is emulated: float32's kernels)."""
    return str(precision).endswith("-mixed") and cpu_has_native_bf16()


def _from_row(cfg: DictConfig, row: dict[str, Any] | None) -> tuple[str, Any]:
    """The precision and kernels of ``row`` (None: no row) for the run ``cfg``."""
    row = row or {}
    precision = str(cfg.trainer.get("precision"))
    if precision == PRECISION_AUTO:
        wanted = row.get("precision", "32-true")
        precision = wanted if wanted == "32-true" or cpu_has_native_bf16() else "32-true"
    dtype = "bfloat16" if needs_bf16(precision) else "float32"
    kernels = row.get("conv_impl", {}).get(dtype)
    net = cfg.model.get("net")
    if (
        kernels is None
        or net is None
        or (not isinstance(kernels, str) and row.get("net") != net_geometry(net))
    ):
        kernels = "native"
    return precision, kernels


def _resumed(ckpt_path: str | None) -> DictConfig | None:
    """The config of the run a checkpoint belongs to (``<run>/checkpoints/x.ckpt``)."""
    if ckpt_path is None:
        return None
    path = Path(ckpt_path).expanduser().resolve().parent.parent / "config.yaml"
    return OmegaConf.load(path) if path.is_file() else None


def resolve_run_choices(cfg: DictConfig, ckpt_path: str | None = None) -> str | None:
    """Make ``trainer.precision`` and ``model.net.conv_impl`` concrete in ``cfg`` where they
    are ``auto`` (module docstring) and return where they came from; None where neither is.

    Args:
        cfg: the run's own config, changed in place before it is frozen.
        ckpt_path: the checkpoint the run resumes from, None for a fresh start.
    """
    net = cfg.model.get("net")
    conv_auto = net is not None and net.get("conv_impl") == AUTO
    precision_auto = str(cfg.trainer.get("precision")) == PRECISION_AUTO
    if not (conv_auto or precision_auto):
        return None
    before = _resumed(ckpt_path)
    if before is not None:
        precision = before.trainer.get("precision")
        kernels = OmegaConf.select(before, "model.net.conv_impl", default="native")
        source = "the run resumed from"
    elif not on_cpu(cfg.trainer):
        precision, kernels, source = "32-true", "native", "a GPU"
    elif net is None or "conv_impl" not in net:  # not the network the rows were measured on
        precision, kernels, source = "32-true", None, "plain defaults (another network)"
    else:
        row, source = cpu_row()
        precision, kernels = _from_row(cfg, row)
    with open_dict(cfg):
        if precision_auto:
            cfg.trainer.precision = precision
        if conv_auto:
            cfg.model.net.conv_impl = kernels
    log.info("trainer.precision=%s, model.net.conv_impl=%s (%s)", cfg.trainer.precision,
             None if net is None else net.get("conv_impl"), source)  # fmt: skip
    return source


def choice_overrides(cfg: DictConfig) -> list[str]:
    """The resolved precision and kernels as command-line overrides: what the first process
    appends to the command line Lightning's launcher starts the others with."""
    found = [f"trainer.precision={cfg.trainer.precision}"]
    impl = OmegaConf.select(cfg, "model.net.conv_impl")
    if impl is not None:
        value = impl if isinstance(impl, str) else f"[{','.join(str(v) for v in impl)}]"
        found.append(f"model.net.conv_impl={value}")
    return found


def write_local_row(
    row: dict[str, Any], path: str | Path | None = None, kind: str | None = None
) -> Path:
    """Put ``row`` as this CPU kind's row into ``path`` (None: ``conf/local/cpu_defaults.yaml``,
    which every later run on this machine reads), the other kinds' rows kept; return the file."""
    path = Path(path) if path else table_files()[0]
    rows = read_table(path)
    rows[kind or cpu_kind()] = row
    path.parent.mkdir(parents=True, exist_ok=True)
    header = "# Written by python -m mfg_lightning.measure; wins over conf/cpu_defaults.yaml.\n"
    path.write_text(header + yaml.safe_dump(rows, sort_keys=False, width=100))
    return path
