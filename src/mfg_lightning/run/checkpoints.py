"""Checkpoints of :mod:`mfg_lightning.train`: read them safely, rebuild the module, find the data.

Researchers share checkpoints, so reading one must never run its author's code:

* **Unpickling** uses ``torch.load(weights_only=True)``: tensors, numbers, strings and plain
  containers only, plus the few types that checkpoints written by earlier versions of the project
  hold (:func:`_legacy_safe_globals`: OmegaConf nodes and Hydra's partial of the optimiser class,
  none of which runs anything when it is rebuilt). A pickle that names any other global (a
  payload calling ``os.system``, say) is refused before it runs: :class:`CheckpointError`.
  A file that cannot be read says which of two things it is (:func:`unreadable_checkpoint`, the
  one message every reader of a checkpoint raises): **unsafe**, a pickle naming anything but
  plain data, or **corrupt**, bytes that are not a whole checkpoint (truncated, random, another
  format).
* **Configs** read from a checkpoint (its model config, ``mfg_dataset_config``) or from a run
  directory's ``config.yaml`` are instantiated only if every ``_target_`` in them, at any depth,
  resolves to one of the classes the project's own configs build (:func:`allowed_targets`: every
  ``_target_`` of the model, dataset, flow and object-motion config groups, and torch's
  optimisers and lr schedulers). The check is on the resolved object, so an
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
import pickletools
import warnings
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
import yaml
from omegaconf import OmegaConf
from torch import Tensor

from mfg_lightning.core.config import config_dir

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
    "config_group_targets",
    "dataset_config",
    "load_checkpoint",
    "model_size",
    "module_from_checkpoint",
    "safe_unpickling",
    "stored_model_config",
    "unreadable_checkpoint",
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
    with torch.serialization.safe_globals(list(_legacy_safe_globals())), warnings.catch_warnings():
        # torch warns before refusing a pickle of another protocol; the refusal says it all
        warnings.filterwarnings("ignore", "Detected pickle protocol", UserWarning)
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
        raise unreadable_checkpoint(path, err) from err
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
        raise unreadable_checkpoint(path, err) from err
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a Lightning checkpoint")
    return ckpt


def saved_loader_places(ckpt: dict[str, Any]) -> list[dict[str, Any]]:
    """The training loaders' saved places in a checkpoint's fit loop (empty where none)."""
    loop = ckpt.get("loops", {}).get("fit_loop", {}).get("state_dict", {})
    places = loop.get("combined_loader") or []
    return [p for p in places if isinstance(p, dict)]


def unreadable_checkpoint(path: str | Path, err: BaseException | None = None) -> CheckpointError:
    """The one error for a checkpoint that was not loaded: unsafe, or corrupt.

    **Unsafe**: its pickle names a global that safe loading refuses (``torch.load`` says so, or,
    where torch stopped earlier on an opcode it does not take, the pickle's own opcodes name one
    outside torch and :func:`_legacy_safe_globals`: read with ``pickletools``, nothing unpickled).
    **Corrupt**: anything else, bytes that are not a whole checkpoint (truncated, random, another
    format).

    Args:
        path: the checkpoint file.
        err: what ``torch.load`` raised, or None (the caller found the file is no zip archive,
            which ``torch.save`` writes).

    Returns:
        A :class:`CheckpointError` whose one line names the file and says which it is.
    """
    text = str(err) if err is not None else ""
    refused = next(
        (line.strip() for line in text.splitlines() if "GLOBAL" in line or "allowlisted" in line),
        None,
    )
    if refused is None:
        named = [g for g in _pickle_globals(Path(path)) if not _plain_global(g)]
        refused = f"it names {named[0]}" if named else None
    if refused is not None:
        detail = refused.removeprefix("WeightsUnpickler error: ").split(" was not an allowed")[0]
        return CheckpointError(
            f"checkpoint {path} is unsafe: it holds Python objects other than tensors and plain "
            f"data ({detail}), which could run code when unpickled; it was not loaded"
        )
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    detail = next((line for line in lines if line.startswith("Unsupported operand")), None)
    if detail is None:
        # the first sentence: torch's zip reader adds advice that does not fit on one line
        detail = lines[0].split(". ")[0] if lines else "not a zip archive, which torch.save writes"
    if len(detail) > 160:
        detail = detail[:159] + "…"
    return CheckpointError(
        f"checkpoint {path} is corrupt: not a readable checkpoint (truncated, or not written by "
        f"torch.save: {detail}); it was not loaded"
    )


def _pickle_globals(path: Path) -> list[str]:
    """The globals (``module.name``) that the pickles of a checkpoint name, read opcode by
    opcode with ``pickletools`` (nothing is unpickled): the ``*.pkl`` members of a zip
    checkpoint, or the pickles at the start of another file (torch's legacy format holds a few in
    a row). ``[]`` where the bytes are not a pickle."""
    found: list[str] = []
    try:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as archive:
                for name in archive.namelist():
                    if name.endswith(".pkl"):
                        with archive.open(name) as stream:
                            found += _stream_globals(stream)
        else:
            with open(path, "rb") as stream:
                found += _stream_globals(stream)
    except (OSError, zipfile.BadZipFile, RuntimeError, NotImplementedError):
        pass  # an unreadable archive member: nothing more to learn from it
    return found


def _stream_globals(stream: Any, pickles: int = 8) -> list[str]:
    """The globals named by up to ``pickles`` pickles in a row at the start of ``stream``."""
    found: list[str] = []
    for _ in range(pickles):
        strings: list[str] = []
        ops = 0
        try:
            for op, arg, _ in pickletools.genops(stream):
                ops += 1
                if op.name in ("GLOBAL", "INST"):
                    found.append(str(arg).replace(" ", "."))
                elif op.name == "STACK_GLOBAL":
                    found.append(".".join(strings[-2:]) or "a global")
                elif isinstance(arg, str):
                    strings.append(arg)
        except Exception:  # not (or no longer) a pickle: random bytes, a tensor's data
            break
        if ops == 0:
            break
    return found


def _plain_global(name: str) -> bool:
    """Whether safe loading may name ``name``: torch's own types and rebuild functions, and
    the legacy types :func:`_legacy_safe_globals` allows."""
    if name.startswith("torch.") or name == "collections.OrderedDict":
        return True
    return name in {f"{t.__module__}.{t.__qualname__}" for t in _legacy_safe_globals()}


# --------------------------------------------------------------------------------------------
# Configs: the allow-list
# --------------------------------------------------------------------------------------------

#: The config groups whose classes a config read from a checkpoint or a run directory may build:
#: every ``_target_`` in their YAML files (:func:`config_group_targets`). A new dataset, network
#: or module is allowed by adding its config file; torch's optimisers and lr schedulers are added
#: by :func:`allowed_targets`.
TARGET_GROUPS = ("model", "dataset", "flow", "object_motion")


def config_group_targets(groups: Sequence[str] = TARGET_GROUPS) -> set[str]:
    """Every ``_target_`` named at any depth in the YAML files of the config ``groups``."""
    found: set[str] = set()

    def walk(node: Any) -> None:
        if isinstance(node, Mapping):
            if isinstance(node.get("_target_"), str):
                found.add(node["_target_"])
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    for group in groups:
        for path in sorted((config_dir() / group).glob("*.yaml")):
            walk(yaml.safe_load(path.read_text()))
    return found


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
    project = [_resolve(name) for name in sorted(config_group_targets())]
    return frozenset(project + _optimisers_and_schedulers())


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
                    "configs build (conf/{model,dataset,flow,object_motion}/, torch optimisers "
                    "and lr schedulers); refusing to instantiate it"
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
