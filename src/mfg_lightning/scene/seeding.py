"""Random generators seeded from keys, so that the same key always draws the same numbers
in any process, worker or call order."""

from __future__ import annotations

import hashlib

import numpy as np


def seeded_rng(seed: int, *keys: object) -> np.random.Generator:
    """A generator seeded from ``seed`` and any keys: independent of call order and workers."""
    digest = hashlib.blake2b(repr((seed, *keys)).encode(), digest_size=8).digest()
    return np.random.default_rng(int.from_bytes(digest, "little"))
