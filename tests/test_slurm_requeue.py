"""SLURM's requeue signal outside the fit and in one process only (mfg_lightning.run.slurm).

Real trainings through the entry point in a simulated SLURM job: each task is started as ``srun``
would start it (``SLURM_*`` variables; two tasks form a gloo process group under
``trainer=ddp``, Lightning starting no process itself), with an ``scontrol`` on the PATH that
records its arguments, and whether ``metrics.json`` existed when it was called. The signal is
sent by the process to itself (:class:`SignalAt`), as SLURM would send it
(``#SBATCH --signal=SIGUSR1@120``).

Before, the signal during the test phase ended every task (status -10) with no ``metrics.json``
and no requeue, and a signal seen by a process other than the first stopped the run without a
requeue.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import pytest
import torch

from conftest import entry_point_env

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent
JOB = "4242"
#: seconds a whole job may take, start-up included
RUN_TIMEOUT = 400
#: seconds from the signal to the end of every task (the machine may be shared)
END_BOUND = 120.0
RUN = [
    "debug=tiny",
    "trainer.max_steps=8",
    "logger=none",
    "callbacks.rich_progress_bar=null",
    "+trainer.enable_progress_bar=false",
]


class SignalAt(L.Callback):
    """Test hook: the process of rank ``rank`` sends ``signal`` to itself at the start of the
    training step ``step`` (``stage="train"``) or of the first test batch (``stage="test"``),
    and writes ``marker``."""

    def __init__(self, signal: str, stage: str, rank: int, marker: str, step: int = 0) -> None:
        self.signum = getattr(__import__("signal"), signal)
        self.stage, self.rank, self.marker, self.step = stage, rank, Path(marker), step

    def _send(self, trainer: L.Trainer) -> None:
        self.marker.write_text(f"{time.time()} {trainer.global_step}\n")
        os.kill(os.getpid(), self.signum)

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any) -> None:
        due = trainer.global_rank == self.rank and trainer.global_step == self.step
        if self.stage == "train" and due and not trainer.sanity_checking:
            self._send(trainer)

    def on_test_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:  # fmt: skip
        if self.stage == "test" and trainer.global_rank == self.rank and batch_idx == 0:
            self._send(trainer)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _job(workdir: Path, run: Path, tasks: int, *overrides: str) -> list[tuple[int, str]]:
    """The tasks of a SLURM job running ``python -m mfg_lightning.train`` into ``run``; each
    task's exit status and output once every task has ended."""
    bin_dir = workdir / "bin"
    bin_dir.mkdir(exist_ok=True)
    scontrol = bin_dir / "scontrol"
    scontrol.write_text(
        "#!/bin/sh\n"
        f"if [ -f {run / 'metrics.json'} ]; then m=yes; else m=no; fi\n"
        f'echo "$@ metrics.json=$m" >> {workdir / "scontrol.log"}\n'
    )
    scontrol.chmod(0o755)
    port = str(_free_port())
    args = [*RUN, *(["trainer=ddp"] if tasks > 1 else []), *overrides, f"hydra.run.dir={run}"]
    procs = []
    for rank in range(tasks):
        env = entry_point_env(
            workdir,
            PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
            SLURM_JOB_ID=JOB, SLURM_JOB_NAME="mfg-test", SLURM_NTASKS=str(tasks),
            SLURM_NTASKS_PER_NODE=str(tasks), SLURM_PROCID=str(rank), SLURM_LOCALID=str(rank),
            SLURM_NODEID="0", SLURM_NODELIST="localhost", MASTER_PORT=port,
            PATH=os.pathsep.join([str(bin_dir), os.environ.get("PATH", "")]),
        )  # fmt: skip
        proc = subprocess.Popen(
            [sys.executable, "-m", "mfg_lightning.train", *args], cwd=workdir, env=env,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        )  # fmt: skip
        procs.append(proc)
    ended = []
    deadline = time.monotonic() + RUN_TIMEOUT
    for proc in procs:
        try:
            out, _ = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            for other in procs:
                if other.poll() is None:
                    os.killpg(other.pid, signal.SIGKILL)  # its own session: the task only
            out, _ = proc.communicate()
            raise AssertionError(f"task not ended after {RUN_TIMEOUT} s:\n{out[-5000:]}") from None
        ended.append((proc.returncode, out))
    return ended


def _seconds_after_signal(workdir: Path, name: str) -> float:
    """Seconds from the signal (its marker) to now, when every task has ended."""
    marker = workdir / f"{name}.marker"
    assert marker.exists(), "the signal was never sent"
    seconds = time.time() - float(marker.read_text().split()[0])
    print(f"every task ended {seconds:.1f} s after the signal")  # shown by pytest -s
    assert seconds < END_BOUND
    return seconds


def _signal_at(workdir: Path, name: str, stage: str, rank: int, step: int = 0) -> list[str]:
    key = "+callbacks.signal_at"
    return [
        f"{key}._target_=test_slurm_requeue.SignalAt", f"{key}.signal=SIGUSR1",
        f"{key}.stage={stage}", f"{key}.rank={rank}", f"{key}.step={step}",
        f"{key}.marker={workdir / f'{name}.marker'}",
    ]  # fmt: skip


@pytest.mark.parametrize("tasks", [1, 2], ids=["one_task", "two_tasks_signal_in_the_second"])
def test_the_requeue_signal_in_the_test_phase_writes_metrics_and_requeues_once(
    tmp_path: Path, tasks: int
) -> None:
    # The signal reaches the last task only, in its first test batch: the test finishes,
    # metrics.json is written, then the first task requeues the job, once.
    run = tmp_path / "run"
    signal_at = _signal_at(tmp_path, "test", "test", rank=tasks - 1)
    ended = _job(tmp_path, run, tasks, *signal_at)
    for returncode, output in ended:
        assert returncode == 0, output[-5000:]
    _seconds_after_signal(tmp_path, "test")
    assert (run / "metrics.json").exists()
    log = (tmp_path / "scontrol.log").read_text().splitlines()
    assert log == [f"requeue {JOB} metrics.json=yes"], ended[0][1][-3000:]


def test_the_requeue_signal_in_a_process_other_than_the_first_requeues_the_job_once(
    tmp_path: Path,
) -> None:
    # Two tasks; the second alone gets the signal during the fit: both stop after the same
    # step, last.ckpt is saved, and the first task requeues the job.
    run = tmp_path / "run"
    ended = _job(tmp_path, run, 2, *_signal_at(tmp_path, "fit", "train", rank=1, step=3))
    for returncode, output in ended:
        assert returncode == 128 + signal.SIGTERM, output[-5000:]
    _seconds_after_signal(tmp_path, "fit")
    log = (tmp_path / "scontrol.log").read_text().splitlines()
    assert log == [f"requeue {JOB} metrics.json=no"], ended[0][1][-3000:]
    last = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert last["global_step"] == 4  # the step the signal came in finished, on both
    assert not (run / "metrics.json").exists()
