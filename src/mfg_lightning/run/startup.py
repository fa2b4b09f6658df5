"""The start-up window of a data-parallel run: a fault in it ends every process within seconds.

**The processes a launcher started end with it.**

Lightning's subprocess launcher (``trainer=ddp``: no torchrun, no SLURM) starts the other
processes of a data-parallel run from the first one, at the start of ``trainer.fit``. Once
Lightning's handlers are in place, every end of the first process ends the others
(:mod:`mfg_lightning.run.together`). Before that, and whenever the first process is killed
without a chance to act (SIGKILL, the out-of-memory killer, a crash in native code), nothing did:
the others waited for it in the process group's rendezvous until its timeout (30 minutes by
default; one was still alive 560 s after the first process got SIGTERM, 1 s after it started).

* The launching process records its pid in :data:`LAUNCHER_VARIABLE` while it fits or tests
  (:func:`launching`), so that the processes it starts inherit it.
* A process started so (``LOCAL_RANK`` > 0 and that variable set) calls
  :func:`end_with_launcher` before it builds the trainer's process group. On Linux it asks the
  kernel for SIGKILL when its parent ends (``prctl(PR_SET_PDEATHSIG)``): the signal arrives even
  while the process waits inside native code (a rendezvous, a collective), where no Python
  handler runs. Elsewhere a daemon thread polls the parent's pid every
  :data:`POLL_SECONDS` and ends the process. Either way a parent that ended before the call (its
  pid is no longer the parent's) ends the process at once.

The kernel's signal follows the thread that started the process (Lightning starts them from the
thread that calls ``trainer.fit``): a run started from a thread that ends before the process does
ends its processes too. Disarmed when the process exits (its work done, the first process may
end first).

SIGKILL, not SIGTERM: without the first process the others can neither save (the first one
writes the checkpoints) nor stop together, and a SIGTERM handler would not run while the process
waits in native code. Nothing is armed under torchrun or SLURM, whose launchers end the tasks
themselves (``srun --kill-on-bad-exit=1``).

**A shorter process-group timeout during start-up.** :class:`StartupDDPStrategy` (``trainer=ddp``
and the configurations built on it) gives the process group ``startup_timeout`` seconds (5
minutes in ``conf/trainer/ddp.yaml``) while it is formed: the first process waits that long for
the others to start (import, compose, build their data) and reach the rendezvous, a process left
waiting for a peer that hangs no longer waits torch's 30 minutes. Once the group is formed, its
timeout becomes ``timeout`` (torch's default, 30 minutes), through the process group's public
``set_timeout``: a collective may legitimately wait minutes for a peer (a checkpoint being
written, an evaluation's uneven share).
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import ctypes.util
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import torch.distributed as dist
from lightning.pytorch.strategies import DDPStrategy

log = logging.getLogger(__name__)

__all__ = [
    "LAUNCHER_VARIABLE",
    "POLL_SECONDS",
    "StartupDDPStrategy",
    "end_with_launcher",
    "launching",
]

#: the environment variable holding the pid of the process that starts the others
LAUNCHER_VARIABLE = "MFG_DDP_LAUNCHER_PID"
#: seconds between two looks at the parent's pid where the kernel cannot watch it (not Linux)
POLL_SECONDS = 1.0
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>

_armed = False


def _launcher_pid(environ: dict[str, str] | os._Environ[str]) -> int | None:
    """The pid of the process that started this one, where Lightning's launcher started it
    (``LOCAL_RANK`` > 0 and :data:`LAUNCHER_VARIABLE` set); else None."""
    try:
        local_rank = int(environ.get("LOCAL_RANK", "0"))
        pid = int(environ.get(LAUNCHER_VARIABLE, "0"))
    except ValueError:
        return None
    return pid if local_rank > 0 and pid > 0 else None


def _end(why: str) -> None:
    """End this process as the kernel would on the parent's death (SIGKILL where it exists)."""
    log.error("local rank %s: %s: ending", os.environ.get("LOCAL_RANK"), why)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    if hasattr(signal, "SIGKILL"):
        os.kill(os.getpid(), signal.SIGKILL)
    os._exit(128 + 9)


def _set_parent_death_signal(signum: int) -> bool:
    """``prctl(PR_SET_PDEATHSIG, signum)``; whether the kernel accepted it (Linux only)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, signum, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent: int) -> None:
    """The daemon thread's loop where the kernel cannot watch the parent."""
    while os.getppid() == parent:
        time.sleep(POLL_SECONDS)
    if _armed:
        _end(f"the process that started it (pid {parent}) has ended")


def _disarm(by_kernel: bool) -> None:
    """At this process's exit: no signal when the parent ends (its work is done)."""
    global _armed
    _armed = False
    if by_kernel:
        _set_parent_death_signal(0)


def end_with_launcher() -> bool:
    """In a process that Lightning's launcher started: end it when the process that started it
    ends, and at once if that one has ended already (see the module's docstring). Once per
    process; elsewhere nothing. Returns whether it is armed."""
    global _armed
    parent = _launcher_pid(os.environ)
    if parent is None:
        return False
    if _armed:
        return True
    # The parent may end before the death signal is set: then this process has another parent
    # already (init or a subreaper), and no signal will come.
    by_kernel = _set_parent_death_signal(signal.SIGKILL) if hasattr(signal, "SIGKILL") else False
    if os.getppid() != parent:
        _end(f"the process that started it (pid {parent}) has ended")
    # Disarmed at exit: a run's processes end in any order once their work is done, and the
    # first one's normal exit must not turn this one's own exit into a SIGKILL.
    atexit.register(_disarm, by_kernel)
    if not by_kernel:
        threading.Thread(
            target=_watch_parent, args=(parent,), name="mfg-parent-watch", daemon=True
        ).start()
    _armed = True
    log.debug("local rank %s ends with pid %d", os.environ.get("LOCAL_RANK"), parent)
    return True


@contextlib.contextmanager
def launching(starts_processes: bool) -> Iterator[None]:
    """Around a fit or test that may start the other processes (``starts_processes``): this
    process's pid is in :data:`LAUNCHER_VARIABLE` for the processes it starts, which
    :func:`end_with_launcher` reads. A process that was itself started so arms its watch
    instead."""
    if end_with_launcher() or not starts_processes:
        yield
        return
    before = os.environ.get(LAUNCHER_VARIABLE)
    os.environ[LAUNCHER_VARIABLE] = str(os.getpid())
    try:
        yield
    finally:
        # not left for a later, unrelated process of this one (a multirun's next job, a test)
        if before is None:
            os.environ.pop(LAUNCHER_VARIABLE, None)
        else:
            os.environ[LAUNCHER_VARIABLE] = before


def _as_timedelta(value: timedelta | float | int) -> timedelta:
    return value if isinstance(value, timedelta) else timedelta(seconds=float(value))


class StartupDDPStrategy(DDPStrategy):
    """Lightning's DDP strategy whose process group has a shorter timeout while it is formed (see
    the module's docstring).

    Args:
        startup_timeout: seconds (or a ``timedelta``) the processes wait for each other while the
            process group is formed (the rendezvous); None: ``timeout`` throughout.
        timeout: the process group's timeout once it is formed (torch's default, 30 minutes).
        **kwargs: Lightning's ``DDPStrategy`` arguments.
    """

    def __init__(
        self,
        *args: Any,
        startup_timeout: timedelta | float | None = None,
        timeout: timedelta | float = dist.default_pg_timeout,
        **kwargs: Any,
    ) -> None:
        self.run_timeout = _as_timedelta(timeout)
        self.startup_timeout = None if startup_timeout is None else _as_timedelta(startup_timeout)
        if self.startup_timeout is not None and self.startup_timeout <= timedelta(0):
            raise ValueError(f"trainer.strategy.startup_timeout: {startup_timeout} is not > 0")
        super().__init__(*args, timeout=self.startup_timeout or self.run_timeout, **kwargs)

    def setup_environment(self) -> None:
        super().setup_environment()
        if self.startup_timeout is not None and dist.is_available() and dist.is_initialized():
            group = dist.group.WORLD
            if group is not None:
                group.set_timeout(self.run_timeout)
                log.debug("process group formed: timeout %s", self.run_timeout)

    def batch_to_device(
        self, batch: Any, device: Any | None = None, dataloader_idx: int = 0
    ) -> Any:
        """A training batch whose every sample was unreadable (None) goes on as the run's
        stand-in (:meth:`mfg_lightning.run.agreed_steps.AgreedSteps.stand_in`), whose step every
        process then skips: Lightning would skip a None batch on this process alone, and the
        others would wait for it in the step's collectives."""
        from mfg_lightning.run.agreed_steps import AgreedSteps

        trainer = self.lightning_module.trainer
        steps = AgreedSteps.of(trainer)
        if batch is None and trainer.training and steps is not None:
            batch = steps.stand_in()
        return super().batch_to_device(batch, device, dataloader_idx)
