"""A GPU user's first run, tested on a CPU: ``make gpu-check``, no collective or host copy per
step that a tensor op avoids, and the test suite itself pinned to the CPU. The install is tested
in test_gpu_install.py, ``last.ckpt`` by wall time in test_last_checkpoint.py.
"""

from __future__ import annotations

import contextlib
import glob
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

from conftest import REPO, bench_module, cuda_env, quiet_trainer, run_make
from mfg_lightning.metrics.frame_errors import FiniteMean
from mfg_lightning.models.mfg import bilinear_matrix

BENCH = REPO / "bench"
TESTS = Path(__file__).resolve().parent


# --------------------------------------------------------------------------------------------
# make gpu-check
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_make_gpu_check_runs_every_part_on_a_cpu(tmp_path: Path) -> None:
    """``make gpu-check`` in its tiny setting on the CPU (seconds, numbers meaningless), with a
    precision list without ``32-true`` (it saved no checkpoint for Part 3 before)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MFG_CACHE_DIR=str(tmp_path))
    env["PYTHON"] = sys.executable
    args = f"--tiny --precisions bf16-mixed --out {tmp_path}"
    proc = run_make(
        "gpu-check",
        f"PYTHON={sys.executable}",
        "GPU_CHECK_ACCELERATOR=cpu",
        f"GPU_CHECK_ARGS={args}",
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, f"{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    assert "install-gpu" not in proc.stdout  # no install on the CPU
    text = (tmp_path / "gpu_check.md").read_text()
    for needle in (
        "## Preparation",
        "CUBLAS_WORKSPACE_CONFIG=:4096:8",
        "/dev/shm",
        "## Training (quick start)",
        "samples/s, cached batches (device side)",
        "samples/s, loader alone",
        "## Determinism",
        "## One checkpoint on the CPU and on the device",
        "checkpoint of the `bf16-mixed` run",
        "3x the first GPU run's largest difference",
        "## Environment",
    ):
        assert needle in text, needle
    assert "| no |" not in text  # bit-identical, and every metric within its tolerance
    # Part 2 turned deterministic algorithms on; Part 3 started with them off again.
    flags = text.split("## torch's settings at the start of each part", 1)[1]
    part3 = next(ln for ln in flags.splitlines() if ln.startswith("| Part 3"))
    assert part3.split("|")[2].strip() == "off"
    assert not torch.are_deterministic_algorithms_enabled()


def test_gpu_check_fits_the_loader_workers_to_dev_shm(tmp_path: Path, monkeypatch) -> None:
    from mfg_lightning.data.workers import plan_workers

    gpu_check = bench_module("gpu_check")
    kb = 154 * 1024  # one sample of the quick start
    roomy = plan_workers(6, 16, 64, kb, tmp_path)
    assert roomy.workers == 6 and roomy.enough and "enough" in roomy.note
    Usage = type(shutil.disk_usage(tmp_path))
    monkeypatch.setattr(shutil, "disk_usage", lambda _: Usage(64 << 20, 0, 64 << 20))
    small = plan_workers(6, 16, 64, kb, Path("/dev/shm"))  # Docker's default 64 MB
    assert 0 <= small.workers < 6 and not small.enough
    assert f"dataset.num_workers={small.workers}" in small.note and "--shm-size=" in small.note
    assert plan_workers(0, 16, 64, kb, Path("/dev/shm")).workers == 0
    # Lightning's precision aliases are accepted, anything else refused before any work.
    assert gpu_check.parse_args(["--precisions", "bf16", "32"]).precisions == [
        "bf16-mixed",
        "32-true",
    ]
    with pytest.raises(SystemExit):
        gpu_check.parse_args(["--precisions", "bf16-true"])


@pytest.mark.cuda
@pytest.mark.slow
def test_make_gpu_check_tiny_on_the_gpu(tmp_path: Path) -> None:
    """On a machine with a GPU: the same check on it, tiny (the GPUs visible again)."""
    if not glob.glob("/dev/nvidia[0-9]*") or os.environ.get("MFG_TESTS_CUDA_VISIBLE_DEVICES") in (
        "",
        "-1",
    ):
        pytest.skip("no NVIDIA GPU on this machine")
    env = cuda_env(OMP_NUM_THREADS="1", MFG_CACHE_DIR=str(tmp_path))
    command = [sys.executable, str(BENCH / "gpu_check.py"), "--tiny", "--out", str(tmp_path)]
    proc = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    if "no CUDA device here" in proc.stderr:
        pytest.skip("torch sees no GPU here: `make install-gpu` says why")
    assert proc.returncode == 0, f"{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    assert "| no |" not in (tmp_path / "gpu_check.md").read_text()


# --------------------------------------------------------------------------------------------
# No collective or host copy per step that a tensor op avoids
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def no_tensor_from_host_values() -> Iterator[None]:
    """The project's code may not build a tensor on a device from Python values: on a GPU that
    is a synchronous host-to-device copy (``torch.tensor(4, device=...)``); a fill
    (``torch.full``) or a tensor-scalar op passes the value as a kernel argument instead."""
    names = ("tensor", "as_tensor", "scalar_tensor")
    saved = {name: getattr(torch, name) for name in names}

    def guarded(name: str):
        original = saved[name]

        def build(data: Any, *args: Any, **kwargs: Any):
            caller = traceback.extract_stack(limit=2)[0].filename
            if (
                kwargs.get("device") is not None
                and not isinstance(data, torch.Tensor)
                and "mfg_lightning" in caller
            ):
                raise AssertionError(f"torch.{name}({data!r}, device=...) in {caller}")
            return original(data, *args, **kwargs)

        return build

    for name in names:
        setattr(torch, name, guarded(name))
    try:
        yield
    finally:
        for name, original in saved.items():
            setattr(torch, name, original)


def test_the_guard_catches_a_tensor_built_from_a_host_value() -> None:
    with no_tensor_from_host_values(), pytest.raises(AssertionError, match="torch.as_tensor"):
        # the code FiniteMean.update had: an int batch size as a weight
        exec(  # run as if from the package, where the guard looks
            compile("torch.as_tensor(4, device='cpu')", "mfg_lightning/x.py", "exec"),
            {"torch": torch},
        )


def test_batch_sizes_and_upsampling_matrices_need_no_host_to_device_copy() -> None:
    values = torch.rand(5, dtype=torch.float64)
    with no_tensor_from_host_values():
        metric = FiniteMean()
        metric.update(values, weight=4)  # the batch size, as the module gives it
        metric.update(torch.tensor([float("nan"), 2.0]), weight=torch.tensor(3.0))
        metric.update(1.5)
        for align in (True, False):
            bilinear_matrix(24, 48, align, torch.device("cpu"))
    assert metric.compute().item() == pytest.approx((4 * values.sum().item() + 6 + 1.5) / 24)
    assert int(metric.nan_count) == 1


def test_training_and_evaluation_steps_build_no_tensor_from_a_host_value() -> None:
    from test_precision import _dm, _module

    model = _module()
    for name in ("training_step", "validation_step"):
        step = getattr(model, name)

        def guarded(*args: Any, _step: Any = step, **kwargs: Any):
            with no_tensor_from_host_values():
                return _step(*args, **kwargs)

        setattr(model, name, guarded)
    trainer = quiet_trainer(max_steps=2, limit_val_batches=2, val_check_interval=2)
    trainer.fit(model, datamodule=_dm())
    assert math.isfinite(float(trainer.callback_metrics["val/trans_err"]))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_gloo_processes_with_fewer_test_samples_than_processes(tmp_path: Path) -> None:
    """Two processes started as torchrun starts them (tests/ddp_worker.py): training has no
    barrier and one all_reduce per step inside the training step, both skip the step whose
    loss is NaN on one of them, and testing on one sample (rank 1 sees none) finishes with the
    metrics one process computes on the same weights."""
    port = str(_free_port())
    procs = []
    for rank in range(2):
        env = dict(
            os.environ,
            RANK=str(rank),
            LOCAL_RANK=str(rank),
            WORLD_SIZE="2",
            NODE_RANK="0",
            MASTER_ADDR="127.0.0.1",
            MASTER_PORT=port,
            OMP_NUM_THREADS="1",
            PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
        )
        log = (tmp_path / f"rank{rank}.log").open("w")
        command = [sys.executable, str(TESTS / "ddp_worker.py"), str(tmp_path)]
        procs.append(subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT))
    try:
        codes = [p.wait(timeout=240) for p in procs]
    finally:
        for p in procs:  # a hang is a failure, not a stuck test run
            if p.poll() is None:
                p.kill()
    logs = "\n".join((tmp_path / f"rank{r}.log").read_text()[-3000:] for r in range(2))
    assert codes == [0, 0], logs
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    for result in ranks:
        assert result["calls"]["barrier"] == [0, 0, 0]
        assert result["calls"]["all_reduce"] == [1, 1, 1]  # the non-finite flag, nothing else
        assert result["skipped_steps"] == 1  # rank 1's NaN step, skipped on both
    assert ranks[0]["metrics"] == ranks[1]["metrics"]

    from ddp_worker import datamodule, module

    model = module(rank=0)
    state = torch.load(tmp_path / "ddp.ckpt", map_location="cpu", weights_only=True)
    model.load_state_dict(state["state_dict"])
    trainer = quiet_trainer()
    trainer.test(model, datamodule=datamodule(), verbose=False)
    single = {
        k: None if math.isnan(float(v)) else float(v)
        for k, v in trainer.callback_metrics.items()
        if k.startswith("test/")
    }
    ddp = ranks[0]["metrics"]
    assert set(ddp) == set(single)
    for key in ("test/trans_err", "test/rot_err", "test/loss", "test/baseline_trans_err"):
        assert single[key] is not None, key
    differ = {
        k: (ddp[k], single[k])
        for k in single
        if (ddp[k] is None) != (single[k] is None)
        or (single[k] is not None and not math.isclose(ddp[k], single[k], rel_tol=1e-6))
    }
    assert not differ, differ


# --------------------------------------------------------------------------------------------
# The suite on the CPU
# --------------------------------------------------------------------------------------------


def test_the_tests_run_on_the_cpu_whatever_the_machine_has() -> None:
    assert os.environ["CUDA_VISIBLE_DEVICES"] == ""
    assert not torch.cuda.is_available()
    assert quiet_trainer().accelerator.__class__.__name__ == "CPUAccelerator"
    # An entry point started by a test inherits the hidden GPUs; a test about CUDA gets them.
    kept = os.environ["MFG_TESTS_CUDA_VISIBLE_DEVICES"]  # the machine's own setting
    assert cuda_env().get("CUDA_VISIBLE_DEVICES", "<unset>") == kept
    assert "MFG_TESTS_CUDA_VISIBLE_DEVICES" not in cuda_env()


def test_a_datamodule_runs_the_loader_workers_that_dev_shm_holds(monkeypatch, caplog) -> None:
    import logging

    from mfg_lightning.core.machine import loader_workers
    from mfg_lightning.data import base
    from module_helpers import small_datamodule

    Usage = type(shutil.disk_usage("/"))
    free = {"bytes": 1 << 40}
    monkeypatch.setattr(shutil, "disk_usage", lambda _: Usage(free["bytes"], 0, free["bytes"]))
    monkeypatch.setattr(base, "SHM", Path("/"))  # a directory on every system the tests run on

    roomy = small_datamodule(num_workers=2)
    assert roomy.val_dataloader().num_workers == 2
    free["bytes"] = 1 << 20  # 1 MB: room for no worker's batches
    small = small_datamodule(num_workers=2, persistent_workers=True)
    with caplog.at_level(logging.WARNING, logger="mfg_lightning.data.base"):
        loader = small.val_dataloader()
    assert loader.num_workers == 0 and not loader.persistent_workers
    assert "too small for 2 loader workers" in caplog.text and "--shm-size=" in caplog.text
    # the workers follow the cores: one core each for the processes, the rest for workers
    monkeypatch.setattr("mfg_lightning.core.machine.usable_cores", lambda: 16)
    assert loader_workers(6) == 6 and loader_workers(6, 4) == 3 and loader_workers(6, 16) == 0
    assert loader_workers(6, [0, 1]) == 6 and loader_workers(6, "0,1,2,3") == 3
    monkeypatch.setenv("SLURM_PROCID", "3")  # a task srun started: its cores are its own
    assert loader_workers(6, 4) == 6
    monkeypatch.delenv("SLURM_PROCID")
    monkeypatch.setattr("mfg_lightning.core.machine.usable_cores", lambda: 2)
    assert loader_workers(6) == 1 and loader_workers(6, "auto") == 1
    # the node's training processes share /dev/shm
    from mfg_lightning.data.workers import plan_workers

    free["bytes"] = 256 << 20  # 6 workers keep ~144 MB in flight, x1.5 headroom
    kb = 154 * 1024
    assert plan_workers(6, 16, 64, kb, Path("/"), processes=1).workers == 6
    assert plan_workers(6, 16, 64, kb, Path("/"), processes=4).workers < 6
