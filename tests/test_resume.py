"""Interrupted runs resume exactly.

Real trainings through the Hydra entry point: one is killed with SIGKILL in the middle of an
optimiser step, mid-epoch, and resumed with ``ckpt_path=last``; others get SIGTERM, Ctrl-C or
SLURM's SIGUSR1 and must save before they exit; all must end with the weights and metrics of an
uninterrupted run. The data order is tested in test_resume_order.py; kills during a checkpoint
write and full disks in test_atomic_writes.py.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
import torch

from resume_runs import PAUSE_AT, RUN, _assert_same_run, _ckpt, _interrupt, _start_paused, _train

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("resume")


@pytest.fixture(scope="module")
def reference(workdir: Path) -> Path:
    """The uninterrupted run."""
    run = workdir / "reference"
    _train(*RUN, f"hydra.run.dir={run}", cwd=workdir)
    return run


def test_sigkill_mid_epoch_then_resume_gives_the_uninterrupted_run(
    workdir: Path, reference: Path
) -> None:
    run = workdir / "killed"
    returncode, _ = _interrupt(run, workdir, signal.SIGKILL, timeout=60)
    assert returncode == -signal.SIGKILL
    assert not (run / "metrics.json").exists()
    # The last periodic checkpoint is from step 8 (mid-epoch 1): steps 9-11 are lost.
    saved = _ckpt(run / "checkpoints" / "last.ckpt")
    assert saved["global_step"] == 8
    assert saved["loops"]["fit_loop"]["state_dict"]["combined_loader"] == [
        {"epoch": 1, "batches": 3, "samples": 18, "processes": 1, "length": 5, "batch_size": 4,
         "dataset": "SyntheticDrivingDataset", "sampler": "EpochShuffleSampler(seed=3)"}
    ]  # fmt: skip

    _train(*RUN, "ckpt_path=last", f"hydra.run.dir={run}", cwd=workdir)
    _assert_same_run(run, reference)
    info = json.loads((run / "run_info.json").read_text())
    assert info["resumed_from"] == str(run / "checkpoints" / "last.ckpt")


def _stopped_by(sig: signal.Signals, run: Path, workdir: Path) -> str:
    """The output of a training in ``run`` stopped by ``sig`` in the middle of a step, which
    exits with status 128 + ``sig``."""
    returncode, output = _interrupt(run, workdir, sig, timeout=120)
    assert returncode == 128 + sig, output[-3000:]
    return output


def _saved_the_step_and_resumes_exactly(run: Path, workdir: Path, reference: Path) -> None:
    """``run``, stopped by a signal, saved ``last.ckpt`` after the interrupted step and left no
    temporary file; ``resume=true`` picks it up by itself (a requeued job with the same run
    directory) and ends with the uninterrupted ``reference``."""
    assert _ckpt(run / "checkpoints" / "last.ckpt")["global_step"] == PAUSE_AT + 1
    assert not list((run / "checkpoints").glob(".*.tmp"))
    _train(*RUN, "resume=true", f"hydra.run.dir={run}", cwd=workdir)
    _assert_same_run(run, reference)


def test_sigterm_saves_a_checkpoint_of_the_current_step_and_resume_continues_exactly(
    workdir: Path, reference: Path
) -> None:
    run = workdir / "terminated"
    err = _stopped_by(signal.SIGTERM, run, workdir)
    assert "SIGTERM" in err
    # The interrupted step finished (global_step 12) and so did the validation that follows it;
    # then the checkpoint was saved (not the periodic one of step 8), readable by evaluation.
    saved = _ckpt(run / "checkpoints" / "last.ckpt")
    assert saved["hyper_parameters"]["model_config"]["net"]["hidden_units"] == 64
    _saved_the_step_and_resumes_exactly(run, workdir, reference)


def test_ctrl_c_saves_a_checkpoint_of_the_current_step_and_resume_continues_exactly(
    workdir: Path, reference: Path
) -> None:
    run = workdir / "ctrl-c"
    out = _stopped_by(signal.SIGINT, run, workdir)
    assert "stopped by SIGINT" in out and "KeyboardInterrupt" not in out
    # As on SIGTERM: the step and its validation finished, then last.ckpt was saved.
    _saved_the_step_and_resumes_exactly(run, workdir, reference)


def test_a_second_ctrl_c_ends_the_run_at_once(workdir: Path) -> None:
    # The step goes on waiting after the first Ctrl-C (a collective whose peer hangs, say).
    run = workdir / "ctrl-c-twice"
    proc, _ = _start_paused(run, workdir, "+callbacks.pause.hold=true")
    proc.send_signal(signal.SIGINT)
    time.sleep(1.0)
    assert proc.poll() is None  # the first one only asked the run to stop after the step
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGINT and time.monotonic() - sent < 10
    # Nothing saved since the periodic checkpoint of step 8, which is intact.
    assert _ckpt(run / "checkpoints" / "last.ckpt")["global_step"] == 8


def _slurm_job(workdir: Path) -> dict[str, str]:
    """The environment of task 0 of a one-task SLURM job (id 4242), as ``srun`` sets it, with a
    ``scontrol`` on the PATH that records its arguments in ``<workdir>/scontrol.log``."""
    bin_dir = workdir / "bin"
    bin_dir.mkdir(exist_ok=True)
    scontrol = bin_dir / "scontrol"
    scontrol.write_text(f'#!/bin/sh\necho "$@" >> {workdir / "scontrol.log"}\n')
    scontrol.chmod(0o755)
    return {
        "SLURM_JOB_ID": "4242", "SLURM_JOB_NAME": "mfg-test", "SLURM_NTASKS": "1",
        "SLURM_NTASKS_PER_NODE": "1", "SLURM_PROCID": "0", "SLURM_LOCALID": "0",
        "SLURM_NODEID": "0", "SLURM_NODELIST": "localhost",
        "PATH": os.pathsep.join([str(bin_dir), os.environ.get("PATH", "")]),
    }  # fmt: skip


def test_slurm_requeue_signal_saves_last_ckpt_requeues_and_the_requeued_job_resumes_exactly(
    workdir: Path, reference: Path
) -> None:
    # SLURM sends SIGUSR1 before the time limit (#SBATCH --signal=SIGUSR1@120): the step
    # finishes, last.ckpt is saved, the job asks to be requeued, the process exits with 143.
    run, job = workdir / "requeued", _slurm_job(workdir)
    returncode, err = _interrupt(run, workdir, signal.SIGUSR1, 120, "resume=true", env=job)
    assert returncode == 128 + signal.SIGTERM, err[-3000:]
    assert (workdir / "scontrol.log").read_text().split() == ["requeue", "4242"]
    assert _ckpt(run / "checkpoints" / "last.ckpt")["global_step"] == PAUSE_AT + 1
    # Lightning's own auto-requeue is off: no hpc_ckpt file, nothing resumes from one
    assert not list(run.rglob("hpc_ckpt*"))

    # The requeued job: the same command in a fresh process, which resume=true continues.
    _train(*RUN, "resume=true", f"hydra.run.dir={run}", cwd=workdir, env=job)
    _assert_same_run(run, reference)
    info = json.loads((run / "run_info.json").read_text())
    assert info["resumed_from"] == str(run / "checkpoints" / "last.ckpt")


def test_inside_slurm_the_trainer_has_lightnings_slurm_environment_without_auto_requeue(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from lightning.fabric.plugins.environments import SLURMEnvironment

    from mfg_lightning.core.config import compose
    from mfg_lightning.run.runs import build_trainer
    from mfg_lightning.run.slurm import SlurmRequeue, job_id

    cfg = compose("train", ["debug=tiny", "logger=none", f"paths.output_dir={tmp_path}"])
    outside = build_trainer(cfg, [], [])._accelerator_connector.cluster_environment
    assert not isinstance(outside, SLURMEnvironment)
    for key, value in _slurm_job(tmp_path).items():
        monkeypatch.setenv(key, value)
    inside = build_trainer(cfg, [], [])._accelerator_connector.cluster_environment
    assert isinstance(inside, SLURMEnvironment) and inside.auto_requeue is False
    # torchrun inside a SLURM task: Lightning's torchrun environment, not SLURM's
    for key, value in {"TORCHELASTIC_RUN_ID": "x", "GROUP_RANK": "0", "RANK": "0",
                       "LOCAL_RANK": "0", "WORLD_SIZE": "1"}.items():  # fmt: skip
        monkeypatch.setenv(key, value)
    from mfg_lightning.run.slurm import slurm_environment

    assert slurm_environment() is None
    assert cfg.callbacks.slurm_requeue._target_.endswith("SlurmRequeue")
    assert job_id() == "4242"
    assert (
        job_id({"SLURM_JOB_ID": "7", "SLURM_ARRAY_JOB_ID": "5", "SLURM_ARRAY_TASK_ID": "3"})
        == "5_3"
    )
    with pytest.raises(ValueError, match="SIGNOPE"):
        SlurmRequeue(signal="SIGNOPE")


def test_resume_true_without_a_checkpoint_starts_fresh_and_a_truncated_one_is_refused(
    tmp_path: Path,
) -> None:
    from mfg_lightning.run.training import resolve_ckpt_path

    assert resolve_ckpt_path(None, tmp_path, resume=True) is None
    assert resolve_ckpt_path(None, tmp_path, resume=False) is None
    last = tmp_path / "checkpoints" / "last.ckpt"
    last.parent.mkdir()
    torch.save({"state_dict": {}}, last)
    assert resolve_ckpt_path(None, tmp_path, resume=True) == str(last)
    assert resolve_ckpt_path("last", tmp_path) == str(last)
    last.write_bytes(last.read_bytes()[:-100])  # what a non-atomic writer killed mid-save leaves
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        resolve_ckpt_path("last", tmp_path)
    with pytest.raises(FileNotFoundError, match="nope.ckpt"):
        resolve_ckpt_path(str(tmp_path / "nope.ckpt"), tmp_path)
