"""A Hydra entry point's command line checked before Hydra runs it, so that a mistake is one
``error:`` line (:mod:`mfg_lightning.core.errors` prints it and exits with status 2) and nothing
is written; and each entry point's own ``--help``.

:func:`check_command_line` composes the config as Hydra will (about 0.3 s a composition; it
imports the classes the config builds, which the entry point imports anyway) and refuses:

* a key the config does not have (``model.loss.ws=100``), naming the closest keys it has
  ("did you mean model.loss.w_s?"). Hydra's own advice, ``+model.loss.ws=100``, would add a key
  that nothing reads;
* a value Hydra cannot compose (an ambiguous ``a=1,2`` without ``-m``, a bad interpolation);
* a key the config leaves mandatory (``???``, e.g. ``evaluate``'s ``ckpt_path``), saying what to
  type;
* a value of the wrong type (``dataset.batch_size=abc``, ``seed=abc``): what a setting takes is
  the annotation of the parameter it becomes (its node's ``_target_``), else its default's type;
* a setting that the object its node builds does not take: an added key (``+model.foo=1``) or a
  preset that does not fit (``dataset=kitti debug=tiny`` sets ``dataset.sequence_length``);
* a run directory that cannot be written (a read-only mount), before Hydra makes it;
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
import inspect
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
    message = (
        _whole_number_error(floats, leaves, argv)
        or _unknown_sweep_key(parsed, leaves, set(cfg.hydra.runtime.choices))
        or _type_error(config_name, parsed, plain, floats, cfg, leaves, container)
    )
    if message is not None:
        return CommandLine(argv, error=message)
    message = _unknown_settings(container, plain, dict(cfg.hydra.runtime.choices))
    if message is not None:
        return CommandLine(argv, error=message)
    swept = {o.key_or_group for o in parsed if o.is_sweep_override()}
    for key, value in leaves.items():
        if value == "???" and key not in swept and not key.startswith("hydra"):
            placeholder = "<path>" if key.endswith(("path", "dir", "root")) else "<value>"
            typed = f"python -m {module} {key}={placeholder}"
            return CommandLine(argv, error=f"{key} is not set; type: {typed} [...]")
    return CommandLine(argv, error=unwritable_run_dir(cfg, multirun=bool(args.multirun)))


def _whole_number_error(
    floats: Sequence[Any], leaves: dict[str, Any], argv: list[str]
) -> str | None:
    """A float given for a whole-number setting: refused unless it is a whole number, which is
    then written into ``argv`` as the integer (``trainer.max_steps=1e3``)."""
    for o in floats:
        default, value = leaves.get(o.key_or_group), o.value()
        if o.is_add() or o.is_force_add() or isinstance(default, bool):
            continue
        if o.key_or_group.rpartition(".")[2] in FRACTION_OR_COUNT:
            continue
        if o.key_or_group not in leaves:
            return _unknown_key_message(o.input_line, o.key_or_group, list(leaves))
        if isinstance(default, int):
            if not float(value).is_integer():
                return (f"{o.input_line}: {o.key_or_group} is a whole number (default {default}); "
                        f"give one, e.g. {o.key_or_group}={round(value)}")  # fmt: skip
            prefix = o.input_line[: len(o.input_line) - len(o.input_line.lstrip("+~"))]
            argv[argv.index(o.input_line)] = f"{prefix}{o.key_or_group}={int(value)}"
    return None


def _unknown_sweep_key(
    parsed: Sequence[Any], leaves: dict[str, Any], groups: set[str]
) -> str | None:
    """A swept key the config does not have (a group's options were checked by Hydra)."""
    for o in parsed:
        key = o.key_or_group
        if not o.is_sweep_override() or o.is_add() or o.is_force_add() or "/" in key:
            continue
        if key not in leaves and key not in groups and not key.startswith("hydra"):
            return _unknown_key_message(o.input_line, key, list(leaves))
    return None


def _type_error(
    config_name: str,
    parsed: Sequence[Any],
    plain: Sequence[Any],
    floats: Sequence[Any],
    cfg: Any,
    leaves: dict[str, Any],
    container: dict,
) -> str | None:
    """A value, or a value of a sweep (``-m dataset.batch_size=8,abc``), of a type its setting
    does not take."""
    from hydra.errors import HydraException

    groups = set(cfg.hydra.runtime.choices)
    group_lines = [o.input_line for o in plain if o.key_or_group in groups]
    try:  # each setting's default, under the groups chosen
        defaults = dict(config_keys(_container(_compose(config_name, group_lines))))
    except HydraException:
        defaults = {}
    for o in plain:
        key = o.key_or_group
        if key in groups or key.startswith("hydra") or o.is_delete() or o in floats:
            continue
        message = _wrong_type(o.input_line, key, o.value(), defaults.get(key), container)
        if message is not None:
            return message
    for o in parsed:
        key = o.key_or_group
        if not o.is_sweep_override() or key in groups or key.startswith("hydra"):
            continue
        try:
            values = list(o.sweep_iterator())
        except Exception:  # an interval (Optuna's) has no values to list
            continue
        for value in values:
            message = _wrong_type(o.input_line, key, value, leaves.get(key), container)
            if message is not None:
                return message
    return None


def unwritable_run_dir(cfg: Any, multirun: bool) -> str | None:
    """The message for a run directory that cannot be made or written (a read-only mount, a
    file in its path), or None; checked by making and removing a directory in it, or in the
    nearest folder above it that exists (Hydra makes the rest). An existing directory that Hydra
    writes nothing into (``data.check``: ``hydra.run.dir=.`` without ``.hydra/``) is not
    checked."""
    import tempfile

    from omegaconf import OmegaConf

    setting = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    try:
        run_dir = Path(str(OmegaConf.select(cfg, setting, throw_on_missing=True)))
    except Exception:  # an interpolation that fails here fails in Hydra too
        return None
    if run_dir.is_dir() and OmegaConf.select(cfg, "hydra.output_subdir") is None:
        return None
    there = run_dir
    while not there.exists() and there != there.parent:
        there = there.parent
    try:
        Path(tempfile.mkdtemp(prefix=".mfg-write-check-", dir=there)).rmdir()
    except OSError as err:
        why = err.strerror or type(err).__name__
        return (
            f"{setting}={run_dir}: cannot write there ({why}: {there}); choose a writable "
            f"directory with paths.log_dir=<dir> (or MFG_LOG_DIR), or {setting}=<dir>"
        )
    return None


#: What a value of each plain type is called in a message.
_KINDS = {int: "a whole number", float: "a number", bool: "true or false", str: "a string",
          list: "a list", dict: "a mapping", type(None): "null"}  # fmt: skip


def _kind(value: Any) -> type:
    """The plain type of an override's value (Hydra gives lists and dicts as Python's own)."""
    for kind in (bool, int, float, str, list, dict):
        if isinstance(value, kind):
            return kind
    return type(None) if value is None else object


def _kinds_of(annotation: Any) -> set[type] | None:
    """The plain types a parameter's annotation accepts (``int | None`` → {int, None}; a
    ``Literal`` → the types of its values; ``Sequence[str]`` → {list}), or None where it names
    anything else (a class, ``Any``, a tensor): then it is not checked."""
    import collections.abc
    import types
    import typing

    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        kinds: set[type] = set()
        for arg in typing.get_args(annotation):
            sub = _kinds_of(arg)
            if sub is None:
                return None
            kinds |= sub
        return kinds
    if origin is typing.Literal:
        return {_kind(v) for v in typing.get_args(annotation)}
    if annotation is type(None) or annotation is None:
        return {type(None)}
    if annotation is float:
        return {float, int}
    if annotation in (int, bool, str):
        return {annotation}
    if origin in (list, tuple, collections.abc.Sequence) or annotation in (list, tuple):
        return {list}
    if origin is dict or annotation is dict:
        return {dict}
    return None


def _wants(kinds: set[type]) -> str:
    order = [int, float, bool, str, list, dict, type(None)]
    if float in kinds:
        kinds = kinds - {int}
    return " or ".join(_KINDS[k] for k in order if k in kinds)


def _target_node(container: dict, key: str) -> tuple[dict | None, str]:
    """The config node holding ``key`` when that node names a ``_target_`` (what it builds
    receives ``key``'s last part as a keyword), and that last part."""
    parent, _, leaf = key.rpartition(".")
    node: Any = container
    for part in parent.split(".") if parent else []:
        node = node.get(part) if isinstance(node, dict) else None
    if isinstance(node, dict) and isinstance(node.get("_target_"), str):
        return node, leaf
    return None, leaf


def _wrong_type(arg: str, key: str, value: Any, default: Any, container: dict) -> str | None:
    """The message for an override whose value is not of the type its setting takes, or None.

    What a setting takes: the annotation of the parameter it becomes (the ``_target_`` of its
    node), else the type of its default. Null and ``${...}`` interpolations are not checked,
    nor a setting whose annotation or default names no plain type."""
    if value is None or (isinstance(value, str) and "${" in value):
        return None
    kinds: set[type] | None = None
    node, leaf = _target_node(container, key)
    if node is not None:
        found = _parameters(_locate(node["_target_"]))
        if found is not None and leaf in found:
            kinds = _kinds_of(found[leaf])
    if kinds is None and default is not None:
        kinds = {_kind(default)} | ({int} if isinstance(default, float) else set())
        if object in kinds or str in kinds:  # a string setting takes what Hydra reads as 1
            return None
    got = _kind(value)
    if kinds is None or got in kinds:
        return None
    shown = f"{value!r}" if isinstance(value, str) else str(value)
    was = "" if default is None else f" (default {default})"
    return f"{arg}: {key} takes {_wants(kinds)}{was}; got {shown}, {_KINDS.get(got, 'a value')}"


def _locate(target: str) -> Any:
    """The object a ``_target_`` names, or None where it cannot be imported (Hydra says why when
    it builds it)."""
    from hydra._internal.utils import _locate as locate

    try:
        return locate(target)
    except Exception:  # any import failure: left to Hydra's own message
        return None


def _parameters(target: Any) -> dict[str, Any] | None:
    """The keyword parameters ``target`` takes (a class: its ``__init__``, following this
    package's ``**kwargs`` up to the base classes that receive them), each with its annotation
    (None where unknown); None where it takes any keyword (or cannot be inspected)."""
    import typing

    if target is None:
        return None
    functions = (
        [c.__dict__["__init__"] for c in target.__mro__ if "__init__" in c.__dict__]
        if isinstance(target, type)
        else [target]
    )
    found: dict[str, Any] = {}
    for fn in functions:
        try:
            signature = inspect.signature(fn)
        except (TypeError, ValueError):
            return None
        try:
            hints = typing.get_type_hints(fn)
        except Exception:  # an unresolvable annotation: that one is not checked
            hints = {}
        takes_more = False
        for name, p in signature.parameters.items():
            if p.kind is p.VAR_KEYWORD:
                takes_more = True
            elif p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and name != "self":
                found.setdefault(name, hints.get(name))
        if not takes_more:
            return found
        if not getattr(fn, "__module__", "").startswith("mfg_lightning."):
            return None  # another library's **kwargs may go anywhere (DDPStrategy: to DDP)
    return None  # **kwargs all the way up (object takes them): anything goes


def _target_nodes(node: Any, path: str = "") -> Iterator[tuple[str, dict]]:
    """Every ``(dotted path, node)`` of a config tree whose node names a ``_target_``."""
    if isinstance(node, dict):
        if isinstance(node.get("_target_"), str) and "${" not in node["_target_"]:
            yield path, node
        for k, v in node.items():
            yield from _target_nodes(v, f"{path}.{k}" if path else str(k))


def _option_sets(group: str, option: str, key: str) -> bool:
    """Whether the option file ``conf/<group>/<option>.yaml`` sets the dotted ``key``."""
    import yaml

    from mfg_lightning.core.config import CONFIG_DIR

    path = Path(CONFIG_DIR) / group / f"{option}.yaml"
    if not path.is_file():
        return False
    text = path.read_text(encoding="utf-8")
    data = yaml.safe_load(text)
    if not any("@package _global_" in line for line in text.splitlines()[:5]):
        package = group.replace("/", ".") + "."  # keys relative to the group's package
        key = key.removeprefix(package) if key.startswith(package) else ""
    node: Any = data
    for part in key.split(".") if key else [None]:
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def _unknown_settings(container: dict, plain: Sequence[Any], choices: dict[str, Any]) -> str | None:
    """The message for a setting that the object its node builds does not take (``+model.foo=1``,
    or a preset such as ``debug=tiny`` that sets ``dataset.sequence_length`` for a dataset
    without one), or None."""
    for path, node in _target_nodes({k: v for k, v in container.items() if k != "hydra"}):
        taken = _parameters(_locate(node["_target_"]))
        if taken is None:
            continue
        unknown = [k for k in node if not str(k).startswith("_") and k not in taken]
        if not unknown:
            continue
        keys = [f"{path}.{k}" if path else str(k) for k in unknown]
        what = node["_target_"]
        added = next((o for o in plain if o.key_or_group in keys), None)
        if added is not None:
            leaf = added.key_or_group.rpartition(".")[2]
            close = closest_keys(leaf, list(taken))
            hint = (f"did you mean {' or '.join(close)}?" if close
                    else f"it takes {', '.join(sorted(taken))}")  # fmt: skip
            return f"{added.input_line}: {what} ({path}) takes no setting {leaf}; {hint}"
        chosen = choices.get(path)
        fits = f" {path}={chosen}" if chosen else f" {path}"
        for group, option in choices.items():
            if group.startswith("hydra") or option is None or group == path:
                continue
            setting = [k for k in keys if _option_sets(group, str(option), k)]
            if setting:
                return (f"{group}={option} does not fit{fits}: it sets {', '.join(setting)}, "
                        f"which {what} does not take")  # fmt: skip
        return f"{', '.join(keys)}: {what} ({path}) takes no such setting"
    return None


def main_module(fn: Any) -> str:
    """The importable name of the module that defines ``fn`` (``mfg_lightning.train`` also when it
    runs as ``python -m mfg_lightning.train``, whose ``__name__`` is ``__main__``)."""
    module = sys.modules.get(fn.__module__)
    spec = getattr(module, "__spec__", None)
    return getattr(spec, "name", None) or fn.__module__
