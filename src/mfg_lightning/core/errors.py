"""One way for every entry point to turn a user's mistake into ``error: …`` and exit status 2.

Imports the standard library only; Hydra is imported inside the functions that need it, so quick
command-line tools (``evaluate_poses``, ``data.check``) use this without loading Lightning.

Every Hydra entry point is ``@exit_on_unknown_choice @hydra.main(...) @exit_on_user_error``: the
first checks the command line before anything runs; the last turns a user error raised while
running into the one line and, for any failure, leaves the run directory as
:mod:`mfg_lightning.core.failed_runs` says (removed when nothing was done yet, else marked
``FAILED``).
"""

from __future__ import annotations

import functools
import inspect
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

__all__ = [
    "UserError",
    "exit_on_unknown_choice",
    "exit_on_user_error",
    "in_multirun",
    "report_user_error",
    "unknown_choice",
    "user_error_message",
]

log = logging.getLogger("mfg_lightning.core.errors")

F = TypeVar("F", bound=Callable[..., Any])


class UserError(Exception):
    """Base class marker: errors whose message is the whole story (bad input, not a bug)."""


def user_error_message(err: BaseException) -> str | None:
    """The one-line message for an error caused by the user's input, or None for a bug.

    Input errors are the project's own ``ValueError`` subclasses (bad config values, malformed
    files, checkpoints that do not fit) and missing files; Hydra wraps errors raised while
    building objects from the config in ``InstantiationException``, whose cause is unwrapped.
    """
    if "hydra" in sys.modules:  # an InstantiationException exists only once Hydra is loaded
        from hydra.errors import InstantiationException

        if isinstance(err, InstantiationException) and err.__cause__ is not None:
            cause = err.__cause__
            if isinstance(cause, TypeError) and "unexpected keyword argument" in str(cause):
                # a setting the built object does not take (a config the command line check
                # did not see: --config-dir, a notebook's compose()): Hydra names the node
                where = " ".join(str(err).split()).partition("full_key: ")[2] or "a config node"
                return f"{where}: {cause}"
            return user_error_message(cause)
    if "omegaconf" in sys.modules:  # a mandatory value (???) read while running
        from omegaconf.errors import MissingMandatoryValue

        if isinstance(err, MissingMandatoryValue):
            key = getattr(err, "full_key", None) or "a mandatory key"
            return f"{key} is not set: give {key}=<value> on the command line"
    if isinstance(err, (ValueError, FileNotFoundError, UserError)):
        return (
            " ".join(str(err).split("\n")[:1]) if isinstance(err, FileNotFoundError) else str(err)
        )
    return None


def in_multirun() -> bool:
    """Whether the calling code runs as one job of a Hydra multirun (``-m``)."""
    if "hydra" not in sys.modules:
        return False
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def report_user_error(err: BaseException) -> int:
    """Print ``error: <message>`` for a user error and return the exit status 2; re-raise a bug.

    For entry points that return their exit status (argparse ``main(argv) -> int``) instead of
    being wrapped by :func:`exit_on_user_error`. Must be called inside the ``except`` block.
    """
    message = user_error_message(err)
    if message is None:
        raise err
    print(f"error: {message}", file=sys.stderr)
    return 2


def exit_on_user_error(fn: F) -> F:
    """Decorator for entry points: input errors print ``error: …`` and exit with status 2;
    anything else (a bug) propagates with its traceback.

    Inside a multirun the error is logged (into the job's ``<job>/<task>.log``, where
    ``mfg_lightning.report`` finds the reason) and re-raised instead: exiting would kill the
    whole sweep, while Hydra records a raised error as this job's failure, runs the remaining
    jobs and fails the sweep at the end.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except Exception as err:
            message = user_error_message(err)
            _settle_run(err, message)
            if message is None:
                if in_multirun():
                    log.exception("job failed: %s: %s", type(err).__name__, err)
                raise
            if in_multirun():
                log.error("error: %s", message)
                raise
            print(f"error: {message}", file=sys.stderr)
            sys.exit(2)

    return wrapper  # type: ignore[return-value]


def _run_dir() -> Path | None:
    """The running Hydra job's output directory, or None outside a Hydra job."""
    if "hydra" not in sys.modules:
        return None
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return Path(HydraConfig.get().runtime.output_dir)


def _settle_run(err: BaseException, message: str | None) -> None:
    """Leave the failed job's directory as :func:`~mfg_lightning.core.failed_runs.
    settle_failed_run` says: removed after a user error before any work, else marked ``FAILED``
    with the error in its log and no empty event files. Never raises (the error at hand wins)."""
    from mfg_lightning.core.failed_runs import settle_failed_run

    line = f"error: {message}" if message is not None else f"{type(err).__name__}: {err}"
    try:
        settle_failed_run(_run_dir(), line, err, user=message is not None, keep=in_multirun())
    except OSError as cleanup:  # e.g. a full disk: say so in the log, keep the real error
        log.warning("could not mark the failed run: %s", cleanup)


def unknown_choice(config_dir: str | Path, overrides: list[str]) -> str | None:
    """The message for the first ``group=option`` override naming an option that
    ``config_dir/<group>/`` does not have (e.g. ``flow=sift``), or None.

    Only plain overrides of an existing group are checked; sweeps (``a,b``, ``choice(…)``),
    packages (``group@pkg=``), additions, deletions and ``hydra/…`` groups (whose options
    plugins such as the joblib launcher bring) are left to Hydra.
    """
    root = Path(config_dir)
    for arg in overrides:
        key, sep, value = arg.partition("=")
        if not sep or key.startswith(("+", "~", "-", "hydra")) or "@" in key:
            continue  # hydra/*: Hydra's own groups and its plugins' live outside conf/
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
    """Decorator for ``@hydra.main`` entry points (put it outside): the command line is checked
    before Hydra runs it (:mod:`mfg_lightning.core.command_line`). An option a config group does
    not have, a key the config does not have ("did you mean …?"), a mandatory key left unset or a
    fraction for an integer setting is one ``error: …`` line and exit status 2, and nothing is
    written (Hydra itself prints a traceback or its search path and exits with 1). ``--help``
    prints this entry point's own help."""
    from mfg_lightning.core.command_line import check_command_line, main_module
    from mfg_lightning.core.config import CONFIG_DIR

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        message = unknown_choice(CONFIG_DIR, sys.argv[1:])
        if message is None:
            # The config name of the @hydra.main inside (its closure: hydra.main keeps no
            # attribute for it; tests/test_errors.py checks every entry point finds its own).
            name = inspect.getclosurevars(fn).nonlocals.get("config_name")
            module = main_module(fn)
            line = check_command_line(
                name, sys.argv[1:], module, sys.modules[fn.__module__].__doc__
            )
            if line.help is not None:
                print(line.help)
                sys.exit(0)
            message = line.error
            sys.argv[1:] = line.argv  # e.g. trainer.max_steps=1e3 as trainer.max_steps=1000
        if message is not None:
            print(f"error: {message}", file=sys.stderr)
            sys.exit(2)
        return fn(*args, **kwargs)

    return wrapper
