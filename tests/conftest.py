"""Shared test settings: quiet, deterministic, CPU-only, small thread pools."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import torch

os.environ.setdefault("MPLBACKEND", "Agg")
# Two test workers share two cores: one thread each keeps them from fighting.
torch.set_num_threads(1)

# Every test runs on the CPU unless it is about CUDA (marked `cuda`, run in a subprocess with
# cuda_env()): fixtures and entry points leave trainer.accelerator=auto, and several tests expect
# the CPU's exact results, so `make test` must not move them to a GPU where there is one. Hidden
# here, before anything initialises CUDA (importing torch does not), for this process and the
# processes it starts; the machine's own setting is kept for cuda_env() in an environment
# variable, which pytest-xdist's workers inherit along with the hidden one.
_VISIBLE_KEPT = "MFG_TESTS_CUDA_VISIBLE_DEVICES"
_UNSET = "<unset>"
os.environ.setdefault(_VISIBLE_KEPT, os.environ.get("CUDA_VISIBLE_DEVICES", _UNSET))
os.environ["CUDA_VISIBLE_DEVICES"] = ""


def cuda_env(**extra: str) -> dict[str, str]:
    """The environment for a subprocess of a test about CUDA: the machine's GPUs visible again
    (as they were before the tests hid them), plus ``extra``."""
    env = dict(os.environ, **extra)
    kept = env.pop(_VISIBLE_KEPT, _UNSET)
    if kept == _UNSET:
        env.pop("CUDA_VISIBLE_DEVICES", None)
    else:
        env["CUDA_VISIBLE_DEVICES"] = kept
    return env


@pytest.fixture(autouse=True)
def _seed_global_generators() -> None:
    """Every test starts from the same global random state, whichever worker runs it and in
    whatever order, so a test that draws unseeded random numbers still sees the same ones."""
    import random

    import numpy as np

    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)


@pytest.fixture(autouse=True, scope="session")
def _session_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """``paths.cache_dir`` of every test that names none (and of the processes it starts): a
    directory of the session's, so that the flow and sample caches a test fills never land in
    the user's ``~/.cache/mfg_lightning``."""
    with pytest.MonkeyPatch.context() as patch:
        path = tmp_path_factory.mktemp("cache")
        patch.setenv("MFG_CACHE_DIR", str(path))
        yield path


REPO = Path(__file__).resolve().parents[1]
# ../shared beside the checkout; MFG_SHARED_DIR points elsewhere (a git worktree, a CI cache).
SHARED = Path(os.environ.get("MFG_SHARED_DIR", REPO.parent / "shared"))
#: KITTI's real ground-truth poses in the shared data; a test about real poses skips without
#: them, saying where it looked (:data:`NO_KITTI_POSES`), and never falls back to synthetic ones.
KITTI_POSES = SHARED / "data" / "kitti_odometry" / "poses"
NO_KITTI_POSES = f"{KITTI_POSES} not present (MFG_SHARED_DIR names the shared data's folder)"

# A user's conf/local/default.yaml (git-ignored: this machine's data directory, trainer...) is
# composed by every entry point. The tests see only what they set up: no local file, in this
# process and the entry points it starts (conf/*.yaml: optional local: ${oc.env:MFG_LOCAL_CONFIG}).
os.environ["MFG_LOCAL_CONFIG"] = "none"


#: Overrides of a seconds-long real training on a small dataset (two steps, one validation and
#: one test batch, no logger or callbacks): the end-to-end tests of each dataset add theirs.
TINY_TRAINING = (
    "dataset.batch_size=2", "dataset.eval_batch_size=4", "model.net.hidden_units=64",
    "model.net.channels=[8,8,16,16,32]", "trainer.max_steps=2", "trainer.val_check_interval=1",
    "trainer.limit_val_batches=1", "trainer.limit_test_batches=1", "logger=none",
    "callbacks=none",
)  # fmt: skip


def run_command(
    command: list[str], *, cwd: Path, env: dict[str, str] | None = None, timeout: int
) -> subprocess.CompletedProcess[str]:
    """Run ``command`` in a subprocess and return what it did: its exit status and its output
    as text, whatever the status (the caller says what a failure means)."""
    return subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )


def run_make(*args: str, cwd: Path = REPO, env: dict[str, str] | None = None, timeout: int = 60):
    """``make args`` in ``cwd`` (the repository by default), through :func:`run_command`; the
    test is skipped where make is not installed."""
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    return run_command(["make", "--no-print-directory", *args], cwd=cwd, env=env, timeout=timeout)


def entry_point_env(cwd: Path, **extra: str) -> dict[str, str]:
    """The environment of an entry point run by a test: one thread per process (tests run in
    parallel), Hydra's short errors, a flow cache under ``cwd``, and ``extra``."""
    return dict(
        os.environ,
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
        HYDRA_FULL_ERROR="0",
        MFG_CACHE_DIR=str(cwd / "cache"),
        **extra,
    )


def run_module(module: str, *args: str, cwd: Path, timeout: int = 300, check: bool = True):
    """Run ``python -m module args`` in a subprocess (a real entry point, as a user would)."""
    env = entry_point_env(cwd)
    proc = run_command([sys.executable, "-m", module, *args], cwd=cwd, env=env, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(
            f"{module} {' '.join(args)} failed ({proc.returncode}):\n"
            f"{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
        )
    return proc


def quiet_trainer(**options: Any):
    """An in-process ``lightning.Trainer`` on the CPU that writes and prints nothing of its own
    (no logger, checkpoints, progress bar or model summary); ``options`` are the test's own
    settings. Like a run's trainer (conf/callbacks), it has the run's
    :class:`~mfg_lightning.run.agreed_steps.AgreedSteps` unless ``callbacks`` bring one."""
    import lightning as L

    from mfg_lightning.run.agreed_steps import AgreedSteps

    callbacks = list(options.pop("callbacks", []))
    if not any(isinstance(cb, AgreedSteps) for cb in callbacks):
        callbacks.append(AgreedSteps())
    options["callbacks"] = callbacks
    quiet = dict(
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    return L.Trainer(**{**quiet, **options})


def tiny_training(tmp_path: Path, *overrides: str) -> Path:
    """Run ``mfg_lightning.train`` with ``overrides`` and :data:`TINY_TRAINING` into
    ``<tmp_path>/run`` (the flow cache in ``<tmp_path>/cache``) and return that run directory."""
    run = tmp_path / "run"
    run_module(
        "mfg_lightning.train", *overrides, *TINY_TRAINING, f"hydra.run.dir={run}", cwd=tmp_path
    )
    return run


def dataset_training(tmp_path: Path, dataset: str, data_root: Path, *overrides: str) -> Path:
    """A dataset's end-to-end test: :func:`tiny_training` on ``dataset=<dataset>`` read from
    ``data_root``, with ``overrides``; checks that the run wrote its metrics and returns its
    directory."""
    run = tiny_training(
        tmp_path, f"dataset={dataset}", f"dataset.data_root={data_root}", *overrides
    )
    assert (run / "metrics.json").is_file()
    return run


def bench_module(name: str) -> ModuleType:
    """``bench/<name>.py`` imported as a module (bench/ is not a package), its own imports of
    ``bench/_common.py`` included."""
    import importlib.util

    bench = REPO / "bench"
    if str(bench) not in sys.path:
        sys.path.insert(0, str(bench))
    spec = importlib.util.spec_from_file_location(f"bench_{name}", bench / f"{name}.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def shared_poses() -> Path:
    poses = KITTI_POSES
    if not poses.is_dir():
        pytest.skip(NO_KITTI_POSES)
    return poses


@pytest.fixture
def threads_kept():
    """A benchmark script sets this process's torch and OpenCV threads: put back after the
    test."""
    import cv2
    import torch

    threads = torch.get_num_threads(), cv2.getNumThreads()
    yield
    torch.set_num_threads(threads[0])
    cv2.setNumThreads(threads[1])
