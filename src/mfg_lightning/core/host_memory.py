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
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys
from functools import cache

log = logging.getLogger(__name__)

#: ``mallopt`` parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Blocks below this come from the heap, not from mmap: glibc's largest accepted value on 64-bit
#: (HEAP_MAX_SIZE / 2 = 32 MiB); the quick start's largest tensor, the decoders' weights and their
#: gradients, is 24.6 MB.
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Freed memory at the heap's top is returned to the kernel only above this: never, in practice.
TRIM_THRESHOLD = 2**31 - 1


@cache
def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process (once); whether it applied."""
    if not sys.platform.startswith("linux"):
        log.debug("host memory: not glibc (%s), left to the system allocator", sys.platform)
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others have no mallopt
        log.debug("host memory: no mallopt in this C library, left as it is")
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    applied = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
    log.debug("host memory: freed blocks kept in the process (mallopt: %s)", applied)
    return applied
