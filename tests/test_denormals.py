"""Subnormal floats flushed in every computing thread (``mfg_lightning.core.denormals``): each
check runs in a fresh process with 2 torch threads, whose pool starts at its first parallel op."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from functools import cache


def _python(code: str) -> str:
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    return done.stdout.strip()


@cache
def _has_flags() -> bool:
    """Whether this CPU has FTZ/DAZ (asked in a process of its own: this one's flags stay as
    they are)."""
    return _python("import torch; print(torch.set_flush_denormal(True))") == "True"


def test_flushed_before_the_pool_starts_every_thread_reads_subnormals_as_zero() -> None:
    out = _python(
        """
        import torch
        torch.set_num_threads(2)
        from mfg_lightning.core.denormals import every_thread_flushes, flush_denormals
        x = torch.ones(8, dtype=torch.int32).view(torch.float32)  # subnormal bits
        print(flush_denormals(), every_thread_flushes(), (x * 2).eq(0).all().item())
        """
    )
    assert out == ("True True True" if _has_flags() else "False False False")


def test_flushed_after_the_pool_started_the_check_fails_and_says_so() -> None:
    """The flags are per thread, and the pool's threads copy them when they start: set once a
    2-thread pool runs (here started by the check itself, which then computes subnormals), they
    reach the calling thread only, and the check sees the other thread still computing them."""
    out = _python(
        """
        import logging, sys, torch
        logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stdout)
        torch.set_num_threads(2)
        from mfg_lightning.core.denormals import every_thread_flushes, flush_denormals
        print(every_thread_flushes())
        print(flush_denormals())
        """
    )
    lines = out.splitlines()
    assert lines[0] == "False" and lines[-1] == "False", out
    assert ("thread pool started before" in out) == _has_flags(), out


def test_a_training_flushes_before_it_computes(tmp_path) -> None:
    """The training entry flushes first thing (``flush_denormals: true``, the default): after
    a tiny real training in a fresh process, the thread of its pool that started inside it reads
    subnormals as zero (half of a 2-thread product is zero), and the calling thread, set back
    when the training returned, computes them again."""
    out = _python(
        f"""
        import torch
        torch.set_num_threads(2)
        from mfg_lightning.core.config import compose
        from mfg_lightning.run.training import train
        from mfg_lightning.core.denormals import calling_thread_flushes
        cfg = compose("train", ["debug=tiny", "trainer.max_steps=2", "test=false",
                                "paths.output_dir={tmp_path}", "logger=none", "callbacks=none"])
        train(cfg)
        x = torch.ones(1 << 22, dtype=torch.int32).view(torch.float32)  # subnormal bits
        print("FLUSHED", (x * 2.0).eq(0).float().mean().item(), calling_thread_flushes())
        """
    )
    assert out.splitlines()[-1] == f"FLUSHED {0.5 if _has_flags() else 0.0} False"
