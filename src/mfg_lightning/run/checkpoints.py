"""Checkpoints of :mod:`mfg_lightning.train`: read them safely, rebuild the module, find the data.

Researchers share checkpoints, so reading one must never run its author's code:

* **Unpickling** uses ``torch.load(weights_only=True)``: tensors, numbers, strings and plain
  containers only, plus the few types that checkpoints written by earlier versions of the project
  hold (:func:`_legacy_safe_globals`: OmegaConf nodes and Hydra's partial of the optimiser class,
  none of which runs anything when it is rebuilt). A pickle that names any other global (a
  payload calling ``os.system``, say) is refused before it runs: :class:`CheckpointError`.
* **Configs** read from a checkpoint (its model config, ``mfg_dataset_config``) or from a run
  directory's ``config.yaml`` are instantiated only if every ``_target_`` in them, at any depth,
  resolves to one of the classes the project's own configs build (:func:`allowed_targets`: the
  LightningModule, the network, the loss, the object-motion filters, the DataModules and flow
  estimators, torch's optimisers and lr schedulers). The check is on the resolved object, so an
  alias of an allowed class passes and nothing else does (``builtins.open``,
  ``subprocess.run``, ...): :class:`UnsafeConfigError` names the key and the target.

What a checkpoint holds to be rebuilt: the module's ``model_config`` hyperparameter (the
resolved model config it was built from, enough to rebuild it without the run directory;
``mfg_model_config`` before) and ``mfg_dataset_config`` (the training dataset's config, the
default of ``evaluate``, ``predict`` and ``analyze_basis``).
"""

from __future__ import annotations

import contextlib
import inspect
import logging
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import OmegaConf
from torch import Tensor

if TYPE_CHECKING:
    from mfg_lightning.models.mfg_module import MFGLitModule

log = logging.getLogger(__name__)

__all__ = [
    "LEGACY_MODEL_SETTINGS",
    "MOVED_MODULES",
    "CheckpointError",
    "CheckpointSizeError",
    "ModelSize",
    "UnsafeConfigError",
    "allowed_targets",
    "build_module",
    "check_targets",
    "dataset_config",
    "load_checkpoint",
    "model_size",
    "module_from_checkpoint",
    "safe_unpickling",
    "stored_model_config",
    "with_legacy_dataset_settings",
    "with_legacy_settings",
    "with_moved_targets",
]


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, unsafe, or does not fit the model it should restore."""


class CheckpointSizeError(CheckpointError):
    """A checkpoint's weights do not fit the model size its config or the caller expects."""


class UnsafeConfigError(CheckpointError):
    """A stored config names a ``_target_`` outside :func:`allowed_targets`."""


# --------------------------------------------------------------------------------------------
# Unpickling
# --------------------------------------------------------------------------------------------


@cache
def _legacy_safe_globals() -> tuple[Any, ...]:
    """Types that checkpoints written before configs were stored as plain data hold.

    Their ``hyper_parameters`` kept the optimiser and scheduler partials (Hydra's
    ``_DeferredTarget``, a ``functools.partial`` subclass, of ``torch.optim.Adam`` and
    ``CosineAnnealingLR``) and OmegaConf nodes of their arguments. Rebuilding any of these only
    stores values; none of them is called while loading.
    """
    import collections
    import functools
    import typing

    from omegaconf import DictConfig, ListConfig
    from omegaconf.base import ContainerMetadata, Metadata
    from omegaconf.nodes import AnyNode

    found: list[Any] = [
        DictConfig,
        ListConfig,
        ContainerMetadata,
        Metadata,
        AnyNode,
        typing.Any,
        collections.defaultdict,
        functools.partial,
        dict,
        list,
        int,
        float,
        str,
        bool,
    ]
    with contextlib.suppress(ImportError, AttributeError):  # present in Hydra 1.3.3 and newer
        from hydra._internal.target_policy import _DeferredTarget

        found.append(_DeferredTarget)
    found += [t for t in _optimisers_and_schedulers() if isinstance(t, type)]
    return tuple(found)


@contextlib.contextmanager
def safe_unpickling() -> Iterator[None]:
    """Within this context ``torch.load(weights_only=True)`` also accepts
    :func:`_legacy_safe_globals` (what Lightning's checkpoint loading needs to resume a run)."""
    with torch.serialization.safe_globals(list(_legacy_safe_globals())):
        yield


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint of :mod:`mfg_lightning.train` onto the CPU, tensors and plain data only.

    Raises:
        CheckpointError: missing or unreadable file, a pickle that names anything but plain data
            (it is refused before it runs), or not a checkpoint of this project (no
            ``state_dict`` or model config).
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        with safe_unpickling():
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated, not a torch file, or an unsafe pickle
        raise CheckpointError(f"cannot read checkpoint {path}: {describe_load_error(err)}") from err
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise CheckpointError(f"{path} is not a Lightning checkpoint (no state_dict)")
    if stored_model_config(ckpt) is None:
        raise CheckpointError(
            f"{path} has no model config: it was not written by mfg_lightning.train"
        )
    return ckpt


def stored_model_config(ckpt: Mapping[str, Any]) -> dict[str, Any] | None:
    """The resolved model config a checkpoint's module was built from: its ``model_config``
    hyperparameter (``mfg_model_config`` in checkpoints of older releases); None: none."""
    hparams = ckpt.get("hyper_parameters")
    stored = hparams.get("model_config") if isinstance(hparams, Mapping) else None
    return stored if stored is not None else ckpt.get("mfg_model_config")


def peek_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint memory-mapped (its tensors are read only when touched): what a resuming run
    reads before Lightning loads it for real (the recorded precision and kernels, the loader's
    saved place). Plain data only, as :func:`load_checkpoint`.

    Raises:
        CheckpointError: unreadable, or not a Lightning checkpoint.
    """
    try:
        with safe_unpickling():
            ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as err:  # truncated, not a torch file, or an unsafe pickle
        raise CheckpointError(f"cannot read checkpoint {path}: {describe_load_error(err)}") from err
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a Lightning checkpoint")
    return ckpt


def saved_loader_places(ckpt: dict[str, Any]) -> list[dict[str, Any]]:
    """The training loaders' saved places in a checkpoint's fit loop (empty where none)."""
    loop = ckpt.get("loops", {}).get("fit_loop", {}).get("state_dict", {})
    places = loop.get("combined_loader") or []
    return [p for p in places if isinstance(p, dict)]


def describe_load_error(err: BaseException) -> str:
    """One line on why ``torch.load`` failed; an unsafe pickle says which global it named."""
    text = str(err)
    if "Unsupported global" in text or "Weights only load failed" in text:
        detail = next(
            (line.strip() for line in text.splitlines() if "Unsupported global" in line), ""
        )
        detail = detail.removeprefix("WeightsUnpickler error: ").split(" was not an allowed")[0]
        return (
            "it holds Python objects other than tensors and plain data"
            + (f" ({detail})" if detail else "")
            + ", which could run code when unpickled; it was not loaded"
        )
    return (text.strip().splitlines() or [type(err).__name__])[0]


# --------------------------------------------------------------------------------------------
# Configs: the allow-list
# --------------------------------------------------------------------------------------------

#: Every class a config read from a checkpoint or a run directory may build, by dotted name
#: (resolved on first use). torch's optimisers and lr schedulers are added by
#: :func:`allowed_targets`. A new DataModule, estimator or network part goes here too:
#: tests/test_checkpoints.py checks that every ``_target_`` of the model, dataset, flow and
#: object-motion config groups is listed.
PROJECT_TARGETS = (
    "mfg_lightning.models.mfg_module.MFGLitModule",
    "mfg_lightning.models.mfg.MFG",
    "mfg_lightning.models.losses.MFGLoss",
    "mfg_lightning.motion.object_motion.ObjectMotionConfig",
    "mfg_lightning.data.synthetic.SyntheticDataModule",
    "mfg_lightning.data.kitti.KittiDataModule",
    "mfg_lightning.data.vkitti.VirtualKittiDataModule",
    "mfg_lightning.data.image_folder.ImageFolderDataModule",
    # the learned flow's training (python -m mfg_lightning.train_flow)
    "mfg_lightning.models.flow_module.FlowLitModule",
    "mfg_lightning.data.flow_pairs.FlowPairsDataModule",
    # the flow network and MFG trained together (experiment=end_to_end)
    "mfg_lightning.models.end_to_end.EndToEndLitModule",
    "mfg_lightning.data.image_pairs.ImagePairsDataModule",
)


#: Modules that moved when the package was laid out in folders (0.1 → 0.2), old → new. A config
#: written by 0.1 (a checkpoint's ``mfg_model_config`` / ``mfg_dataset_config``, a run
#: directory's ``config.yaml``) names its ``_target_`` classes by their old modules; they are read
#: as the new ones (:func:`with_moved_targets`) before the allow-list is checked.
MOVED_MODULES: dict[str, str] = {
    "mfg_lightning.geometry": "mfg_lightning.core.geometry",
    "mfg_lightning.atomic": "mfg_lightning.core.atomic",
    "mfg_lightning.errors": "mfg_lightning.core.errors",
    "mfg_lightning.config": "mfg_lightning.core.config",
    "mfg_lightning.tables": "mfg_lightning.core.tables",
    "mfg_lightning.data.errors": "mfg_lightning.core.data_errors",
    "mfg_lightning.data.worlds": "mfg_lightning.scene.worlds",
    "mfg_lightning.data.render": "mfg_lightning.scene.render",
    "mfg_lightning.data.flow_estimation": "mfg_lightning.flow.estimators",
    "mfg_lightning.data.flow_io": "mfg_lightning.flow.io",
    "mfg_lightning.losses": "mfg_lightning.models.losses",
    "mfg_lightning.baselines": "mfg_lightning.motion.baselines",
    "mfg_lightning.object_motion": "mfg_lightning.motion.object_motion",
    "mfg_lightning.object_motion_viz": "mfg_lightning.pictures.object_motion",
    "mfg_lightning.trajectories": "mfg_lightning.trajectory.trajectories",
    "mfg_lightning.pose_io": "mfg_lightning.trajectory.pose_io",
    "mfg_lightning.visualization": "mfg_lightning.pictures.colours",
    "mfg_lightning.plots": "mfg_lightning.pictures.plots",
    "mfg_lightning.callbacks": "mfg_lightning.run.callbacks",
    "mfg_lightning.checkpoints": "mfg_lightning.run.checkpoints",
    "mfg_lightning.runs": "mfg_lightning.run.runs",
    "mfg_lightning.scoring": "mfg_lightning.analysis.scoring",
    "mfg_lightning.basis": "mfg_lightning.analysis.basis",
    "mfg_lightning.sweeps": "mfg_lightning.analysis.sweeps",
    "mfg_lightning.result_tables": "mfg_lightning.analysis.result_tables",
    # classes (a whole target): the batch checks became part of the run's AgreedSteps
    "mfg_lightning.callbacks.BatchChecks": "mfg_lightning.run.agreed_steps.AgreedSteps",
    "mfg_lightning.run.callbacks.BatchChecks": "mfg_lightning.run.agreed_steps.AgreedSteps",
}


def moved_target(target: str) -> str:
    """``target`` renamed by :data:`MOVED_MODULES` (the whole target, else the longest
    matching module prefix), or unchanged."""
    parts = target.split(".")
    for n in range(len(parts), 0, -1):
        new = MOVED_MODULES.get(".".join(parts[:n]))
        if new is not None:
            return ".".join([new, *parts[n:]])
    return target


def with_moved_targets(cfg: Any, source: str | Path) -> Any:
    """A plain config (mappings and lists) with every ``_target_`` of a moved module renamed
    (:func:`moved_target`), logged once per config. Anything else is returned as it is."""
    renamed: list[str] = []

    def walk(node: Any) -> Any:
        if isinstance(node, Mapping):
            out = {k: walk(v) for k, v in node.items()}
            target = out.get("_target_")
            if isinstance(target, str) and moved_target(target) != target:
                out["_target_"] = moved_target(target)
                renamed.append(f"{target} → {out['_target_']}")
            return out
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node

    cfg = walk(cfg)
    if renamed:
        log.warning("%s names classes by their 0.1 modules: reading %s", source, ", ".join(renamed))
    return cfg


def _optimisers_and_schedulers() -> list[Any]:
    """torch's own optimiser and lr-scheduler classes."""
    from torch.optim import Optimizer, lr_scheduler

    found = []
    for module, base in ((torch.optim, Optimizer), (lr_scheduler, lr_scheduler.LRScheduler)):
        for value in vars(module).values():
            if inspect.isclass(value) and issubclass(value, base) and value is not base:
                found.append(value)
    found.append(lr_scheduler.ReduceLROnPlateau)
    return found


@cache
def allowed_targets() -> frozenset[Any]:
    """The resolved objects a stored config may name as ``_target_``."""
    return frozenset([_resolve(name) for name in PROJECT_TARGETS] + _optimisers_and_schedulers())


def _resolve(target: str) -> Any:
    """The object a dotted ``_target_`` names, as Hydra resolves it (without Hydra's log line
    for names that do not resolve: those are refused with our own message)."""
    from hydra._internal.utils import _locate

    return _locate(target)


def check_targets(cfg: Any, source: str, key: str = "") -> None:
    """Refuse a config whose ``_target_`` anywhere resolves outside :func:`allowed_targets`.

    Args:
        cfg: a plain or OmegaConf mapping / list (interpolations are resolved first).
        source: where the config came from, for the message (a checkpoint or config.yaml).
        key: the dotted key of ``cfg`` itself in the message.

    Raises:
        UnsafeConfigError: naming the source, the key and the target.
    """
    if OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    if isinstance(cfg, Mapping):
        if "_target_" in cfg:
            target = cfg["_target_"]
            where = f"{key}._target_" if key else "_target_"
            try:
                resolved = _resolve(target) if isinstance(target, str) else None
            except Exception:  # unknown module or attribute: certainly not an allowed class
                resolved = None
            if resolved is None or resolved not in allowed_targets():
                raise UnsafeConfigError(
                    f"{source}: {where} = {target!r} is not one of the classes this project's "
                    "configs build (mfg_lightning.run.checkpoints.PROJECT_TARGETS, torch "
                    "optimisers and lr schedulers); refusing to instantiate it"
                )
        for name, value in cfg.items():
            check_targets(value, source, f"{key}.{name}" if key else str(name))
    elif isinstance(cfg, (list, tuple)):
        for i, value in enumerate(cfg):
            check_targets(value, source, f"{key}[{i}]")


# --------------------------------------------------------------------------------------------
# Rebuilding the module
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelSize:
    """The sizes that decide whether MFG weights fit: ``M`` hidden units and the input grid (a
    :class:`mfg_lightning.models.mfg.MotionFieldNetwork`'s ``hidden_units``, ``height`` and
    ``width``, which its config names alike)."""

    hidden_units: int
    height: int
    width: int

    def __str__(self) -> str:
        return f"hidden_units={self.hidden_units}, input {self.height}×{self.width}"


def model_size(model_config: Mapping[str, Any]) -> ModelSize:
    """The :class:`ModelSize` of a resolved model config (:func:`stored_model_config`)."""
    net = model_config.get("net", {})
    return ModelSize(int(net["hidden_units"]), int(net["height"]), int(net["width"]))


def _weights_description(state_dict: Mapping[str, Tensor]) -> str:
    """What the weights themselves say about the size (the decoders are ``(2·h·w, M)``)."""
    w = state_dict.get("net.decoder_t.weight")
    if w is None or w.dim() != 2:
        return "weights without an MFG decoder"
    return f"weights with hidden_units={w.shape[1]} and {w.shape[0] // 2}-pixel decoder fields"


#: Model settings added after checkpoints were first written, with the value every checkpoint
#: that lacks them was trained with. A stored config missing one is read with this value, so an
#: old checkpoint keeps the behaviour it was trained with when a default changes.
LEGACY_MODEL_SETTINGS: dict[str, dict[str, Any]] = {
    "net": {"init": "torch", "align_corners": False, "input_scale": 1.0},
    "loss": {"balance_squared": True},
}


def with_legacy_settings(cfg: Mapping[str, Any], path: str | Path) -> dict[str, Any]:
    """``cfg`` with its moved ``_target_`` modules renamed (:func:`with_moved_targets`) and every
    missing :data:`LEGACY_MODEL_SETTINGS` key filled in (both logged)."""
    cfg = with_moved_targets(cfg, path)
    cfg = {k: dict(v) if isinstance(v, Mapping) else v for k, v in cfg.items()}
    filled = []
    if "top_k" in cfg and cfg["top_k"] is None:  # before 1.0 alone said "all units"
        cfg["top_k"] = 1.0
    for part, settings in LEGACY_MODEL_SETTINGS.items():
        node = cfg.get(part)
        if not isinstance(node, dict):
            continue
        for key, value in settings.items():
            if key not in node:
                node[key] = value
                filled.append(f"model.{part}.{key}={value}")
    if filled:
        log.warning(
            "checkpoint %s predates %s: using the behaviour it was trained with (%s)",
            path,
            ", ".join(f.split("=")[0] for f in filled),
            ", ".join(filled),
        )
    return cfg


#: Dataset keys that the ``flow`` config group replaced, by the flow setting each became.
_LEGACY_FLOW_KEYS = {
    "noise_std": "noise_std",
    "outlier_fraction": "outlier_fraction",
    "dis_preset": "preset",
    "dis_params": "params",
    "flow_height": "height",
    "flow_width": "width",
}


def with_legacy_dataset_settings(cfg: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """A dataset config written with older keys, rewritten into today's. Logged as a warning.

    * Configs written before the ``flow`` group carried the flow settings as dataset keys
      (synthetic ``noise_std`` / ``outlier_fraction``: exact flow; KITTI ``dis_preset`` /
      ``dis_params`` / ``flow_height`` / ``flow_width``: DIS, or ``flow_dir``: the user's files);
      they become ``flow`` with the same values, so the checkpoint is evaluated on the flow it
      was trained on.
    * Synthetic ``test_offsets`` is ``offsets`` (one name with ``dataset=kitti``'s; it now sets
      the offsets of every split).
    """
    cfg = _with_legacy_flow(with_moved_targets(cfg, path), path)
    if "test_offsets" in cfg:
        cfg = dict(cfg)
        offsets = cfg.pop("test_offsets")
        if "offsets" not in cfg:
            cfg["offsets"] = offsets
            log.warning(
                "%s: dataset.test_offsets is now dataset.offsets (every split): reading %s",
                path,
                list(offsets),
            )
    return cfg


def _with_legacy_flow(cfg: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """The flow settings of a dataset config written before the ``flow`` group, as ``flow``."""
    if "flow" in cfg or not (set(cfg) & {*_LEGACY_FLOW_KEYS, "flow_dir"}):
        return cfg
    cfg = dict(cfg)
    flow_dir = cfg.pop("flow_dir", None)
    moved = {new: cfg.pop(old) for old, new in _LEGACY_FLOW_KEYS.items() if old in cfg}
    if flow_dir is not None:
        flow = {"source": "files", "dir": flow_dir}
    elif "noise_std" in moved or "outlier_fraction" in moved:
        flow = {"source": "exact", **moved}
    else:
        flow = {"source": "dis", **moved}
    cfg["flow"] = flow
    log.warning("checkpoint %s predates the flow config group: reading its flow as %s", path, flow)
    return cfg


def build_module(
    ckpt: Mapping[str, Any],
    path: str | Path,
    expected: ModelSize | None = None,
    **overrides: Any,
) -> MFGLitModule:
    """Rebuild the LightningModule of a read checkpoint from its stored config, with its weights.

    Args:
        ckpt: what :func:`load_checkpoint` returned.
        path: the checkpoint file (for messages).
        expected: the size the caller needs (e.g. a dataset's resolution); None: any.
        overrides: replace top-level keys of the stored model config (e.g. ``top_k=0.05``).

    Returns:
        The module in evaluation mode on the CPU, with ``model_config`` and ``dataset_config``
        set from the checkpoint (the dataset config with the run-directory fallback).

    Raises:
        UnsafeConfigError: the stored config names a target outside the allow-list.
        CheckpointSizeError: the stored size differs from ``expected``, or the weights do not fit
            the architecture of the stored config. The message names the file and both sizes.
    """
    from hydra.utils import instantiate

    cfg = {**with_legacy_settings(stored_model_config(ckpt) or {}, path), **overrides}
    check_targets(cfg, f"checkpoint {path} (model_config)")
    size = model_size(cfg)
    if expected is not None and size != expected:
        raise CheckpointSizeError(
            f"checkpoint {path} holds an MFG with {size}, but {expected} is expected"
        )
    module: MFGLitModule = instantiate(cfg, _partial_=True)(model_config=cfg)
    try:
        module.load_state_dict(ckpt["state_dict"])
    except RuntimeError as err:
        first = str(err).strip().splitlines()
        raise CheckpointSizeError(
            f"checkpoint {path}: weights do not fit an MFG with {size} (its stored config): it "
            f"holds {_weights_description(ckpt['state_dict'])} "
            f"({first[-1].strip() if first else err})"
        ) from err
    module.dataset_config = dataset_config(ckpt, path)
    return module.eval()


def module_from_checkpoint(
    path: str | Path, expected: ModelSize | None = None, **overrides: Any
) -> MFGLitModule:
    """:func:`load_checkpoint` then :func:`build_module`."""
    return build_module(load_checkpoint(path), path, expected, **overrides)


def dataset_config(ckpt: Mapping[str, Any], path: str | Path) -> dict | None:
    """The dataset config a checkpoint was trained with, checked against the allow-list.

    Stored in the checkpoint (``mfg_dataset_config``) or, for checkpoints without it, in the run
    directory's ``config.yaml`` (``<run>/checkpoints/<file>.ckpt`` → ``<run>/config.yaml``).

    Returns:
        A plain dict, or None when neither has one.

    Raises:
        UnsafeConfigError: the config names a target outside the allow-list.
    """
    if ckpt.get("mfg_dataset_config"):
        stored = with_legacy_dataset_settings(dict(ckpt["mfg_dataset_config"]), path)
        check_targets(stored, f"checkpoint {path} (mfg_dataset_config)")
        return stored
    run_config = Path(path).expanduser().resolve().parent.parent / "config.yaml"
    if not run_config.is_file():
        return None
    try:
        cfg = OmegaConf.load(run_config)
    except Exception as err:
        raise CheckpointError(f"cannot read {run_config}: {err}") from err
    if "dataset" not in cfg:
        return None
    try:
        stored = OmegaConf.to_container(cfg.dataset, resolve=True)
    except Exception as err:  # an interpolation into keys the file does not have
        raise CheckpointError(f"{run_config}: cannot resolve dataset: {err}") from err
    stored = with_legacy_dataset_settings(stored, run_config)
    check_targets(stored, str(run_config), "dataset")
    return stored
