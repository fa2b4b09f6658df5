"""Data-parallel training (``trainer=ddp``): a real 2-process CPU run through the entry point.

The metrics of a DDP test run must be what one process computes on the same weights and data.
The comparison is exact by construction: the DDP run tests its best checkpoint, and the same
checkpoint is evaluated again by ``mfg_lightning.evaluate`` in a single process. Only the
reduction across processes differs, so every value must agree to float32 rounding (per-sample
sums are added in another order). The tiny test split has an odd number of samples (11), so an
even split over 2 processes needs padding: a sample counted twice changes a mean by about 1/11.
The two runs are ``bench/scaleout.py``'s :func:`reduction`, which reports the same comparison.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from conftest import bench_module, run_module

pytestmark = pytest.mark.slow

scaleout = bench_module("scaleout")

# What must be among the compared values: per-frame means, the mean-motion baseline, the
# trajectory metrics (gathered across processes, whole-trajectory ATE included) and the
# object-motion scores.
REQUIRED = (
    "test/trans_err",
    "test/rot_err",
    "test/loss",
    "test/active_fraction",
    "test/baseline_trans_err",
    "test/ate",
    "test/ate_std",
    "test/rpe_trans",
    "test/rpe_rot",
    "test/ate_traj",
    "test/object/iou",
    "test/object/gt_pixels",
)


def _launch(args: list[str], cwd: Path) -> None:
    """``python -m <args>`` as the tests run entry points (it raises if the run fails)."""
    run_module(*args, cwd=cwd, timeout=240)


def test_ddp_metrics_equal_single_process_metrics_of_the_same_checkpoint(tmp_path: Path) -> None:
    # the benchmark's comparison: the DDP run in <tmp>/ddp, the evaluation in <tmp>/single
    ddp, single = scaleout.reduction(tmp_path, _launch)
    best = json.loads((tmp_path / "ddp" / "metrics.json").read_text())["best_checkpoint"]
    assert best and Path(best).is_file()

    shared = sorted(k for k in ddp if k.startswith("test/") and k in single)
    missing = [k for k in REQUIRED if k not in shared]
    assert not missing, f"not reported by both runs: {missing}"
    differ = []
    for key in shared:
        a, b = ddp[key], single[key]
        if a is None or b is None:  # NaN (e.g. drift on a sequence shorter than 100 m)
            if a is not b:
                differ.append((key, a, b))
        elif not math.isclose(a, b, rel_tol=1e-5, abs_tol=1e-7):
            differ.append((key, a, b))
    assert not differ, "DDP (2 processes) ≠ single process:\n" + "\n".join(
        f"  {k}: ddp {a} single {b}" for k, a, b in differ
    )


def test_a_ddp_multirun_runs_each_job_once_in_its_own_directory(tmp_path: Path) -> None:
    """``-m`` with ``trainer=ddp``: Lightning starts each job's second process with the parent's
    command line, which held ``-m`` and the whole sweep (every child ran the sweep again).
    ``run.training.children_run_this_job`` hands the children the job's own overrides and
    directory: the sweep is launched once, and each job's directory has its own results."""
    sweep = tmp_path / "sweep"
    proc = run_module(
        "mfg_lightning.train", "-m", "debug=tiny", "trainer=ddp", "trainer.precision=32-true",
        "logger=none", "seed=0,1", f"hydra.sweep.dir={sweep}", cwd=tmp_path, timeout=600,
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    assert out.count("Launching 2 jobs locally") == 1, out[-3000:]
    # the evaluation's values are gathered already: Lightning's sync_dist advice is silenced
    assert "sync_dist=True" not in out
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert jobs == ["0", "1"]
    seeds = [json.loads((sweep / j / "run_info.json").read_text())["seed"] for j in jobs]
    assert seeds == [0, 1]
    for j in jobs:
        metrics = json.loads((sweep / j / "metrics.json").read_text())
        assert metrics["best_checkpoint"].startswith(str(sweep / j))
