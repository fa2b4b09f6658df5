"""Question 3: does training scale out over processes, and do the metrics survive it?

1. Training throughput of ``python -m mfg_lightning.train`` with one process and with
   ``trainer=ddp`` (2 processes, gloo), as samples per second. Each setting runs twice, for
   ``--short`` and ``--long`` steps, and the rate is the difference: process start-up, data
   set-up and the DDP rendezvous cancel out.
2. The metric reduction: a ``trainer=ddp`` run tests its best checkpoint, and
   ``mfg_lightning.evaluate`` tests the same checkpoint in one process; the values must agree
   (``tests/test_ddp.py`` runs this same comparison and asserts it).

``python bench/scaleout.py`` (a few minutes on 2 CPU cores); ``--tiny`` for a smoke run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Report, add_common_arguments, fmt, markdown_table

#: Reported in the reduction table (all test metrics are compared).
SHOWN = ("test/trans_err", "test/rot_err", "test/loss", "test/baseline_trans_err", "test/ate",
         "test/ate_std", "test/rpe_trans", "test/rpe_rot", "test/object/iou")  # fmt: skip


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    p.add_argument("--batch-size", type=int, default=16, help="per process")
    p.add_argument("--short", type=int, default=10, help="steps of the short run")
    p.add_argument("--long", type=int, default=50, help="steps of the long run")
    threads = "torch threads of the single process (default: all cores; DDP processes share them)"
    add_common_arguments(p, threads)
    return p.parse_args(argv)


def run(args: list[str], cwd: Path, env: dict[str, str] | None = None) -> float:
    """Run ``python -m mfg_lightning.<args>`` and return its wall time (s)."""
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", *args],
        cwd=cwd,
        env={**os.environ, "HYDRA_FULL_ERROR": "1", **(env or {})},
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed:\n{proc.stderr[-4000:]}")
    return time.perf_counter() - start


def training_rate(processes: int, steps: tuple[int, int], batch: int, tiny: bool, tmp: Path):
    """Samples per second (all processes together) from two runs of different length."""
    trainer = ["trainer=ddp", f"trainer.devices={processes}"] if processes > 1 else []
    times = []
    for n in steps:
        times.append(
            run(
                [
                    "mfg_lightning.train",
                    *(["debug=tiny"] if tiny else []),
                    *trainer,
                    f"trainer.max_steps={n}",
                    "trainer.limit_val_batches=0",
                    f"dataset.batch_size={batch}",
                    "logger=none",
                    "callbacks=none",
                    "test=false",
                    f"hydra.run.dir={tmp / f'rate-{processes}-{n}'}",
                ],
                tmp,
            )
        )
    if times[1] <= times[0]:  # a load spike during the short run: no rate to report
        return float("nan"), times
    return (steps[1] - steps[0]) * batch * processes / (times[1] - times[0]), times


def parameter_count(tiny: bool) -> int:
    """Parameters of the benchmarked model: the size of the gradient all-reduce."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    cfg = compose("train", ["debug=tiny"] if tiny else [])
    return sum(p.numel() for p in instantiate(cfg.model.net).parameters())


def reduction(tmp: Path, launch: Callable[[list[str], Path], object] = run) -> tuple[dict, dict]:
    """Test metrics of one checkpoint: under DDP (2 processes) and in one process.

    The DDP run writes ``<tmp>/ddp``, the single-process evaluation of its best checkpoint
    ``<tmp>/single``. ``launch(args, cwd)`` runs ``python -m <args>`` and raises if it fails:
    :func:`run` here, the tests' own runner in ``tests/test_ddp.py``, which asserts the two agree.
    """
    ddp_dir, single_dir = tmp / "ddp", tmp / "single"
    launch(
        [
            "mfg_lightning.train",
            "debug=tiny",
            "trainer=ddp",
            # the run tests in the precision it trained in, evaluate in float32: the same
            # precision on both sides, so that only the reduction is compared
            "trainer.precision=32-true",
            "logger=none",
            f"hydra.run.dir={ddp_dir}",
        ],
        tmp,
    )
    ddp = json.loads((ddp_dir / "metrics.json").read_text())
    launch(
        [
            "mfg_lightning.evaluate",
            f"ckpt_path={ddp['best_checkpoint']}",
            "eval.write_poses=false",
            f"hydra.run.dir={single_dir}",
        ],
        tmp,
    )
    single = json.loads((single_dir / "metrics.json").read_text())["metrics"]
    return ddp["metrics"], single


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    if args.tiny:
        # Every run starts Python, Lightning and Hydra (seconds): the smoke run does the
        # fewest that still exercise both parts.
        args.processes, args.short, args.long, args.batch_size = [2], 1, 2, 4
    cores = os.cpu_count() or 1
    if args.threads:
        # Child processes read it: one process uses them all, DDP splits them.
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
    report = Report("scaleout", "Scale-out: data-parallel training (DDP)", args.out)
    params = parameter_count(args.tiny)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        rows, rates = [], {}
        for n in args.processes:
            rate, times = training_rate(n, (args.short, args.long), args.batch_size, args.tiny, tmp)
            rates[n] = rate
            threads = args.threads or max(1, cores // n)
            rows.append(
                [
                    n,
                    threads,
                    args.batch_size * n,
                    fmt(rate, 1),
                    fmt(rate / rates[args.processes[0]], 2),
                    f"{times[0]:.1f} / {times[1]:.1f}",
                ]
            )
        report.add(
            f"## Training throughput (quick-start model{' (tiny)' if args.tiny else ''}, "
            f"batch {args.batch_size} per process, steps {args.short} → {args.long})\n\n"
            + markdown_table(
                [
                    "processes",
                    "threads / process",
                    "effective batch",
                    "samples/s",
                    "× 1 process",
                    "wall time short / long (s)",
                ],
                rows,
            )
            + "\nSamples per second = (long − short) steps × batch × processes / (difference of "
            "the wall times). Every process renders its own batches (the synthetic data, in "
            "the process: `num_workers=0`) and runs its step on cores / processes threads "
            "(Lightning's default); each step adds an all-reduce of the "
            f"{params / 1e6:.2f} M gradients (gloo). On a CPU-only machine these trade against "
            "each other; DDP is meant for several GPUs or nodes."
        )
        ddp, single = reduction(tmp)
    shared = sorted(k for k in ddp if k.startswith("test/") and k in single)
    worst = 0.0
    for key in shared:
        a, b = ddp[key], single[key]
        if a is None or b is None:
            worst = worst if a is b else math.inf
        else:
            worst = max(worst, abs(a - b) / max(abs(b), 1e-12))
    shown = []
    for key in SHOWN:
        a, b = ddp.get(key), single.get(key)
        diff = None if a is None or b is None else abs(a - b)
        shown.append([f"`{key}`", fmt(a, 6), fmt(b, 6), fmt(diff, 9)])
    report.add(
        "## Metric reduction: the same checkpoint tested by 2 DDP processes and by 1 process\n\n"
        + markdown_table(["metric", "DDP (2 processes)", "1 process", "|difference|"], shown)
        + f"\nAll {len(shared)} test metrics compared; the largest relative difference is "
        f"{worst:.1e} (float32 sums added in another order; `tests/test_ddp.py` requires "
        "≤ 1e-5). Tiny setting (`debug=tiny`): 11 test samples, an odd number, so the split "
        "cannot be divided evenly over the two processes."
    )
    return report.write()


if __name__ == "__main__":
    main()
