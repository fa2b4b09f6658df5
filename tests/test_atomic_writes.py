"""Checkpoint and cache files survive kills and full disks: a kill during a checkpoint write
leaves the previous file loadable; a run whose disk fills up fails with one clear line and
leaves its previous checkpoint loadable; runs sharing the flow cache never read a partial
entry."""

from __future__ import annotations

import errno
import multiprocessing as mp
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from mfg_lightning.data.kitti import FlowCache
from mfg_lightning.run.callbacks import AtomicCheckpointIO, StorageError, storage_error
from resume_runs import RUN, _env, _train

pytestmark = pytest.mark.slow


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
        "+callbacks.fill._target_=resume_runs.FillDisk",
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
