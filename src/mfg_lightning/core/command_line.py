"""A Hydra entry point's command line checked before Hydra runs it, so that a mistake is one
``error:`` line (:mod:`mfg_lightning.core.errors` prints it and exits with status 2) and nothing
is written; and each entry point's own ``--help``.

:func:`check_command_line` composes the config as Hydra will (about 0.3 s) and refuses:

* a key the config does not have (``model.loss.ws=100``), naming the closest keys it has
  ("did you mean model.loss.w_s?"). Hydra's own advice, ``+model.loss.ws=100``, would add a key
  that nothing reads;
* a value Hydra cannot compose (an ambiguous ``a=1,2`` without ``-m``, a bad interpolation);
* a key the config leaves mandatory (``???``, e.g. ``evaluate``'s ``ckpt_path``), saying what to
  type;
* a fraction for an integer setting (``trainer.max_steps=1.5``). A whole-number float for an
  integer setting (``trainer.max_steps=1e3``, which Hydra reads as ``1000.0``) is accepted as the
  integer: the override is rewritten to ``trainer.max_steps=1000``. Lightning's settings that
  read a float as a fraction (``val_check_interval``, ``limit_*_batches``, ...:
  :data:`FRACTION_OR_COUNT`) keep their floats.

Only the command lines of this package's configs are checked (not ``--config-dir`` ones); sweeps
(``-m a=1,2``) are checked key by key. The module imports Hydra only inside its functions.
"""

from __future__ import annotations

import difflib
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = ["CommandLine", "check_command_line", "closest_keys", "config_keys", "help_text"]

#: Lightning settings where a float is a fraction and an integer a count (``1.0``: every batch of
#: an epoch, ``1``: one batch): their floats are left as given.
FRACTION_OR_COUNT = (
    "val_check_interval",
    "limit_train_batches",
    "limit_val_batches",
    "limit_test_batches",
    "limit_predict_batches",
    "overfit_batches",
)


class CommandLine:
    """The outcome of :func:`check_command_line`.

    Attributes:
        argv: the arguments to run with (overrides rewritten where a float became an integer).
        error: the one-line message of a mistake, or None.
        help: the help text to print instead of running, or None.
    """

    def __init__(self, argv: list[str], error: str | None = None, help: str | None = None) -> None:
        self.argv, self.error, self.help = argv, error, help


def config_keys(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """Every leaf ``(dotted key, raw value)`` of a config container (a plain dict/list tree, as
    ``OmegaConf.to_container(cfg, resolve=False)`` gives; mandatory values are ``"???"``)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from config_keys(v, f"{prefix}{k}.")
    else:
        yield prefix.rstrip("."), node


def closest_keys(key: str, keys: Sequence[str], n: int = 3) -> list[str]:
    """The keys of ``keys`` most like ``key``: scored by the likeness of the whole dotted key
    and, under the same parent, of the last part (``ws`` → ``w_s``); the best, and those
    within 0.03 of it, at most ``n``."""
    parent, _, leaf = key.rpartition(".")

    def score(k: str) -> float:
        whole = difflib.SequenceMatcher(None, key, k).ratio()
        k_parent, _, k_leaf = k.rpartition(".")
        part = difflib.SequenceMatcher(None, leaf, k_leaf).ratio() if k_parent == parent else 0
        return max(whole, part)

    scored = sorted(((score(k), k) for k in keys), reverse=True)
    if not scored or scored[0][0] < 0.6:
        return []
    return [k for s, k in scored[:n] if s >= scored[0][0] - 0.03]


def _compose(config_name: str, overrides: Sequence[str]) -> Any:
    from hydra import compose, initialize_config_dir

    from mfg_lightning.core.config import CONFIG_DIR

    with initialize_config_dir(version_base="1.3", config_dir=CONFIG_DIR):
        return compose(config_name, list(overrides), return_hydra_config=True)


def _container(cfg: Any) -> dict:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(cfg, resolve=False)  # type: ignore[return-value]


def _composition_error(err: Exception) -> tuple[str | None, str]:
    """``(the key Hydra could not override or None, Hydra's message on one line)``."""
    text = " ".join(line.strip() for line in str(err).splitlines() if line.strip())
    marker = "Could not override '"
    if marker in text:
        start = text.index(marker) + len(marker)
        return text[start : text.index("'", start)], text
    return None, text


def _unknown_key_message(arg: str, key: str, keys: Sequence[str]) -> str:
    if not key.startswith("hydra"):  # Hydra's own settings are not what a user misspelt
        keys = [k for k in keys if not k.startswith("hydra.")]
    close = closest_keys(key, keys)
    hint = f"did you mean {' or '.join(close)}?" if close else "see the keys with --cfg job"
    return f"{arg}: the config has no key {key}; {hint}"


def help_text(config_name: str, module: str, doc: str | None) -> str:
    """The ``--help`` of one entry point: its module docstring's first paragraph, the usage, and
    the config groups *its* config uses, each with its options and the default."""
    from mfg_lightning.core.config import CONFIG_DIR

    cfg = _compose(config_name, [])
    choices = dict(cfg.hydra.runtime.choices)
    lines = [
        (doc or module).strip().split("\n\n")[0],
        "",
        f"Usage: python -m {module} [group=option ...] [key=value ...] [-m for sweeps]",
        "",
        f"Config groups of conf/{config_name}.yaml (group=option; default in brackets):",
    ]
    for group in sorted(g for g in choices if not g.startswith("hydra")):
        options = sorted(p.stem for p in (Path(CONFIG_DIR) / group).glob("*.yaml"))
        default = "none" if choices[group] is None else choices[group]
        lines.append(f"  {group}: {', '.join(options) or '(none here)'} [{default}]")
    lines += ["", "Keys: print the composed config with --cfg job (one part: --cfg job "
              "--package model). Hydra's own options: --hydra-help."]  # fmt: skip
    return "\n".join(lines)


def check_command_line(
    config_name: str | None, argv: Sequence[str], module: str, doc: str | None = None
) -> CommandLine:
    """Check the arguments of a Hydra entry point (module docstring).

    Args:
        config_name: the entry point's config (``train``, ``evaluate``, ...); None: no check.
        argv: the command line after the program name.
        module: the entry point's module, for messages (``mfg_lightning.evaluate``).
        doc: the entry point's docstring, for ``--help``.
    """
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    argv = list(argv)
    try:
        args = get_args_parser().parse_args(argv)
    except SystemExit:  # Hydra's own usage error: let Hydra say it
        return CommandLine(argv)
    if config_name is None or args.config_path or args.config_dir or args.experimental_rerun:
        return CommandLine(argv)
    config_name = args.config_name or config_name
    if args.help:
        return CommandLine(argv, help=help_text(config_name, module, doc))
    if args.hydra_help or args.shell_completion or args.info:
        return CommandLine(argv)
    try:
        parsed = OverridesParser.create().parse_overrides(args.overrides)
    except HydraException as err:
        return CommandLine(argv, error=_composition_error(err)[1])
    sweeps = [o for o in parsed if o.is_sweep_override()]
    if sweeps and not args.multirun:
        arg = sweeps[0].input_line
        return CommandLine(argv, error=(f"{arg}: a sweep needs -m (--multirun); a list is "
                                        "key=[a,b], a string with a comma key='a,b'"))  # fmt: skip
    plain = [o for o in parsed if not o.is_sweep_override()]
    lines = [o.input_line for o in plain]
    # Whole-number floats for integer settings: composed without them to read the defaults.
    floats = [o for o in plain if isinstance(o.value(), float) and not o.is_delete()]
    try:
        cfg = _compose(config_name, [x for x in lines if x not in {o.input_line for o in floats}])
    except HydraException as err:
        key, text = _composition_error(err)
        if key is None:
            return CommandLine(argv, error=text)
        arg = next((o.input_line for o in plain if o.key_or_group == key), key)
        rest = [x for x in lines if x != arg and x not in {o.input_line for o in floats}]
        try:
            keys = [k for k, _ in config_keys(_container(_compose(config_name, rest)))]
        except HydraException:
            keys = []
        return CommandLine(argv, error=_unknown_key_message(arg, key, keys))
    container = _container(cfg)
    leaves = dict(config_keys(container))
    for o in floats:
        default, value = leaves.get(o.key_or_group), o.value()
        if o.is_add() or o.is_force_add() or isinstance(default, bool):
            continue
        if o.key_or_group.rpartition(".")[2] in FRACTION_OR_COUNT:
            continue
        if o.key_or_group not in leaves:
            return CommandLine(argv, error=_unknown_key_message(o.input_line, o.key_or_group,
                                                                list(leaves)))  # fmt: skip
        if isinstance(default, int):
            if not float(value).is_integer():
                return CommandLine(argv, error=(
                    f"{o.input_line}: {o.key_or_group} is a whole number (default {default}); "
                    f"give one, e.g. {o.key_or_group}={round(value)}"))  # fmt: skip
            prefix = o.input_line[: len(o.input_line) - len(o.input_line.lstrip("+~"))]
            rewritten = f"{prefix}{o.key_or_group}={int(value)}"
            argv[argv.index(o.input_line)] = rewritten
    # Sweeps: their keys must exist too (a group's options were checked by unknown_choice).
    for o in parsed:
        key = o.key_or_group
        if not o.is_sweep_override() or o.is_add() or o.is_force_add() or "/" in key:
            continue
        known = key in leaves or key in dict(cfg.hydra.runtime.choices)
        if not known and not key.startswith("hydra"):
            return CommandLine(argv, error=_unknown_key_message(o.input_line, key,
                                                                    list(leaves)))  # fmt: skip
    swept = {o.key_or_group for o in parsed if o.is_sweep_override()}
    for key, value in leaves.items():
        if value == "???" and key not in swept and not key.startswith("hydra"):
            placeholder = "<path>" if key.endswith(("path", "dir", "root")) else "<value>"
            typed = f"python -m {module} {key}={placeholder}"
            return CommandLine(argv, error=f"{key} is not set; type: {typed} [...]")
    return CommandLine(argv)


def main_module(fn: Any) -> str:
    """The importable name of the module that defines ``fn`` (``mfg_lightning.train`` also when it
    runs as ``python -m mfg_lightning.train``, whose ``__name__`` is ``__main__``)."""
    module = sys.modules.get(fn.__module__)
    spec = getattr(module, "__spec__", None)
    return getattr(spec, "name", None) or fn.__module__
