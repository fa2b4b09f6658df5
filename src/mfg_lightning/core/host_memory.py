"""Keep the memory that freed tensors held inside the process, so that the next training step
reuses it instead of asking the kernel for fresh pages.

Why: every training step frees its activations and (``zero_grad(set_to_none=True)``, Lightning's
and torch's default) its gradients, and allocates them again in the next step. glibc's ``malloc``
serves blocks of hundreds of kilobytes to tens of megabytes from ``mmap`` and returns them with
``munmap`` when they are freed, or trims the heap's free top; the next step then takes a page
fault for every 4 KiB page it touches again. Counted with ``getrusage`` (a count, whatever the
machine's load): the quick start's network at batch 16 took 13,000–14,000 minor faults per step,
and 0 once freed memory stays (``bench/results/throughput.md``, "Host memory kept").

:func:`keep_freed_memory` raises glibc's mmap and trim thresholds with ``mallopt`` (documented
glibc API, the same as the ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_`` environment
variables, which glibc reads only when a process starts). The process keeps its peak footprint
instead of handing freed memory back: its resident size stays at the high-water mark a training
reaches anyway. Elsewhere (macOS, Windows, musl) it does nothing and says so.

It also serves every block from the heap (``M_MMAP_MAX`` 0, glibc's own switch for it): glibc
takes a block above 32 MiB, the largest threshold ``mallopt`` accepts, from ``mmap`` whatever
the threshold. On an AVX2-only AMD EPYC, oneDNN's convolutions at batch 16 on 2 threads ask for
one 36.3 MiB scratch block a step (``strace``: one ``mmap`` and ``munmap`` of 38,047,744 bytes
a step); it took 2,400 of the 6,000–8,000 faults a step until the heap served it
(``tests/test_host_memory.py``). An AVX-512 machine runs other oneDNN kernels, with smaller blocks.

:func:`freed_memory_kept` applies it for one block of code (``train()``) and then sets glibc's
starting values back and hands the kept memory back (``malloc_trim``), so that a notebook or a
test that trains in-process goes on as before. ``mallopt`` has no getter: this module records
what it set (:func:`allocator_settings`), and a 40 MiB block shows it (``mallinfo2``: from
``mmap`` under glibc's own settings, from the heap while memory is kept). Once a threshold is
set, glibc no longer raises its mmap threshold by itself (its "dynamic threshold"); no call turns
that back on, so the restored process starts again from glibc's 128 KiB.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

log = logging.getLogger(__name__)

#: ``mallopt`` parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
#: Blocks below this come from the heap, not from mmap: glibc's largest accepted value on 64-bit
#: (HEAP_MAX_SIZE / 2 = 32 MiB); the quick start's largest tensor, the decoders' weights and their
#: gradients, is 24.6 MB.
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Freed memory at the heap's top is returned to the kernel only above this: never, in practice.
TRIM_THRESHOLD = 2**31 - 1
#: No block from mmap at all: the larger ones (oneDNN's scratch, above MMAP_THRESHOLD) too.
MMAP_MAX = 0
#: The settings while freed memory is kept: (mmap threshold, trim threshold, mmap max).
KEPT = (MMAP_THRESHOLD, TRIM_THRESHOLD, MMAP_MAX)
#: glibc's own starting values (malloc.c: DEFAULT_MMAP_THRESHOLD_MIN, DEFAULT_TRIM_THRESHOLD,
#: DEFAULT_MMAP_MAX), unless the environment the process started with set them.
GLIBC_DEFAULTS = (128 * 1024, 128 * 1024, 65536)

#: What this module last set for this process; None: nothing (glibc's own settings).
_applied: tuple[int, int, int] | None = None


def _libc() -> ctypes.CDLL | None:
    """The C library when it is glibc (it has ``mallopt``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    except (OSError, AttributeError):  # musl and others have no mallopt
        return None
    return libc


def _set(libc: ctypes.CDLL, settings: tuple[int, int, int]) -> bool:
    mmap_threshold, trim_threshold, mmap_max = settings
    return all(
        libc.mallopt(param, value) == 1
        for param, value in ((_M_MMAP_THRESHOLD, mmap_threshold),
                             (_M_TRIM_THRESHOLD, trim_threshold), (_M_MMAP_MAX, mmap_max))
    )  # fmt: skip


def starting_settings() -> tuple[int, int, int]:
    """The settings this process's glibc started with: its defaults, or what the environment
    variables ``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_`` and ``MALLOC_MMAP_MAX_`` or
    ``GLIBC_TUNABLES`` (``glibc.malloc.mmap_threshold``, ...) said."""
    names = ("mmap_threshold", "trim_threshold", "mmap_max")
    tunables = dict(
        item.partition("=")[::2] for item in os.environ.get("GLIBC_TUNABLES", "").split(":")
    )
    values = []
    for name, default in zip(names, GLIBC_DEFAULTS, strict=True):
        given = os.environ.get(f"MALLOC_{name.upper()}_", tunables.get(f"glibc.malloc.{name}"))
        try:
            values.append(int(given, 0) if given else default)
        except ValueError:
            values.append(default)
    return values[0], values[1], values[2]


def allocator_settings() -> tuple[int, int, int]:
    """This process's (mmap threshold, trim threshold, mmap max), as far as this module knows:
    what it set last, else what glibc started with (``mallopt`` has no getter)."""
    return starting_settings() if _applied is None else _applied


def keep_freed_memory() -> bool:
    """Keep freed blocks in the process (module docstring) until :func:`freed_memory_kept`
    restores; whether it applied."""
    global _applied
    libc = _libc()
    if libc is None:
        log.debug("host memory: not glibc (%s), left to the system allocator", sys.platform)
        return False
    applied = _set(libc, KEPT)
    if applied:
        _applied = KEPT
    log.debug("host memory: freed blocks kept in the process (mallopt: %s)", applied)
    return applied


@contextmanager
def freed_memory_kept(enabled: bool = True) -> Iterator[bool]:
    """Keep freed memory inside the block (when ``enabled``; yields whether it applied), then set
    back what it changed and hand the memory kept back to the kernel."""
    before = _applied
    applied = keep_freed_memory() if enabled else False
    try:
        yield applied
    finally:
        libc = _libc() if applied and before != KEPT else None
        if libc is not None:
            _restore(libc, before)


def _restore(libc: ctypes.CDLL, before: tuple[int, int, int] | None) -> None:
    global _applied
    _set(libc, starting_settings() if before is None else before)
    _applied = before
    libc.malloc_trim(ctypes.c_size_t(0))
    log.debug("host memory: allocator settings restored, kept memory returned")
