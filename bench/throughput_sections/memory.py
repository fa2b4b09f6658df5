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


#: A bare training step of the network in a fresh process (the allocator setting lasts for the
#: process): ``<kept|default> <batch> <bf16|fp32> <hidden units> <steps>`` → minor page faults,
#: system and wall milliseconds per step, after a warm-up.
FAULTS_PROBE = """
import resource, sys, time, torch
from mfg_lightning.models.mfg import MFG
how, dtype = sys.argv[1], sys.argv[3]
batch, hidden, steps = int(sys.argv[2]), int(sys.argv[4]), int(sys.argv[5])
if how == "kept":
    from mfg_lightning.core.host_memory import keep_freed_memory
    keep_freed_memory()
torch.manual_seed(0)
net = MFG(hidden_units=hidden)
opt = torch.optim.Adam(net.parameters(), lr=1e-4, fused=True)
flow = torch.randn(batch, 2, 48, 128)
def step():
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype == "bf16"):
        out = net(flow)
    loss = out.v_t.abs().mean() + out.v_omega.abs().mean() + out.hidden.float().mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
for _ in range(6):
    step()
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
for _ in range(steps):
    step()
r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
print((r1.ru_minflt - r0.ru_minflt) / steps, 1e3 * (r1.ru_stime - r0.ru_stime) / steps,
      1e3 * (t1 - t0) / steps)
"""


def page_fault_rows(tiny: bool, threads: int, repeats: int) -> list[list[str]]:
    """Per batch 16 step of the bare loop, float32 and bf16-mixed, with the system allocator's
    default and with freed memory kept (``keep_freed_memory``, what training does): minor page
    faults, system time and wall time (medians of ``repeats`` interleaved processes)."""
    import statistics

    hidden, steps = (64, 3) if tiny else (1000, 20)
    batch = 4 if tiny else 16
    rows = []
    for dtype in ("fp32", "bf16"):
        got: dict[str, list[list[float]]] = {"default": [], "kept": []}
        for _ in range(repeats):
            for how in got:
                proc = subprocess.run(
                    [sys.executable, "-c", FAULTS_PROBE, how, str(batch), dtype, str(hidden),
                     str(steps)],
                    env={**os.environ, "OMP_NUM_THREADS": str(threads)},
                    capture_output=True, text=True, check=True,
                )  # fmt: skip
                got[how].append([float(v) for v in proc.stdout.split()[-3:]])
        for how, values in got.items():
            faults, system, wall = (statistics.median(v[i] for v in values) for i in range(3))
            rows.append([f"{'bf16-mixed' if dtype == 'bf16' else 'float32'}", how,
                         fmt(faults, 0), fmt(system, 2), fmt(wall, 1)])  # fmt: skip
    return rows


def host_memory_section(run: Run) -> None:
    """:func:`page_fault_rows` as a table of the memory section."""
    rows = page_fault_rows(run.args.tiny, torch.get_num_threads(), run.args.candidate_repeats)
    run.report.add(
        "## Host memory kept: page faults per training step\n\n"
        + markdown_table(
            ["precision", "freed memory", "minor page faults / step", "system ms / step",
             "wall ms / step"],
            rows,
        )
        + "\nThe bare step of the network (forward, a loss, backward, fused Adam) at batch "
        f"{4 if run.args.tiny else 16}, each row a fresh process, medians of "
        f"{run.args.candidate_repeats} interleaved pairs. *default*: the C library returns the "
        "memory of freed tensors (activations, and the gradients `zero_grad` sets to None) and "
        "the next step takes a page fault for every page it touches again; *kept*: "
        "`keep_freed_memory` (`mfg_lightning.core.host_memory`, on in every training run) "
        "keeps it in the process. The faults are a count, whatever the machine's load."
    )  # fmt: skip
