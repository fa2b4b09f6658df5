"""4. The peak resident memory and wall time of a real training run (``python -m
mfg_lightning.train``, a few steps of the quick-start config)."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import torch
from _common import fmt, markdown_table

from .measure import Run

#: Runs the command given as its arguments and prints the child's peak RSS in kilobytes. The
#: measurement runs in this small process because Linux counts, in a child's peak RSS, the
#: memory of the process that forked it up to the exec: forked from the benchmark itself (a
#: couple of GB by then) the number would be the benchmark's, not the training run's.
RSS_PROBE = """
import os, subprocess, sys
proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
_, status, usage = os.wait4(proc.pid, 0)
sys.stderr.write(proc.stderr.read().decode()[-2000:] if status else "")
print(usage.ru_maxrss)
sys.exit(1 if status else 0)
"""


def peak_rss_mb(steps: int, tiny: bool, threads: int) -> tuple[float, float]:
    """Peak resident memory (MB) and wall time (s) of ``python -m mfg_lightning.train`` for a
    few steps of the quick-start config (no logger, no validation, no test)."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "mfg_lightning.train",
            f"trainer.max_steps={steps}",
            "trainer.limit_val_batches=0",
            "logger=none",
            "callbacks=none",
            "test=false",
            f"hydra.run.dir={tmp}",
            f"paths.cache_dir={tmp}/cache",
            *(["debug=tiny"] if tiny else []),
        ]
        start = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-c", RSS_PROBE, *cmd],
            cwd=tmp,
            env={**os.environ, "OMP_NUM_THREADS": str(threads)},
            capture_output=True,
            text=True,
            check=False,
        )
        seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr}")
    # ru_maxrss is in kilobytes on Linux (bytes on macOS).
    scale = 1 / 1024 if sys.platform != "darwin" else 1 / 2**20
    return int(proc.stdout.split()[-1]) * scale, seconds


def section(run: Run) -> None:
    """Measure :func:`peak_rss_mb` for ``--rss-steps`` and add the table."""
    args = run.args
    rss, seconds = peak_rss_mb(args.rss_steps, args.tiny, torch.get_num_threads())
    command = (
        f"`python -m mfg_lightning.train trainer.max_steps={args.rss_steps} "
        "trainer.limit_val_batches=0 logger=none callbacks=none test=false"
        + (" debug=tiny" if args.tiny else "")
        + f"` (batch {4 if args.tiny else 16}, the default loader: each sample "
        "generated once, then read from the sample cache)"
    )
    run.report.add(
        "## Peak resident memory of a training run\n\n"
        + markdown_table(
            ["run", "peak RSS (MB)", "wall time (s)"], [[command, fmt(rss, 0), fmt(seconds, 1)]]
        )
    )
