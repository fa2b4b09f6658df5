"""A callback that counts, per training step, what makes the host wait for the device.

Counted, in every process of a run (DDP included):

* **reads**: ``Tensor.item``, ``.tolist``, ``.cpu`` and the conversions
  ``float()``, ``int()``, ``bool()`` of a tensor. On a GPU each waits for the queued kernels; on
  the CPU the same calls are made, which is what makes them countable here.
* **collectives**: every ``torch.distributed`` call that talks to the other processes
  (``all_reduce``, ``broadcast``, ``barrier``, the object collectives, ...) and DDP's broadcast of
  the module's buffers before a forward (``_broadcast_coalesced``). DDP's gradient all-reduce
  runs inside the backward in C++ and is not counted: every data-parallel step needs it.

A step's window runs from its ``on_train_batch_start`` to the next one's, or to the start of a
validation (which and whose end are not counted), in the training loop's thread, without the
data loading (frames of ``torch.utils.data``; the prefetch threads are not counted): what
Lightning, the module and every callback do for that step. At the end of training each process
writes ``host_waits_rank<r>.json``: ``{"log_every": n, "steps": {step: {name: count}}}`` (and the
ends of the epochs, counted apart under ``"epoch_end"``).

Used by tests/test_host_waits.py through the entry point (``+callbacks.host_waits._target_=
host_waits.CountHostWaits``, with tests/ on ``PYTHONPATH``). ``accelerator_cadence`` makes the
run read as on a GPU, where a read waits for the device
(:meth:`~mfg_lightning.models.nonfinite.NonFiniteLosses.reads_wait_for_nothing` answers no): the
stop and fail flags of :class:`~mfg_lightning.models.agreement.Agreement` at the logging steps
only, instead of every step as on a CPU, and the step's non-finite verdict not at all
(``callbacks.batch_checks.deferred`` does the same for the batch checks).

Not a test module (no ``test_`` prefix): pytest does not collect it.
"""

from __future__ import annotations

import collections
import json
import sys
import threading
from pathlib import Path
from typing import Any

import lightning as L
import torch
import torch.distributed as dist

from mfg_lightning.models.nonfinite import NonFiniteLosses

# (``numpy()`` is not among them: it refuses a device tensor, so it never waits for one)
READS = ("item", "tolist", "cpu", "__float__", "__int__", "__bool__")
COLLECTIVES = (
    "all_reduce",
    "broadcast",
    "barrier",
    "all_gather",
    "all_gather_into_tensor",
    "all_gather_object",
    "broadcast_object_list",
    "gather",
    "gather_object",
    "reduce",
    "reduce_scatter",
    "scatter",
    "monitored_barrier",
    "_broadcast_coalesced",
)


def _loading() -> bool:
    """Whether the caller is inside the data loading (the dataset, the collate, the loader)."""
    frame = sys._getframe(2)
    while frame is not None:
        if "torch/utils/data/" in frame.f_code.co_filename.replace("\\", "/"):
            return True
        frame = frame.f_back
    return False


def _site(frame: Any) -> str:
    """``file:line`` of ``frame``, the file relative to its package's parent."""
    name = frame.f_code.co_filename.replace("\\", "/")
    for root in ("site-packages/", "src/", "tests/"):
        if root in name:
            name = name.split(root, 1)[1]
            break
    return f"{name}:{frame.f_lineno}"


class CountHostWaits(L.Callback):
    """Count the host waits of every training step (see the module's docstring).

    Args:
        path: the folder of the ``host_waits_rank<r>.json`` files.
        accelerator_cadence: read as on a GPU: the agreed flags at the logging steps only and
            the step's non-finite verdict not at all (a CPU reads both every step).
        where: also count each call by its call site (``"item at file:line"``), to find them.
    """

    def __init__(self, path: str, accelerator_cadence: bool = True, where: bool = False) -> None:
        self.path = Path(path)
        self.where = where
        self.accelerator_cadence = accelerator_cadence
        self.steps: dict[int | str, collections.Counter] = {}
        self._current: collections.Counter | None = None
        self._patched: list[tuple[Any, str, Any]] = []
        self._thread: int | None = None  # the training loop's

    # -- patching ------------------------------------------------------------------------------

    def _count(self, name: str) -> None:
        if self._current is None or threading.get_ident() != self._thread:
            return  # outside a step, or a data-loading thread (the project's prefetcher)
        if not _loading():
            self._current[name] += 1
            if self.where:
                caller = sys._getframe(2)
                self._current[f"{name} at {_site(caller)}"] += 1

    def _wrap(self, owner: Any, name: str) -> None:
        original = getattr(owner, name, None)
        if original is None:
            return

        def counted(*args: Any, **kwargs: Any) -> Any:
            self._count(name)
            return original(*args, **kwargs)

        setattr(owner, name, counted)
        self._patched.append((owner, name, original))

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit" or self._patched:
            return
        self._thread = threading.get_ident()
        for name in READS:
            self._wrap(torch.Tensor, name)
        for name in COLLECTIVES:
            self._wrap(dist, name)
        if self.accelerator_cadence:
            original = vars(NonFiniteLosses)["reads_wait_for_nothing"]
            self._patched.append((NonFiniteLosses, "reads_wait_for_nothing", original))
            NonFiniteLosses.reads_wait_for_nothing = staticmethod(lambda device: False)

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit":
            return
        for owner, name, original in reversed(self._patched):
            setattr(owner, name, original)
        self._patched.clear()

    # -- the windows ---------------------------------------------------------------------------

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any, **kwargs: Any) -> None:
        self._current = self.steps.setdefault(trainer.global_step, collections.Counter())

    def on_train_start(self, trainer: L.Trainer, *args: Any) -> None:
        # The end of an epoch (Lightning's fit loop: the epoch-end hooks, the epoch's logging) is
        # not a step's: counted apart, under "epoch_end"
        loop = trainer.fit_loop
        step_end = loop.on_advance_end

        def on_advance_end(*args: Any, **kwargs: Any) -> Any:
            self._current = self.steps.setdefault("epoch_end", collections.Counter())
            try:
                return step_end(*args, **kwargs)
            finally:
                self._current = None

        loop.on_advance_end = on_advance_end  # type: ignore[method-assign]

    def on_validation_start(self, trainer: L.Trainer, *args: Any) -> None:
        # the validation and what its end calls (checkpoints, the convergence rule) are not
        # the step's: counting resumes at the next step
        self._current = None

    def on_train_end(self, trainer: L.Trainer, *args: Any) -> None:
        self._current = None
        self.path.mkdir(parents=True, exist_ok=True)
        result = {
            "log_every": trainer.log_every_n_steps,
            "world_size": trainer.world_size,
            "steps": {str(k): dict(v) for k, v in self.steps.items()},
        }
        out = self.path / f"host_waits_rank{trainer.global_rank}.json"
        out.write_text(json.dumps(result, indent=1))
