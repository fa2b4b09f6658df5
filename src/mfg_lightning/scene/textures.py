"""Procedural textures of the persistent-world renderer: seeded random tables, value noise,
noise octaves and box-filtered lines, all prefiltered for a pixel's footprint.

Every function is elementwise or a table lookup (no transcendental functions on pixel tensors),
so a texture is bit-identical in any process and thread count. Coordinates are surface
coordinates in metres unless stated; footprints are the metres one pixel spans on the surface.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch

from mfg_lightning.scene.seeding import seeded_rng

__all__ = [
    "NOISE_SIZE",
    "cell_random",
    "coverage",
    "fade",
    "fbm",
    "grey_rgb",
    "lookup",
    "noise",
    "noise_table",
    "periodic_dist",
    "random_table",
]

#: Side of the square lattice of random values that value noise interpolates (a power of two).
NOISE_SIZE = 256


def noise_table(seed: int, name: str) -> torch.Tensor:
    """The world's lattice of random values in [-1, 1]: flat ``(NOISE_SIZE²,)`` float32.

    Args:
        seed, name: the world's seed and trajectory name (``World.seed``, ``World.name``).
    """
    return random_table(seed, name, "texture")


@functools.lru_cache(maxsize=64)
def random_table(seed: int, name: str, what: str) -> torch.Tensor:
    """A world's table of random float32 values: uniform in [-1, 1] (``"texture"``,
    ``(NOISE_SIZE²,)``) or standard normal (``"sensor"``, ``(2¹⁶,)``). Kept per world (tables
    are small and a trajectory's frames are rendered in bulk)."""
    rng = seeded_rng(seed, "world", name, what)
    if what == "texture":
        values = rng.uniform(-1, 1, NOISE_SIZE * NOISE_SIZE)
    else:
        values = rng.standard_normal(1 << 16)
    return torch.from_numpy(values.astype(np.float32))


def lookup(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``table[index]`` for a 1-D table and an integer index of any shape (``index_select``,
    several times faster than advanced indexing on CPU); shaped like ``index``."""
    return table.index_select(0, index.reshape(-1)).view(index.shape)


def noise(table: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Value noise in [-1, 1] at lattice coordinates ``(a, b)`` (``(n,)`` each, lattice cells;
    smoothstep-interpolated), ``(n,)``."""
    n = NOISE_SIZE
    fa, fb = a.floor(), b.floor()
    ta, tb = a - fa, b - fb
    ta = ta * ta * (3 - 2 * ta)
    tb = tb * tb * (3 - 2 * tb)
    ia, ib = fa.long() & (n - 1), fb.long() & (n - 1)
    ja, jb = (ia + 1) & (n - 1), (ib + 1) & (n - 1)
    v00, v01 = lookup(table, ib * n + ia), lookup(table, ib * n + ja)
    v10, v11 = lookup(table, jb * n + ia), lookup(table, jb * n + ja)
    top = v00 + (v01 - v00) * ta
    bottom = v10 + (v11 - v10) * ta
    return top + (bottom - top) * tb


def cell_random(table: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """A random value in [-1, 1] per integer cell ``(i, j)`` (e.g. per window or slab; ``(n,)``
    each, whole numbers as floats), ``(n,)``."""
    n = NOISE_SIZE
    return lookup(
        table, ((j.long() * 7 + 3) & (n - 1)) * n + ((i.long() * 13 + j.long()) & (n - 1))
    )


def fade(footprint: torch.Tensor, wavelength: float) -> torch.Tensor:
    """Weight of a texture component of ``wavelength`` seen through a pixel of ``footprint``
    (both metres): 1 while it spans four pixels or more, 0 below ~1.3."""
    return (1.5 - 2.0 * footprint / wavelength).clamp(0.0, 1.0)


def fbm(
    table: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    footprint: torch.Tensor,
    octaves: Sequence[tuple[float, float]],
    offset: torch.Tensor | float = 0.0,
) -> torch.Tensor:
    """Sum of noise octaves ``(wavelength m, amplitude)`` at surface coordinates ``(a, b)``
    (``(n,)`` metres), each faded by the footprint ``(n,)`` (and computed only where it has not
    faded out), ``(n,)``."""
    out = torch.zeros_like(a)
    for k, (wavelength, amplitude) in enumerate(octaves):
        weight = fade(footprint, wavelength)
        shift = 37.0 * k + offset
        if bool((weight > 0).all()):
            value = noise(table, a / wavelength + shift, b / wavelength + 0.61 * shift)
            out = out + amplitude * weight * value
            continue
        sel = (weight > 0).nonzero(as_tuple=True)[0]
        if not len(sel):
            continue
        if isinstance(shift, torch.Tensor):
            shift = shift.index_select(0, sel)
        value = noise(
            table,
            a.index_select(0, sel) / wavelength + shift,
            b.index_select(0, sel) / wavelength + 0.61 * shift,
        )
        out.index_add_(0, sel, amplitude * weight.index_select(0, sel) * value)
    return out


def coverage(
    dist: torch.Tensor, width: float | torch.Tensor, footprint: torch.Tensor
) -> torch.Tensor:
    """Fraction of a pixel's footprint (an interval of ``footprint`` metres centred ``dist``
    from a line's centre) covered by the line of ``width`` metres: box-filtered edges. All
    ``(n,)`` (or a float ``width``); the fraction in [0, 1]."""
    half_fp = footprint * 0.5
    if isinstance(width, torch.Tensor):
        lo = torch.maximum(dist - half_fp, -0.5 * width)
        hi = torch.minimum(dist + half_fp, 0.5 * width)
    else:
        lo = (dist - half_fp).clamp_min(-0.5 * width)
        hi = (dist + half_fp).clamp_max(0.5 * width)
    return (hi - lo).clamp_min_(0.0).div_(footprint.clamp_min(1e-6))


def periodic_dist(
    x: torch.Tensor, period: float | torch.Tensor, centre: float | torch.Tensor
) -> torch.Tensor:
    """Distance from ``x`` to the nearest of ``centre + k · period`` (same units as ``x``)."""
    q = (x - centre) / period
    return (q - q.round()).abs() * period


def grey_rgb(v: torch.Tensor, tint: Sequence[float] = (1.0, 1.0, 1.0)) -> torch.Tensor:
    """Grey levels ``(n,)`` as tinted RGB ``(n, 3)``."""
    return v[:, None] * torch.tensor(tint, dtype=v.dtype)
