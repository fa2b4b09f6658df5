"""Flush subnormal floats to zero in every thread that computes a training step.

Why: a sparse network leaves most of its units silent. Their decoder columns and the channels
that feed them get exactly zero gradients, so Adam's first moments decay by β₁ = 0.9 a step
and reach the subnormal range (below 1.2e-38 in float32) after some 800 steps. x86 cores compute
on subnormal operands about ten times slower than on normal ones. At the end of the quick start
(1,200 steps) 37 % of Adam's state values were subnormal, and its fused step took 49 ms of the
100 ms training step against 9 ms on fresh states (py-spy over the whole run; the step alone on
the checkpoint's states: 100 ms with subnormals computed, 9.5 ms flushed).

How: :func:`torch.set_flush_denormal` sets the calling thread's FTZ and DAZ flags (a result below
the normal range is written as zero, and such an operand is read as zero). The flags are per
thread, and the threads of torch's intra-op pool (OpenMP) copy them from the thread that
creates them, when the pool starts: set after the pool exists, they reach the calling thread
alone (the same Adam step then still took 100 ms on 2 threads). So :func:`flush_denormals` is
called before a training process computes anything, and it checks with one parallel product
over subnormal values that every thread of the pool flushes.

:func:`denormals_flushed` flushes for one block of code (``train()``) and then sets the calling
thread's flags back, so that a notebook or a test that trains in-process computes as before.
Where torch's thread pool started before the block (any parallel torch work first), that is
the whole process as it was. A pool started inside the block keeps its threads' flags: nothing
in torch reaches them once they run, so such threads go on flushing (slower subnormals are the
only thing a flush saves; no result a model computes differs above 1.2e-38).

What it changes: values below 1.2e-38 become zero. Nothing a model computes is meaningful at that
size; the trained numbers differ from an unflushed run's in the last bits, as with any change of
kernels (the run records the setting in its ``config.yaml``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

import torch

log = logging.getLogger(__name__)

#: Elements of the check's product (16 MB): enough to be split over every thread of the pool.
_CHECK_ELEMENTS = 1 << 22


def every_thread_flushes() -> bool:
    """Whether an element-wise product spread over torch's intra-op threads reads subnormal
    operands as zero in every one of them (with DAZ the product of a subnormal is 0).

    The operand is the smallest subnormal written as its bit pattern (the integer 1): a float
    fill would convert the value in the calling thread, which flushes it to zero itself, and
    the check would pass whatever the other threads do."""
    x = torch.ones(_CHECK_ELEMENTS, dtype=torch.int32).view(torch.float32)
    return bool((x * 2.0).eq(0).all())


def calling_thread_flushes() -> bool:
    """Whether the calling thread reads a subnormal operand as zero (its DAZ flag: a
    one-element product runs in the calling thread)."""
    x = torch.ones(1, dtype=torch.int32).view(torch.float32)  # the smallest subnormal
    return bool((x * 2.0).eq(0).all())


#: Whether the warning about a pool that started first was given (once a process).
_warned = False


def flush_denormals() -> bool:
    """Set FTZ/DAZ for this process's computing threads; whether every intra-op thread now
    flushes. False, with a warning (once a process), where the CPU has no such flags or the pool
    started before the call (a thread then keeps computing subnormals: slower, not wrong)."""
    global _warned
    if not torch.set_flush_denormal(True):
        log.debug("denormals: this CPU cannot flush them; computed as they are")
        return False
    if every_thread_flushes():
        log.debug("denormals: flushed to zero in every intra-op thread")
        return True
    if _warned:
        return False
    _warned = True
    log.warning(
        "denormals: torch's thread pool started before they were flushed, so some of its "
        "threads compute subnormal values at full cost (slower training; call "
        "mfg_lightning.core.denormals.flush_denormals() before any torch work to flush them)"
    )
    return False


@contextmanager
def denormals_flushed(enabled: bool = True) -> Iterator[bool]:
    """Flush subnormals inside the block (when ``enabled``; yields whether every thread
    flushes), then set the calling thread's flags back as they were (module docstring)."""
    if not enabled:
        yield False
        return
    before = calling_thread_flushes()
    try:
        yield flush_denormals()
    finally:
        torch.set_flush_denormal(before)
