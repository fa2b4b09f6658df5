"""``python -m mfg_lightning.train_flow`` stopped by SIGTERM resumes to the uninterrupted run.

Real trainings through the entry point (tiny: the settings of tests/test_learned_flow.py, with a
random crop so that the augmentation draws), each stopped by SIGTERM at the start of a step
(tests/ddp_faults.py) and resumed with ``ckpt_path=last``; the resumed run must end with the
uninterrupted run's weights, optimiser and scheduler state and validation metrics, bit for bit.
The augmentation's draws come from a generator derived from the seed, the rank and the step
(``FlowLitModule.augmentation_generator``): with torch's global generator, which is not in the
checkpoint and was seeded afresh by the resumed run, the crops and flips after the stop differed.

Under ``trainer=ddp`` (2 gloo processes) SIGTERM reaches one process or both (a scheduler signals
every task): both stop after the same step (the run's agreement,
``mfg_lightning.run.agreed_steps.AgreedSteps``), save ``last.ckpt`` together and exit with 143,
within :data:`END_BOUND` seconds of the signal. Before, SIGTERM to one process left both running
for minutes without a checkpoint (Lightning's handler made a collective call in the handler).
"""

from __future__ import annotations

import json
import math
import os
import signal
from pathlib import Path
from typing import Any

import pytest
import torch

from conftest import entry_point_env
from ddp_faults import FaultyRun, run_with_faults

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent
#: seconds from the SIGTERM to the end of every process of the run (issue's bound)
END_BOUND = 30.0
# 22 training pairs of 2: 11 steps an epoch in one process, 6 in each of two; a validation
# every 4 steps of an epoch. The signal arrives at the start of step 7: the run stops after step 8
# (global_step 8), mid-epoch (1 process: after the validation of step 8; 2: in epoch 1).
RUN = [
    "dataset.train_sequences=1", "dataset.sequence_length=16", "dataset.val_fraction=0.25",
    "dataset.frame_stride=2", "dataset.val_every=2", "dataset.image_hw=[64,128]",
    "dataset.batch_size=2", "dataset.num_workers=0", "dataset.prepare_workers=0",
    "model.net.pyramid=[8,8,12,16]", "model.net.decoder=[16,16]", "model.net.context=[8,8]",
    "model.net.dilations=[1,2]", "model.level_weights=[1,1,1]", "model.crop=[32,64]",
    "model.image_log_every_n_steps=0", "trainer.max_steps=12", "trainer.val_check_interval=4",
    "trainer.log_every_n_steps=1", "logger=none", "callbacks.rich_progress_bar=null",
    "callbacks.figures=null", "+trainer.enable_progress_bar=false",
]  # fmt: skip
FAULT_STEP = 7


def _train_flow(workdir: Path, run: str, *overrides: str, faults: dict | None = None) -> FaultyRun:
    env = entry_point_env(
        workdir, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
    )
    args = [*RUN, *overrides]
    return run_with_faults("mfg_lightning.train_flow", args, workdir, run, env, faults)


def _last(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "checkpoints" / "last.ckpt"
    return torch.load(path, map_location="cpu", weights_only=False)


def _differences(got: Any, want: Any, where: str = "") -> list[str]:
    """Where two checkpoint parts differ (tensors bit for bit, numbers and structure exactly)."""
    if isinstance(want, torch.Tensor):
        same = isinstance(got, torch.Tensor) and got.shape == want.shape and torch.equal(got, want)
        return [] if same else [where]
    if isinstance(want, dict):
        if not isinstance(got, dict) or got.keys() != want.keys():
            return [f"{where} (keys)"]
        return [d for k in want for d in _differences(got[k], want[k], f"{where}/{k}")]
    if isinstance(want, (list, tuple)):
        if not isinstance(got, (list, tuple)) or len(got) != len(want):
            return [f"{where} (length)"]
        pairs = enumerate(zip(got, want, strict=True))
        return [d for i, (g, w) in pairs for d in _differences(g, w, f"{where}/{i}")]
    return [] if got == want else [f"{where}: {got!r} != {want!r}"]


def _assert_resumed_equals_uninterrupted(resumed: Path, reference: Path) -> None:
    got, want = _last(resumed), _last(reference)
    assert got["global_step"] == want["global_step"] == 12
    differ = [
        *_differences(got["state_dict"], want["state_dict"], "state_dict"),
        *_differences(got["optimizer_states"], want["optimizer_states"], "optimizer_states"),
        *_differences(got["lr_schedulers"], want["lr_schedulers"], "lr_schedulers"),
    ]
    assert not differ, f"resumed ≠ uninterrupted: {differ[:10]}"
    got_m = json.loads((resumed / "metrics.json").read_text())["metrics"]
    want_m = json.loads((reference / "metrics.json").read_text())["metrics"]
    assert got_m.keys() == want_m.keys() and "val/epe" in want_m
    assert all(math.isclose(got_m[k], want_m[k], rel_tol=1e-9) for k in want_m), (got_m, want_m)


def _assert_stopped(run: FaultyRun, run_dir: Path, processes: int) -> None:
    assert run.returncode == 128 + signal.SIGTERM, run.output[-5000:]
    assert run.seconds_after_fault is not None, "the fault never acted:\n" + run.output[-5000:]
    print(f"ended {run.seconds_after_fault:.1f} s after SIGTERM")  # shown by pytest -s
    assert run.seconds_after_fault <= END_BOUND, run.output[-5000:]
    assert run.output.count(f"stopped by SIGTERM at step {FAULT_STEP + 1}") == processes
    saved = _last(run_dir)
    assert saved["global_step"] == FAULT_STEP + 1
    (order,) = saved["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert order["processes"] == processes and order["batches"] > 0, order  # mid-epoch


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("flow_faults")


def test_train_flow_stopped_by_sigterm_resumes_to_the_uninterrupted_run(workdir: Path) -> None:
    reference = _train_flow(workdir, "reference")
    assert reference.returncode == 0, reference.output[-5000:]
    stopped = _train_flow(workdir, "stopped", faults={"sigterm": ("sigterm", [FAULT_STEP], 0)})
    _assert_stopped(stopped, workdir / "stopped", processes=1)
    resumed = _train_flow(workdir, "stopped", "ckpt_path=last")
    assert resumed.returncode == 0, resumed.output[-5000:]
    _assert_resumed_equals_uninterrupted(workdir / "stopped", workdir / "reference")


@pytest.mark.parametrize("ranks", [(1,), (0, 1)], ids=["one_process", "both_processes"])
def test_train_flow_under_ddp_stops_together_on_sigterm_and_resumes_exactly(
    workdir: Path, ranks: tuple[int, ...]
) -> None:
    if not (workdir / "ddp_reference" / "metrics.json").is_file():
        reference = _train_flow(workdir, "ddp_reference", "trainer=ddp")
        assert reference.returncode == 0, reference.output[-5000:]
    run = f"ddp_stopped_{len(ranks)}"
    faults = {f"sigterm{rank}": ("sigterm", [FAULT_STEP], rank) for rank in ranks}
    stopped = _train_flow(workdir, run, "trainer=ddp", faults=faults)
    _assert_stopped(stopped, workdir / run, processes=2)
    assert "local rank 1 ended with status 143" in stopped.output
    resumed = _train_flow(workdir, run, "trainer=ddp", "ckpt_path=last")
    assert resumed.returncode == 0, resumed.output[-5000:]
    _assert_resumed_equals_uninterrupted(workdir / run, workdir / "ddp_reference")
