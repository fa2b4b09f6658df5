"""Where computed flow is cached: ``paths.cache_dir``, by default ``$MFG_CACHE_DIR`` or
``~/.cache/mfg_lightning`` (never the user's data directory)."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """``$MFG_CACHE_DIR`` or ``~/.cache/mfg_lightning`` (the ``paths.cache_dir`` default)."""
    env = os.environ.get("MFG_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "mfg_lightning"
