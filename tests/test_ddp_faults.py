"""A fault in one process of a data-parallel run: every process takes the decision together.

Real 2-process trainings through the entry point (``trainer=ddp``: gloo on the CPU; Lightning
starts the second process with the same command), with a fault injected into one process only
(tests/ddp_faults.py). A process that skipped a step, stopped or raised on its own used to leave
the other waiting in a collective until the process group's 30-minute timeout, or crashed both
(Lightning's SIGTERM handler makes a collective call):

* SIGTERM in one process: both stop after the same step, ``last.ckpt`` is saved, both exit with
  143; resumed with ``ckpt_path=last``, the run ends with the test metrics of an uninterrupted
  2-process run (each process resumes its share of the epoch's order mid-epoch).
* A non-finite loss, and a batch without samples, in one process: both skip those steps
  (``AgreedSteps``); too many in a row end both with ``NonFiniteLossError`` at the same step.
* A batch refused in one process (``AgreedSteps``' batch checks): both end at the same step, one
  with the batch's error, the other naming it (exit status 2). On the way, a batch without
  samples in the other process is skipped by both.
* An error in the first process that nothing agrees on: the other process ends as well.

Bound: every process of a faulty run has ended within :data:`END_BOUND` seconds of the (last)
fault. Idle, that is the few seconds of the processes' exit; the bound is generous because the
machine may be shared, and far below the 30-minute timeout at which a waiting process would
otherwise have been ended.
"""

from __future__ import annotations

import json
import math
import os
import signal
from pathlib import Path

import pytest
import torch

from conftest import entry_point_env
from ddp_faults import FaultyRun, run_with_faults

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent
#: seconds from the (last) fault to the end of every process of the run
END_BOUND = 120.0
#: seconds a whole run may take, start-up included (a hang fails the test, never blocks it)
RUN_TIMEOUT = 600
# debug=tiny under trainer=ddp: 4 samples per process and step, 3 steps per epoch and process,
# a validation after every 2nd step. The fault acts at the start of step 3 (global_step 3), the
# first step of epoch 1: stopped there, the run has trained one batch of epoch 1 (mid-epoch) and
# the validation after it has run.
RUN = [
    "debug=tiny",
    "trainer=ddp",
    "trainer.max_steps=8",
    "logger=none",
    "callbacks.rich_progress_bar=null",
    "+trainer.enable_progress_bar=false",
]
FAULT_STEP = 3


def _train(workdir: Path, run: str, *overrides: str, faults: dict[str, tuple] | None = None):
    """``python -m mfg_lightning.train`` of :data:`RUN` into ``<workdir>/<run>`` with the faults
    ``{name: (kind, steps, rank)}`` (tests/ddp_faults.py), until every process has ended."""
    env = entry_point_env(
        workdir, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
    )
    return run_with_faults("mfg_lightning.train", [*RUN, *overrides], workdir, run, env,
                           faults, RUN_TIMEOUT)  # fmt: skip


def _ended_in_time(run: FaultyRun) -> None:
    assert run.seconds_after_fault is not None, "the fault never acted:\n" + run.output[-5000:]
    print(f"ended {run.seconds_after_fault:.1f} s after the fault")  # shown by pytest -s
    assert run.seconds_after_fault <= END_BOUND, (
        f"ended {run.seconds_after_fault:.0f} s after the fault (bound {END_BOUND:.0f} s)"
    )


def _test_metrics(run_dir: Path) -> dict[str, float | None]:
    metrics = json.loads((run_dir / "metrics.json").read_text())["metrics"]
    return {k: v for k, v in metrics.items() if k.startswith("test/")}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("ddp_faults")


def test_sigterm_in_one_process_stops_both_after_one_step_and_the_run_resumes_exactly(
    workdir: Path,
) -> None:
    reference = _train(workdir, "reference")
    assert reference.returncode == 0, reference.output[-5000:]
    # The default settings (precision and kernels auto): the first process decides, the other
    # is handed its choice, and one line says which kernels both ran.
    assert reference.output.count("kernels of all 2 processes") == 1, reference.output[-5000:]
    assert "takes the first process's kernels" not in reference.output

    stopped = _train(workdir, "stopped", faults={"sigterm": ("sigterm", [FAULT_STEP], 1)})
    assert stopped.returncode == 128 + signal.SIGTERM, stopped.output[-5000:]
    _ended_in_time(stopped)
    # Both stopped after the same step (the one SIGTERM arrived in), and both exited with 143.
    assert stopped.output.count(f"stopped by SIGTERM at step {FAULT_STEP + 1}") == 2
    assert "local rank 1 ended with status 143" in stopped.output
    saved = torch.load(
        workdir / "stopped" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False
    )
    assert saved["global_step"] == FAULT_STEP + 1
    (order,) = saved["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    per_epoch = math.ceil(math.ceil(order["samples"] / 2) / 4)  # batches per process and epoch
    assert order["processes"] == 2 and order["epoch"] == 1
    assert 0 < order["batches"] < per_epoch, order  # mid-epoch

    resumed = _train(workdir, "stopped", "ckpt_path=last")
    assert resumed.returncode == 0, resumed.output[-5000:]
    got, want = _test_metrics(workdir / "stopped"), _test_metrics(workdir / "reference")
    assert got.keys() == want.keys() and "test/trans_err" in want
    differ = {
        k: (got[k], want[k])
        for k in want
        if (got[k] is None) != (want[k] is None)
        or (want[k] is not None and not math.isclose(got[k], want[k], rel_tol=1e-6, abs_tol=1e-9))
    }
    assert not differ, f"resumed ≠ uninterrupted: {differ}"


def test_a_non_finite_loss_or_no_sample_in_one_process_is_skipped_by_both(workdir: Path) -> None:
    # Steps 2 (NaN) and 3 (no sample) are skipped by both; step 4 trains; 5, 6 and 7 (NaN) are
    # three in a row, which ends both at step 7.
    run = _train(
        workdir,
        "non_finite",
        "model.optimizer.fused=false",
        "model.max_consecutive_nonfinite=3",
        faults={"nan": ("non_finite", [2, 5, 6, 7], 1), "empty": ("no_samples", [3], 1)},
    )
    assert run.returncode == 1, run.output[-5000:]
    _ended_in_time(run)
    # process 1 names its cause, process 0 skips the same steps on its word
    assert run.output.count("non-finite loss (nan) on ") == 4
    assert run.output.count("no usable sample on this process: step skipped") == 1
    assert run.output.count("no usable sample in another process on ") == 5
    assert run.output.count("NonFiniteLossError: 3 consecutive non-finite losses") == 2


def test_a_batch_refused_in_one_process_ends_both_at_the_same_step(workdir: Path) -> None:
    run = _train(
        workdir,
        "refused",
        faults={"bad": ("bad_batch", [FAULT_STEP], 1), "empty": ("no_samples", [2], 0)},
    )
    assert run.returncode == 2, run.output[-5000:]
    _ended_in_time(run)
    errors = [line for line in run.output.splitlines() if line.startswith("error: ")]
    # both end at the step of the refused batch, process 1 with the batch's error
    assert len(errors) == 2, run.output[-5000:]
    assert any("'pose' has non-finite values" in line for line in errors), errors
    assert any(f"process 1 of the run failed at step {FAULT_STEP}" in line for line in errors), (
        errors
    )
    assert "Traceback" not in run.output
    # step 2, without a sample in process 0, was skipped by both
    assert run.output.count("no usable sample on this process: step skipped") == 1
    assert run.output.count("no usable sample in another process on ") == 1


def test_an_error_in_the_first_process_alone_ends_the_other_too(workdir: Path) -> None:
    run = _train(workdir, "error", faults={"error": ("error", [FAULT_STEP], 0)})
    assert run.returncode == 1, run.output[-5000:]
    _ended_in_time(run)
    assert "RuntimeError: injected error in process 0" in run.output


def test_ddp_broadcasts_buffers_only_for_a_module_whose_forward_changes_them() -> None:
    import lightning as L
    from lightning.pytorch.strategies import DDPStrategy

    from mfg_lightning.run.together import BuffersWhereNeeded, buffers_change_in_forward
    from module_helpers import small_module

    class WithBatchNorm(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.norm = torch.nn.BatchNorm1d(4)

    def chosen(module: L.LightningModule, **given: bool) -> bool | None:
        strategy = DDPStrategy(process_group_backend="gloo", **given)
        trainer = L.Trainer(accelerator="cpu", devices=2, strategy=strategy, logger=False)
        BuffersWhereNeeded().setup(trainer, module, "fit")
        kwargs = strategy._ddp_kwargs
        return kwargs.get("forward_sync_buffers", kwargs.get("broadcast_buffers"))

    mfg = small_module()
    assert [name for name, _ in mfg.named_buffers()]  # it has buffers (the mean motion)
    assert not buffers_change_in_forward(mfg) and buffers_change_in_forward(WithBatchNorm())
    assert chosen(mfg) is False
    assert chosen(WithBatchNorm()) is True
    assert chosen(mfg, broadcast_buffers=True) is True  # a given setting is kept
    one = L.Trainer(accelerator="cpu", devices=1, logger=False)
    BuffersWhereNeeded().setup(one, mfg, "fit")  # one process: nothing to set, no error
