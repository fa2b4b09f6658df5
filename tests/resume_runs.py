"""What the tests of interrupted and resumed trainings share (tests/test_resume.py,
tests/test_atomic_writes.py, tests/test_resume_guards.py): the run's settings, the test hooks
the training subprocess loads (:class:`PauseAt`, :class:`FillDisk`), starting, interrupting and
running ``python -m mfg_lightning.train``, and the comparison of a run with the uninterrupted
one."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import pytest
import torch

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
            "+callbacks.pause._target_=resume_runs.PauseAt", f"+callbacks.pause.step={PAUSE_AT}",
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
