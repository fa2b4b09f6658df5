"""Faults injected into one process of a real ``trainer=ddp`` training (tests/test_ddp_faults.py).

:class:`Fault` is a Lightning callback that the training builds from the command line
(``+callbacks.fault._target_=ddp_faults.Fault``, with this folder on ``PYTHONPATH``); Lightning
starts the second process with the same command, so both have it, and it acts in the process of
rank ``rank`` only, at the training steps ``steps`` (global steps, before the step runs):

* ``sigterm``: the process sends SIGTERM to itself, as a scheduler would;
* ``bad_batch``: the first sample's pose is made non-finite, which ``AgreedSteps`` refuses;
* ``non_finite``: the step's loss is NaN (a forward hook on the loss);
* ``no_samples``: the batch arrives as None (before its transfer to the device), as when every
  sample was skipped as unreadable;
* ``error``: a ``RuntimeError`` that nothing agrees on (a bug in one process).

It writes ``<marker>`` (the time and the step) each time it acts, so that the test can time the
end of the run from the last fault. :func:`run_with_faults` runs an entry point with faults and
times its end.

Not a test module (no ``test_`` prefix): pytest does not collect it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch

KINDS = ("sigterm", "bad_batch", "non_finite", "no_samples", "error")


class Fault(L.Callback):
    """One kind of fault in the process of rank ``rank`` at the training steps ``steps``.

    Args:
        kind: one of :data:`KINDS`.
        steps: the global steps at whose start it acts.
        marker: the file written each time it acts.
        rank: the process it acts in.
    """

    def __init__(self, kind: str, steps: list[int], marker: str, rank: int = 1) -> None:
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        self.kind, self.steps, self.marker, self.rank = kind, set(steps), Path(marker), rank

    def _due(self, trainer: L.Trainer) -> bool:
        return (
            trainer.global_rank == self.rank
            and trainer.training
            and not trainer.sanity_checking
            and trainer.global_step in self.steps
        )

    def _mark(self, trainer: L.Trainer) -> None:
        self.marker.write_text(f"{time.time()} {trainer.global_step}\n")

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        # First among the callbacks, so that a corrupted batch reaches AgreedSteps.
        trainer.callbacks.remove(self)
        trainer.callbacks.insert(0, self)
        self._trainer = trainer
        if self.kind == "non_finite":
            pl_module.loss_fn.register_forward_hook(self._nan_loss)
        if self.kind == "no_samples":
            step = pl_module.on_before_batch_transfer

            def none_batch(batch: Any, dataloader_idx: int) -> Any:
                if self._due(trainer):
                    self._mark(trainer)
                    batch = None
                return step(batch, dataloader_idx)

            pl_module.on_before_batch_transfer = none_batch  # type: ignore[method-assign]

    def _nan_loss(self, module: torch.nn.Module, args: Any, terms: Any) -> Any:
        trainer = self._trainer
        if not module.training or not self._due(trainer):
            return terms
        self._mark(trainer)
        return terms._replace(total=terms.total * float("nan"))

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        if not self._due(trainer) or self.kind not in ("sigterm", "bad_batch", "error"):
            return
        self._mark(trainer)
        if self.kind == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)
        elif self.kind == "bad_batch":
            batch["pose"][0, 0, 3] = float("nan")
        else:
            raise RuntimeError(f"injected error in process {trainer.global_rank}")


@dataclass
class FaultyRun:
    """How a run ended: the first process's exit status, the output of every process, and the
    seconds from the last fault to the end of the last process (None: no fault acted)."""

    returncode: int
    output: str
    seconds_after_fault: float | None


def run_with_faults(
    module: str,
    args: list[str],
    workdir: Path,
    run: str,
    env: dict[str, str],
    faults: dict[str, tuple] | None = None,
    timeout: float = 600,
) -> FaultyRun:
    """``python -m <module> <args>`` into ``<workdir>/<run>`` with the faults ``{name: (kind,
    steps, rank)}``, until every process it started has ended (their shared output is closed).
    ``env`` must put this folder on ``PYTHONPATH``. A run still going after ``timeout`` seconds
    is killed (its own session: its processes only) and fails the test."""
    markers, args = [], [*args, f"hydra.run.dir={workdir / run}"]
    for name, (kind, steps, rank) in (faults or {}).items():
        marker = workdir / f"{run}.{name}.marker"
        marker.unlink(missing_ok=True)
        markers.append(marker)
        key = f"+callbacks.{name}"
        args += [f"{key}._target_=ddp_faults.Fault", f"{key}.kind={kind}", f"{key}.steps={steps}",
                 f"{key}.rank={rank}", f"{key}.marker={marker}"]  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", module, *args], cwd=workdir, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        output, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        raise AssertionError(f"{run}: not ended after {timeout} s:\n{output[-5000:]}") from None
    ended = time.time()
    acted = [float(m.read_text().split()[0]) for m in markers if m.exists()]
    return FaultyRun(proc.returncode, output, ended - max(acted) if acted else None)
