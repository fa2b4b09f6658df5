"""Interrupted runs resume exactly; checkpoints survive kills and full disks.

Real trainings through the Hydra entry point: one is killed with SIGKILL in the middle of an
optimiser step, mid-epoch, and resumed with ``ckpt_path=last``; another gets SIGTERM and must
save before it exits; both must end with the weights and metrics of an uninterrupted run.
A run whose disk fills up must fail with one clear line and leave the previous checkpoint
loadable; a kill during a checkpoint write must not break the previous file.
"""

from __future__ import annotations

import errno
import json
import multiprocessing as mp
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import pytest
import torch

from mfg_lightning.data.kitti import FlowCache
from mfg_lightning.data.resumable_loader import EpochShuffleSampler, ResumableDataLoader
from mfg_lightning.run.callbacks import AtomicCheckpointIO, StorageError, storage_error

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent
# 24 optimiser steps over 5 batches per epoch (18 training samples, batch 4): epochs end after
# steps 5, 10, 15, 20; validation after every 6th step; the resumable checkpoint every 4 steps.
# Runs are stopped in the middle of the step that takes global_step from 11 to 12 (the second
# batch of epoch 2). The checkpoint before it (step 8) sits after the third batch of epoch 1, so
# resuming from it has to continue mid-epoch; step 12 is followed by a validation.
RUN = [
    "debug=tiny",
    "seed=3",
    "logger=none",
    "callbacks.rich_progress_bar=null",
    "+trainer.enable_progress_bar=false",
    "trainer.max_steps=24",
    "trainer.val_check_interval=6",
    "callbacks.last_checkpoint.every_n_train_steps=4",
]
PAUSE_AT = 11  # global_step during the paused optimiser step


class PauseAt(L.Callback):
    """Test hook loaded by the training subprocess: in the middle of step ``step`` (gradients
    computed, weights not yet updated) write ``marker`` and wait for a signal (``hold``: wait
    on after it too, as a step stuck in a collective would)."""

    def __init__(self, step: int, marker: str, hold: bool = False) -> None:
        self.step, self.marker, self.hold = step, Path(marker), hold

    def on_before_optimizer_step(self, trainer: L.Trainer, *args: Any) -> None:
        if trainer.global_step != self.step:
            return
        self.marker.write_text(str(os.getpid()))
        deadline = time.monotonic() + 120
        # SIGKILL ends the process here; SIGTERM only sets Lightning's flag, then the step
        # goes on as Lightning would let it.
        while (self.hold or not trainer.received_sigterm) and time.monotonic() < deadline:
            time.sleep(0.02)


class FillDisk(L.Callback):
    """Test hook: after step ``step``, fill the run directory's file system (leaving
    ``leave`` bytes), before the checkpoint callbacks save."""

    def __init__(self, step: int, leave: int = 16 * 1024) -> None:
        self.step, self.leave = step, leave

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if trainer.global_step == self.step:
            target = Path(trainer.default_root_dir) / "filler"
            free = shutil.disk_usage(target.parent).free
            with open(target, "wb") as fh:
                fh.write(b"\0" * max(0, free - self.leave))


def _env() -> dict[str, str]:
    return dict(
        os.environ,
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
        HYDRA_FULL_ERROR="0",
        PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
    )


def _start_paused(
    run: Path, cwd: Path, *extra: str, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, Path]:
    """Start a training that pauses in the middle of an optimiser step; wait until it does
    (``env``: more environment variables)."""
    marker = cwd / f"paused-{run.name}"
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "mfg_lightning.train", *RUN, *extra, f"hydra.run.dir={run}",
            "+callbacks.pause._target_=test_resume.PauseAt", f"+callbacks.pause.step={PAUSE_AT}",
            f"+callbacks.pause.marker={marker}",
        ],
        cwd=cwd, env={**_env(), "MFG_CACHE_DIR": str(cwd / "cache"), **(env or {})},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 180
    while not marker.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            out, err = proc.communicate()
            raise AssertionError(f"training did not reach the pause:\n{out}\n{err[-4000:]}")
        time.sleep(0.05)
    return proc, marker


def _interrupt(
    run: Path, cwd: Path, sig: signal.Signals, timeout: int, *extra: str, **kw: Any
) -> tuple[int, str]:
    """Send ``sig`` to a training paused mid-step (:func:`_start_paused`, given ``extra`` and
    ``kw``); its exit status and output (stdout, where the run's own log lines go, then stderr)
    once it has ended."""
    proc, _ = _start_paused(run, cwd, *extra, **kw)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out + err


def _train(
    *args: str, cwd: Path, check: bool = True, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """``python -m mfg_lightning.train`` as a user runs it (with this directory importable, so
    that Hydra can build the test hooks above; ``env``: more environment variables)."""
    proc = subprocess.run(
        [sys.executable, "-m", "mfg_lightning.train", *args],
        cwd=cwd, env={**_env(), "MFG_CACHE_DIR": str(cwd / "cache"), **(env or {})},
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    if check and proc.returncode != 0:
        raise AssertionError(f"training failed ({proc.returncode}):\n{proc.stderr[-5000:]}")
    return proc


def _ckpt(path: Path) -> dict[str, Any]:
    return torch.load(path, map_location="cpu", weights_only=False)


def _max_weight_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    assert a.keys() == b.keys()
    return max((a[k].double() - b[k].double()).abs().max().item() for k in a)


def _metrics(run: Path) -> dict[str, float | None]:
    return json.loads((run / "metrics.json").read_text())["metrics"]


def _assert_same_run(run: Path, reference: Path) -> float:
    """Final weights, optimiser state and every metric of ``run`` equal those of
    ``reference`` (within float tolerance). Returns the largest weight difference."""
    got, want = _ckpt(run / "checkpoints" / "last.ckpt"), _ckpt(reference / "checkpoints/last.ckpt")
    assert got["global_step"] == want["global_step"] == 24
    diff = _max_weight_difference(got["state_dict"], want["state_dict"])
    assert diff <= 1e-6, f"weights differ by {diff}"
    adam = [s["exp_avg_sq"] for s in got["optimizer_states"][0]["state"].values()]
    adam_ref = [s["exp_avg_sq"] for s in want["optimizer_states"][0]["state"].values()]
    assert all(
        torch.allclose(a, b, rtol=1e-5, atol=1e-12) for a, b in zip(adam, adam_ref, strict=True)
    )
    m, m_ref = _metrics(run), _metrics(reference)
    assert m.keys() == m_ref.keys() and any(k.startswith("val/") for k in m)
    for key, value in m_ref.items():
        if value is None:
            assert m[key] is None, key
        else:
            assert m[key] == pytest.approx(value, rel=1e-5, abs=1e-7), key
    best = json.loads((run / "metrics.json").read_text())["best_checkpoint"]
    best_ref = json.loads((reference / "metrics.json").read_text())["best_checkpoint"]
    assert Path(best).name == Path(best_ref).name  # the same validation chose the same weights
    return diff


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


def test_sigterm_saves_a_checkpoint_of_the_current_step_and_resume_continues_exactly(
    workdir: Path, reference: Path
) -> None:
    run = workdir / "terminated"
    returncode, err = _interrupt(run, workdir, signal.SIGTERM, timeout=120)
    assert returncode == 128 + signal.SIGTERM, err[-3000:]
    assert "SIGTERM" in err
    # The interrupted step finished (global_step 12) and so did the validation that follows it;
    # then the checkpoint was saved (not the periodic one of step 8), readable by evaluation.
    saved = _ckpt(run / "checkpoints" / "last.ckpt")
    assert saved["global_step"] == PAUSE_AT + 1
    assert saved["hyper_parameters"]["model_config"]["net"]["hidden_units"] == 64
    assert not list((run / "checkpoints").glob(".*.tmp"))

    # resume=true picks up last.ckpt by itself (a requeued job with the same run directory).
    _train(*RUN, "resume=true", f"hydra.run.dir={run}", cwd=workdir)
    _assert_same_run(run, reference)


def test_ctrl_c_saves_a_checkpoint_of_the_current_step_and_resume_continues_exactly(
    workdir: Path, reference: Path
) -> None:
    run = workdir / "ctrl-c"
    returncode, out = _interrupt(run, workdir, signal.SIGINT, timeout=120)
    assert returncode == 128 + signal.SIGINT, out[-3000:]
    assert "stopped by SIGINT" in out and "KeyboardInterrupt" not in out
    # As on SIGTERM: the step and its validation finished, then last.ckpt was saved.
    assert _ckpt(run / "checkpoints" / "last.ckpt")["global_step"] == PAUSE_AT + 1
    assert not list((run / "checkpoints").glob(".*.tmp"))

    _train(*RUN, "resume=true", f"hydra.run.dir={run}", cwd=workdir)
    _assert_same_run(run, reference)


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


# --------------------------------------------------------------------------------------------
# The data order
# --------------------------------------------------------------------------------------------


def _ids(loader: ResumableDataLoader) -> list[list[int]]:
    return [batch.tolist() for batch in loader]


def _flat(batches: list[list[int]]) -> list[int]:
    return [i for batch in batches for i in batch]


def test_epoch_order_depends_on_seed_and_epoch_only_and_resumes_mid_epoch() -> None:
    data = torch.arange(18)
    loader = ResumableDataLoader(data, seed=5, batch_size=4)
    epochs = []
    for epoch in range(3):
        loader.order.set_epoch(epoch)
        epochs.append(_ids(loader))
    assert all(sorted(_flat(e)) == list(range(18)) for e in epochs)  # permutations
    assert epochs[0] != epochs[1] != epochs[2]
    assert _ids(ResumableDataLoader(data, seed=6, batch_size=4)) != epochs[0]

    # Stop after 3 batches of epoch 1, save, restore into a new loader (a new process).
    loader.order.set_epoch(1)
    it = iter(loader)
    seen = [next(it).tolist() for _ in range(3)]
    state = loader.state_dict()
    assert state == {"epoch": 1, "batches": 3, "samples": 18, "processes": 1, "length": 5,
                     "batch_size": 4, "dataset": "Tensor",
                     "sampler": "EpochShuffleSampler(seed=5)"}  # fmt: skip
    resumed = ResumableDataLoader(data, seed=5, batch_size=4)
    resumed.load_state_dict(state)
    assert resumed.state_dict() == state  # saved again before iterating: still the same place
    resumed.order.set_epoch(1)  # what Lightning does at the start of the epoch
    assert seen + _ids(resumed) == epochs[1]
    assert len(resumed) == 5  # the epoch's length, as Lightning counts its batches
    resumed.order.set_epoch(2)  # the next epoch starts from its beginning
    assert _ids(resumed) == epochs[2]


def test_an_order_saved_at_the_end_of_an_epoch_resumes_with_the_next_one() -> None:
    data = torch.arange(10)
    loader = ResumableDataLoader(data, seed=0, batch_size=5)
    loader.load_state_dict({"epoch": 0, "batches": 2, "samples": 10})
    loader.order.set_epoch(1)
    sampler = EpochShuffleSampler(10, 0)
    assert _flat(_ids(loader)) == sampler.permutation(1).tolist()


def test_under_ddp_each_process_takes_its_share_of_the_order_and_resumes_it_mid_epoch() -> None:
    data, processes = torch.arange(19), 2  # 19: the last round is padded
    loaders = [
        ResumableDataLoader(data, seed=5, batch_size=3, num_replicas=processes, rank=r)
        for r in range(processes)
    ]
    shares = []
    for loader in loaders:
        loader.order.set_epoch(1)
        shares.append(_ids(loader))
    assert [len(share) for share in shares] == [len(loader) for loader in loaders] == [4, 4]
    # positions r, r + 2, ... of the epoch's one permutation, padded with its first index
    permutation = EpochShuffleSampler(19, 5).permutation(1).tolist()
    padded = [*permutation, permutation[0]]
    assert [_flat(share) for share in shares] == [padded[0::2], padded[1::2]]

    # Stopped after 2 batches of each process (the checkpoint holds rank 0's state, the same as
    # rank 1's), resumed by 2 new processes: each continues its own share.
    states = []
    for loader in loaders:
        it = iter(loader)
        [next(it) for _ in range(2)]
        states.append(loader.state_dict())
    assert states[0] == states[1] == {"epoch": 1, "batches": 2, "samples": 19, "processes": 2,
                                      "length": 4, "batch_size": 3, "dataset": "Tensor",
                                      "sampler": "EpochShuffleSampler(seed=5)"}  # fmt: skip
    for rank, share in enumerate(shares):
        resumed = ResumableDataLoader(data, seed=5, batch_size=3, num_replicas=2, rank=rank)
        resumed.load_state_dict(states[0])
        resumed.order.set_epoch(1)
        assert share[:2] + _ids(resumed) == share
    # Another number of processes: the interrupted epoch starts again, whole.
    other = ResumableDataLoader(data, seed=5, batch_size=3, num_replicas=3, rank=0)
    other.load_state_dict(states[0])
    other.order.set_epoch(1)
    assert _flat(_ids(other)) == permutation[0::3]


# --------------------------------------------------------------------------------------------
# Checkpoint files: kills during a save, full disks, concurrent cache writers
# --------------------------------------------------------------------------------------------

_WRITER = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    import torch
    from mfg_lightning.run.callbacks import AtomicCheckpointIO

    path, marker = Path(sys.argv[1]), Path(sys.argv[2])
    io = AtomicCheckpointIO()
    io.save_checkpoint({"version": 1, "w": torch.ones(1_000_000)}, path)
    real_fsync = os.fsync

    def slow_fsync(fd):  # the new file's bytes are written: the worst moment to be killed
        real_fsync(fd)
        marker.write_text("writing")
        time.sleep(120)

    os.fsync = slow_fsync
    io.save_checkpoint({"version": 2, "w": torch.full((2_000_000,), 2.0)}, path)
    """
)


def test_a_kill_during_a_checkpoint_save_leaves_the_previous_checkpoint_loadable(
    tmp_path: Path,
) -> None:
    path, marker = tmp_path / "checkpoints" / "last.ckpt", tmp_path / "marker"
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path), str(marker)], env=_env(), cwd=tmp_path
    )
    deadline = time.monotonic() + 120
    while not marker.exists():
        assert proc.poll() is None and time.monotonic() < deadline, "writer did not start"
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    temps = list(path.parent.glob(".last.ckpt.*.tmp"))
    assert len(temps) == 1 and temps[0].stat().st_size > 8_000_000  # the interrupted write
    ckpt = AtomicCheckpointIO().load_checkpoint(path)
    assert ckpt["version"] == 1 and torch.equal(ckpt["w"], torch.ones(1_000_000))


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 24 MB tmpfs (root in a sandbox); skipped where mounting is not permitted."""
    mount = tmp_path / "disk"
    mount.mkdir()
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(mount)],
        capture_output=True,
        check=False,
    )
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {proc.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_full_disk_during_training_is_one_clear_error_and_the_last_checkpoint_loads(
    small_disk: Path, tmp_path: Path
) -> None:
    run = small_disk / "run"
    proc = _train(
        *RUN,
        f"hydra.run.dir={run}",
        "+callbacks.fill._target_=test_resume.FillDisk",
        "+callbacks.fill.step=8",
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-3000:]
    error = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(error) == 1, proc.stderr[-3000:]
    assert f"cannot write checkpoint {run / 'checkpoints' / 'last.ckpt'}" in error[0]
    assert "no space left on device" in error[0]
    assert "Traceback" not in proc.stderr
    # The checkpoint of step 4 is intact and resumable; no temporary file is left behind.
    ckpt = AtomicCheckpointIO().load_checkpoint(
        run / "checkpoints" / "last.ckpt", weights_only=False
    )
    assert ckpt["global_step"] == 4
    assert not list((run / "checkpoints").glob(".*.tmp"))


def test_a_full_disk_keeps_the_previous_checkpoint_and_cache_entry(small_disk: Path) -> None:
    io = AtomicCheckpointIO()
    path = small_disk / "checkpoints" / "last.ckpt"
    io.save_checkpoint({"step": 1, "w": torch.ones(1000)}, path)
    cache = FlowCache(small_disk / "cache")
    entry = cache.path("09", (48, 128), 0, 1)
    flow = np.ones((48, 128, 2), np.float32)
    cache.store(entry, flow)
    free = shutil.disk_usage(small_disk).free
    (small_disk / "filler").write_bytes(b"\0" * (free - 64 * 1024))

    with pytest.raises(StorageError, match=r"cannot write checkpoint .*last\.ckpt: no space left"):
        io.save_checkpoint({"step": 2, "w": torch.ones(1_000_000)}, path)
    assert io.load_checkpoint(path)["step"] == 1
    with pytest.raises(OSError) as err:
        cache.store(entry, np.zeros((480, 1280, 2), np.float32))
    # ENOSPC from deep inside a data module: the entry point turns it into one line. A failed
    # write() names no file, so the line says where the run writes instead.
    assert err.value.errno == errno.ENOSPC
    message = str(storage_error(err.value.filename, err.value, hint=f"cache {small_disk}"))
    assert message.startswith("cannot write") and "no space left on device" in message
    # When the name is known, a temporary file of mfg_lightning.core.atomic is reported as its
    # target.
    temporary = entry.with_name(f".{entry.name}.{'0' * 32}.tmp")
    full = OSError(errno.ENOSPC, "No space left on device", str(temporary))
    assert str(storage_error(full.filename, full)).startswith(
        f"cannot write file {entry}: no space left on device ("
    )
    assert np.array_equal(cache.load(entry, flow.shape, np.float32), flow)
    assert not [p for p in small_disk.rglob("*.tmp")]


def _cache_writer(root: str, worker: int, rounds: int) -> None:
    cache = FlowCache(Path(root))
    for i in range(rounds):
        # Every writer stores full arrays whose every element is the same value.
        value = float(worker * 1000 + i)
        cache.store(cache.path("00", (48, 128), 0, 1), np.full((96, 256, 2), value, np.float32))


def test_concurrent_runs_sharing_the_flow_cache_never_see_a_partial_entry(
    tmp_path: Path,
) -> None:
    """Two processes keep rewriting one cache entry (a joblib multirun computing the same flow)
    while this one reads it: every read is absent or one whole array."""
    ctx = mp.get_context("fork")  # the writers need numpy only
    writers = [ctx.Process(target=_cache_writer, args=(str(tmp_path), w, 150)) for w in (1, 2)]
    for w in writers:
        w.start()
    cache = FlowCache(tmp_path)
    entry = cache.path("00", (48, 128), 0, 1)
    reads = 0
    while any(w.is_alive() for w in writers) or reads == 0:
        array = cache.load(entry, (96, 256, 2), np.float32)
        if array is not None:
            assert (array == array.flat[0]).all(), "a reader saw a mix of two writes"
            reads += 1
    for w in writers:
        w.join(timeout=60)
        assert w.exitcode == 0
    assert reads > 0
    assert not list(tmp_path.rglob("*.tmp"))
    # The surviving entry is one writer's last array.
    final = cache.load(entry, (96, 256, 2), np.float32)
    assert final is not None and float(final.flat[0]) in (1149.0, 2149.0)
