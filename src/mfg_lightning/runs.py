"""Building the parts of a run from a config, and writing what a run produced.

Shared by the entry points (train, evaluate) so that each of them stays thin.
"""

from __future__ import annotations

import json
import logging
import math
import subprocess
from pathlib import Path
from typing import Any

import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.atomic import atomic_write_text

log = logging.getLogger(__name__)


def instantiate_list(cfg: DictConfig | None) -> list[Any]:
    """Instantiate every entry with a ``_target_`` of a config mapping (callbacks, loggers)."""
    if not cfg:
        return []
    return [instantiate(v) for v in cfg.values() if isinstance(v, DictConfig) and "_target_" in v]


def build_model(cfg: DictConfig) -> L.LightningModule:
    """Instantiate the LightningModule and remember its resolved config for checkpoints."""
    model = instantiate(cfg.model)
    model.model_config = OmegaConf.to_container(cfg.model, resolve=True)
    model.dataset_config = OmegaConf.to_container(cfg.dataset, resolve=True)
    return model


def to_float(value: Any) -> float | None:
    """A metric value as a JSON-safe float (None for NaN or infinity)."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def write_metrics(path: Path, metrics: dict[str, Any], extra: dict[str, Any] | None = None) -> dict:
    """Write ``metrics.json``: ``{"metrics": {...}, **extra}`` with plain floats."""
    payload = {"metrics": {k: to_float(v) for k, v in sorted(metrics.items())}}
    payload.update(extra or {})
    atomic_write_text(path, json.dumps(payload, indent=2) + "\n")
    return payload


def git_commit() -> str | None:
    """The commit of the source tree the package was imported from, if it is a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else None


def run_info() -> dict[str, Any]:
    """Version information stored with every run."""
    import torch

    from mfg_lightning import __version__

    return {
        "mfg_lightning": __version__,
        "git_commit": git_commit(),
        "torch": torch.__version__,
        "lightning": L.__version__,
    }


class UserError(Exception):
    """Base class marker: errors whose message is the whole story (bad input, not a bug)."""


def user_error_message(err: BaseException) -> str | None:
    """The one-line message for an error caused by the user's input, or None for a bug.

    Input errors are the project's own ``ValueError`` subclasses (bad config values, malformed
    files, checkpoints that do not fit) and missing files; Hydra wraps errors raised while
    building objects from the config in ``InstantiationException``, whose cause is unwrapped.
    """
    from hydra.errors import InstantiationException

    if isinstance(err, InstantiationException) and err.__cause__ is not None:
        return user_error_message(err.__cause__)
    if isinstance(err, (ValueError, FileNotFoundError, UserError)):
        return (
            " ".join(str(err).split("\n")[:1]) if isinstance(err, FileNotFoundError) else str(err)
        )
    return None


def in_multirun() -> bool:
    """Whether the calling code runs as one job of a Hydra multirun (``-m``)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def exit_on_user_error(fn):
    """Decorator for entry points: input errors print ``error: …`` and exit with status 2;
    anything else (a bug) propagates with its traceback.

    Inside a multirun the error is logged (into the job's ``<job>/<task>.log``, where
    ``mfg_lightning.report`` finds the reason) and re-raised instead: exiting would kill the
    whole sweep, while Hydra records a raised error as this job's failure, runs the remaining
    jobs and fails the sweep at the end.
    """
    import functools
    import sys

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except Exception as err:
            message = user_error_message(err)
            if message is None:
                if in_multirun():
                    log.exception("job failed: %s: %s", type(err).__name__, err)
                raise
            if in_multirun():
                log.error("error: %s", message)
                raise
            print(f"error: {message}", file=sys.stderr)
            sys.exit(2)

    return wrapper


def unknown_choice(config_dir: str | Path, overrides: list[str]) -> str | None:
    """The message for the first ``group=option`` override naming an option that
    ``config_dir/<group>/`` does not have (e.g. ``flow=sift``), or None.

    Only plain overrides of an existing group are checked; sweeps (``a,b``, ``choice(…)``),
    packages (``group@pkg=``), additions and deletions are left to Hydra.
    """
    root = Path(config_dir)
    for arg in overrides:
        key, sep, value = arg.partition("=")
        if not sep or key.startswith(("+", "~", "-")) or "@" in key:
            continue
        if any(c in value for c in ",()[]{}$*") or value in ("", "null"):
            continue
        group = root / key.replace(".", "/")
        if not group.is_dir() or (group / f"{value}.yaml").is_file():
            continue
        options = sorted(p.stem for p in group.glob("*.yaml"))
        return (
            f"{key}={value}: Could not find '{key}/{value}' (no such option of the {key} group); "
            f"options: {', '.join(options)}"
        )
    return None


def exit_on_unknown_choice(fn):
    """Decorator for ``@hydra.main`` entry points (put it outside): an override naming an option
    a config group does not have is one ``error: …`` line and exit status 2, as other input
    errors (Hydra itself prints its search path and exits with 1)."""
    import functools
    import sys

    from mfg_lightning.config import CONFIG_DIR

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        message = unknown_choice(CONFIG_DIR, sys.argv[1:])
        if message is not None:
            print(f"error: {message}", file=sys.stderr)
            sys.exit(2)
        return fn(*args, **kwargs)

    return wrapper
