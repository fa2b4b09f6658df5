"""What glibc's allocator does with a large block, read from its own counters: the observable
side of ``mallopt``, which has no getter (tests/test_host_memory.py, tests/test_isolation.py).
Read in a fresh process: one that trained before may serve a large block from a free chunk its
heap kept, whatever the settings."""

from __future__ import annotations

import ctypes
import ctypes.util


class _Mallinfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (2.33 and later): the allocator's counters."""

    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]  # fmt: skip


def has_mallinfo2() -> bool:
    """Whether this C library counts its blocks (glibc 2.33 and later)."""
    return hasattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), "mallinfo2")


def big_block_from_mmap() -> bool:
    """Whether glibc serves a 40 MiB block with ``mmap`` (its own settings: always, being above
    the largest threshold) or from the heap (freed memory kept: ``M_MMAP_MAX`` 0), read from
    ``mallinfo2``'s count of mmapped blocks."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    libc.mallinfo2.restype = _Mallinfo2
    libc.malloc.argtypes, libc.malloc.restype = [ctypes.c_size_t], ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    before = libc.mallinfo2().hblks
    block = libc.malloc(40 << 20)
    mapped = libc.mallinfo2().hblks > before
    libc.free(block)
    return mapped
