"""The start-up window of a data-parallel run (mfg_lightning.run.startup): a process started by
the first process of ``trainer=ddp`` ends with it, from its first second, and the process group
has a shorter timeout while it is formed.

Before, SIGTERM or SIGKILL to the first process before Lightning had installed its handlers left
the second one waiting in the rendezvous until the process group's timeout (30 minutes; it was
still alive after 560 s).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest

from conftest import entry_point_env
from mfg_lightning.run.startup import LAUNCHER_VARIABLE, StartupDDPStrategy

#: seconds within which the second process must be gone once the first is killed
GONE_BOUND = 30.0

linux_only = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _child_of(parent: int, local_rank: int) -> int | None:
    """The pid of the process ``parent`` started with ``LOCAL_RANK=<local_rank>`` (None: none)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if ppid != parent:
                continue
            environ = (entry / "environ").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if f"LOCAL_RANK={local_rank}".encode() in environ:
            return int(entry.name)
    return None


def _wait_gone(pid: int, bound: float) -> float:
    """Seconds until ``pid`` no longer runs; fails past ``bound``."""
    start = time.monotonic()
    while _alive(pid):
        if time.monotonic() - start > bound:
            os.kill(pid, signal.SIGKILL)
            raise AssertionError(f"pid {pid} still alive {bound:.0f} s after its parent ended")
        time.sleep(0.05)
    return time.monotonic() - start


# A launcher (a parent whose pid the child has in MFG_DDP_LAUNCHER_PID) and its child, which
# arms the watch after `delay` seconds, then waits as a process in a rendezvous would.
_FAMILY = textwrap.dedent(
    """
    import os, subprocess, sys, time
    if os.environ.get("LOCAL_RANK") == "1":
        time.sleep(float(sys.argv[1]))
        from mfg_lightning.run.startup import end_with_launcher
        print("armed" if end_with_launcher() else "not armed", flush=True)
        time.sleep(120)
    else:
        env = dict(os.environ, LOCAL_RANK="1", {var}=str(os.getpid()))
        subprocess.Popen([sys.executable, *sys.argv], env=env)
        time.sleep(120)
    """
).format(var=LAUNCHER_VARIABLE)


@linux_only
@pytest.mark.parametrize("armed_first", [True, False], ids=["armed", "parent_gone_first"])
def test_a_started_process_ends_with_the_process_that_started_it(
    tmp_path: Path, armed_first: bool
) -> None:
    script = tmp_path / "family.py"
    script.write_text(_FAMILY)
    # armed: the parent is killed once the child armed its watch (the kernel's death signal);
    # parent_gone_first: before the child looks (it ends at once when it does)
    delay = "0" if armed_first else "3"
    parent = subprocess.Popen(
        [sys.executable, str(script), delay], stdout=subprocess.PIPE, text=True,
        env=entry_point_env(tmp_path), start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while (child := _child_of(parent.pid, 1)) is None:
            assert time.monotonic() < deadline and parent.poll() is None, "no child started"
            time.sleep(0.02)
        if armed_first:
            assert parent.stdout is not None
            assert parent.stdout.readline().strip() == "armed"
        parent.kill()
        parent.wait()
        seconds = _wait_gone(child, GONE_BOUND)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(parent.pid, signal.SIGKILL)  # its own session: the family only
    print(f"child gone {seconds:.1f} s after its parent was killed")
    assert seconds < GONE_BOUND


def test_nothing_is_armed_outside_a_launched_process(monkeypatch: pytest.MonkeyPatch) -> None:
    from mfg_lightning.run import startup

    monkeypatch.setattr(startup, "_armed", False)
    monkeypatch.delenv(LAUNCHER_VARIABLE, raising=False)
    monkeypatch.setenv("LOCAL_RANK", "1")  # torchrun's worker: its agent ends it
    assert startup.end_with_launcher() is False
    monkeypatch.setenv(LAUNCHER_VARIABLE, str(os.getppid()))
    monkeypatch.setenv("LOCAL_RANK", "0")  # the first process itself
    assert startup.end_with_launcher() is False
    with startup.launching(starts_processes=True):
        assert os.environ[LAUNCHER_VARIABLE] == str(os.getpid())
    assert os.environ[LAUNCHER_VARIABLE] == str(os.getppid())  # put back


def test_the_process_group_has_the_startup_timeout_until_it_is_formed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import torch.distributed as dist
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    cfg = compose("train", ["debug=tiny", "trainer=ddp", "logger=none"])
    strategy = instantiate(cfg.trainer.strategy)
    assert isinstance(strategy, StartupDDPStrategy)
    assert strategy.startup_timeout == timedelta(minutes=5)
    assert strategy.run_timeout == dist.default_pg_timeout  # torch's 30 minutes once formed
    with pytest.raises(ValueError, match="startup_timeout"):
        StartupDDPStrategy(startup_timeout=0)

    # A real one-process gloo group: formed with the start-up timeout, then set to the run's.
    import lightning as L

    given: list[timedelta] = []
    monkeypatch.setattr(
        dist.ProcessGroup, "set_timeout", lambda self, timeout: given.append(timeout)
    )
    monkeypatch.setenv("MASTER_PORT", "29517")
    monkeypatch.setattr(dist, "init_process_group", _recording_init(dist.init_process_group, given))
    ddp = StartupDDPStrategy(startup_timeout=20, timeout=timedelta(minutes=7))
    trainer = L.Trainer(accelerator="cpu", devices=1, strategy=ddp, logger=False)
    try:
        trainer.strategy.setup_environment()
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
    assert given == [timedelta(seconds=20), timedelta(minutes=7)]


def _recording_init(init: Callable[..., Any], given: list[timedelta]) -> Callable[..., Any]:
    """``init_process_group`` recording the timeout it is given in ``given``."""

    def record(*args: Any, **kwargs: Any) -> Any:
        given.append(kwargs["timeout"])
        return init(*args, **kwargs)

    return record


@linux_only
@pytest.mark.slow
def test_killing_the_first_process_in_the_startup_window_ends_the_second_within_seconds(
    tmp_path: Path,
) -> None:
    # trainer=ddp: Lightning starts the second process from the first at the start of fit; the
    # first is killed (SIGKILL) as soon as the second exists, long before either has formed the
    # process group or installed a handler.
    args = [
        "debug=tiny", "trainer=ddp", "trainer.max_steps=4", "logger=none",
        "callbacks.rich_progress_bar=null", "+trainer.enable_progress_bar=false",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]  # fmt: skip
    first = subprocess.Popen(
        [sys.executable, "-m", "mfg_lightning.train", *args], cwd=tmp_path,
        env=entry_point_env(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while (second := _child_of(first.pid, 1)) is None:
            if first.poll() is not None or time.monotonic() > deadline:
                out, _ = first.communicate()
                raise AssertionError(f"the second process never started:\n{out[-5000:]}")
            time.sleep(0.02)
        first.kill()
        seconds = _wait_gone(second, GONE_BOUND)
        # its output (shared with the first) closes when it ends
        output, _ = first.communicate(timeout=GONE_BOUND)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(first.pid, signal.SIGKILL)  # its own session: the run's processes only
    print(f"the second process was gone {seconds:.1f} s after the first was killed")
    assert seconds < GONE_BOUND, output[-5000:]
    assert "has ended: ending" in output, output[-5000:]
