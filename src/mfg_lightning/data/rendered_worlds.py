"""The worlds of the rendered datasets (:mod:`mfg_lightning.data.rendered`) from
``dataset.world``: the world settings, the objects crossing the road, and the generated world of
one trajectory. The scene modules are imported on first use, so that ``flow=exact`` never loads
them."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch


def world_config(fields: dict[str, Any]) -> Any:
    """``dataset.world`` → :class:`~mfg_lightning.scene.worlds.WorldConfig` (None: defaults),
    the crossings' keys (:data:`mfg_lightning.scene.crossing.KEYS`) left to
    :func:`crossing_config`."""
    from mfg_lightning.scene import worlds
    from mfg_lightning.scene.crossing import KEYS

    known = {f.name for f in dataclasses.fields(worlds.WorldConfig)}
    unknown = sorted(set(fields) - known - set(KEYS))
    if unknown:
        raise ValueError(
            f"unknown dataset.world setting(s) {unknown}; known: {sorted(known | set(KEYS))}"
        )
    own = {k: tuple(v) if isinstance(v, list) else v for k, v in fields.items() if k in known}
    return worlds.WorldConfig(**own) if own else None


def crossing_config(fields: dict[str, Any]) -> Any:
    """The crossing objects of ``dataset.world``
    (:class:`~mfg_lightning.scene.crossing.CrossingConfig`; None: none)."""
    if not fields:
        return None
    from mfg_lightning.scene.crossing import split_world_fields

    return split_world_fields(fields)[1]


def crossing_module(crossing: Any) -> tuple[Any, ...]:
    """The crossings' module where a dataset has crossings (part of its cache key), else ()."""
    if crossing is None:
        return ()
    from mfg_lightning.scene import crossing as module

    return (module,)


def generate_world(
    poses: torch.Tensor, seed: int, name: str, config: Any = None, crossing: Any = None
) -> Any:
    """The persistent world of one trajectory
    (:meth:`mfg_lightning.scene.worlds.World.generate`), with ``crossing``'s objects crossing
    the road added (:func:`mfg_lightning.scene.crossing.with_crossings`; None: none)."""
    from mfg_lightning.scene import worlds

    world = worlds.World.generate(poses, seed=seed, name=name, config=config)
    if crossing is None:
        return world
    from mfg_lightning.scene.crossing import with_crossings

    return with_crossings(world, crossing)
