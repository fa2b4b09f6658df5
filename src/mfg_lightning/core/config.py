"""Where the Hydra configs live, and composing them outside a Hydra app (tests, notebooks);
reading a hand-edited YAML file of the package (:func:`load_yaml_mapping`).

``conf/`` sits at the top level of the repository. A wheel ships it inside the package as
``mfg_lightning/conf`` (pyproject's ``force-include``); an editable install reads the
repository's copy.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import yaml
from omegaconf import DictConfig, OmegaConf


def processes_cpus(workers: int | None) -> int:
    """The cores one training process needs: itself plus its data loader's ``workers``.

    The ``${processes_cpus:${dataset.num_workers}}`` resolver of ``conf/hydra/launcher/slurm.yaml``
    (sbatch ``--cpus-per-task``), so that a job asks for what its trainer will start."""
    n = 0 if workers is None else int(workers)
    if n < 0:
        raise ValueError(f"dataset.num_workers must be >= 0, got {workers}")
    return 1 + n


def loader_workers(most: int, processes: object = 1) -> int:
    """The ``${loader_workers:most[,processes]}`` resolver of ``conf/trainer/gpu.yaml`` and
    ``ddp_gpu.yaml``: :func:`mfg_lightning.core.machine.loader_workers` (at most ``most`` loader
    workers per training process, as the usable cores allow)."""
    from mfg_lightning.core.machine import loader_workers as sized

    return sized(int(most), processes)


# registered at import: every entry point imports this module before Hydra composes
for _name, _resolver in (("processes_cpus", processes_cpus), ("loader_workers", loader_workers)):
    if not OmegaConf.has_resolver(_name):
        OmegaConf.register_new_resolver(_name, _resolver)


def config_dir() -> Path:
    """Absolute path of the config directory, for installed and editable packages alike."""
    package = Path(__file__).resolve().parents[1]  # mfg_lightning/
    packaged = package / "conf"
    if packaged.is_dir():
        return packaged
    repo = package.parents[1] / "conf"
    if repo.is_dir():
        return repo
    raise FileNotFoundError(
        f"mfg_lightning's configs are neither at {packaged} nor at {repo}; reinstall the package"
    )


CONFIG_DIR = str(config_dir())


def compose(config_name: str = "train", overrides: Sequence[str] = ()) -> DictConfig:
    """Compose a config as the entry points would, without running anything.

    Inside a running Hydra app it composes with that app's Hydra (whose search path is
    :data:`CONFIG_DIR` for this package's entry points). ``hydra:`` interpolations (the run
    directory) are not available outside an app: pass
    ``paths.output_dir=...`` in ``overrides`` when the config will be instantiated.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        # Inside a running app (an entry point that composes the configs of its own runs, e.g.
        # mfg_lightning.reproduce): its Hydra already searches CONFIG_DIR.
        return hydra_compose(
            config_name=config_name, overrides=list(overrides), return_hydra_config=False
        )
    with initialize_config_dir(version_base="1.3", config_dir=CONFIG_DIR):
        return hydra_compose(
            config_name=config_name, overrides=list(overrides), return_hydra_config=False
        )


class _UniqueKeys(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (it keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set[str] = set()
        for key_node, _ in node.value:
            key = str(self.construct_object(key_node, deep=deep))
            if key in seen:  # the mark of the repeated key: its file and line
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def load_yaml_mapping(path: Path) -> dict:
    """A YAML file holding one mapping (UTF-8, safe types only), its keys as written; a key given
    twice or a file that is not a mapping is refused, naming the file and the line."""
    with path.open(encoding="utf-8") as fh:  # a stream: YAML's errors name the file
        data = yaml.load(fh, Loader=_UniqueKeys)  # a SafeLoader
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping, got {type(data).__name__}")
    return data
