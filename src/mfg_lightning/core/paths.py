"""Paths as a committed report names them: never an absolute path of the machine that wrote it."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

__all__ = ["portable_overrides", "portable_path"]


def portable_path(text: str, root: str | Path, cache: str | Path | None = None) -> str:
    """``text`` as a reader of a report can use it, if it is an absolute path.

    Args:
        text: any text; only an absolute path is rewritten.
        root: the repository (or working directory) the report is read from.
        cache: the user cache (``paths.cache_dir``), shown as ``<cache>``; None: no such root.

    Returns:
        The path relative to ``root``; ``../…`` beside it (``../shared/…``); ``<cache>/…`` under
        ``cache``; else ``<path>``. Other text is returned as it is.
    """
    if not Path(text).is_absolute():
        return text
    # Normalised, links kept as they are: a ../shared that is a link still reads as ../shared.
    path = Path(os.path.abspath(text))
    top = Path(os.path.abspath(Path(root).expanduser()))
    bases = [(top, None), (top.parent, "..")]
    if cache is not None:
        bases.append((Path(os.path.abspath(Path(cache).expanduser())), "<cache>"))
    for base, shown in bases:
        try:
            rest = path.relative_to(base)
        except ValueError:
            continue
        return str(rest) if shown is None else f"{shown}/{rest}"
    return "<path>"


def portable_overrides(
    overrides: Iterable[str], root: str | Path, cache: str | Path | None = None
) -> list[str]:
    """Hydra overrides ``key=value`` with every absolute-path value made :func:`portable_path`."""
    out = []
    for item in overrides:
        key, sep, value = str(item).partition("=")
        out.append(f"{key}{sep}{portable_path(value, root, cache)}" if sep else str(item))
    return out
