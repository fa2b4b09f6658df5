"""Errors a user can act on: a Hydra entry point's command line checked before anything runs
(one ``error:`` line naming the closest keys, exit status 2, nothing written), whole-number
floats for integer settings, each entry point's own ``--help``, and what a failed run leaves
(nothing, or a ``FAILED`` marker, its log holding the error, no empty event files)."""

from __future__ import annotations

import importlib
import inspect
import logging
from pathlib import Path

import pytest

from conftest import run_module
from mfg_lightning.core.command_line import (
    _compose,
    _container,
    check_command_line,
    closest_keys,
    config_keys,
    help_text,
)
from mfg_lightning.core.failed_runs import (
    FAILED,
    event_count,
    is_failed,
    newest_run,
    remove_empty_event_files,
    settle_failed_run,
)

#: Every Hydra entry point → its config.
ENTRY_POINTS = {
    "mfg_lightning.train": "train",
    "mfg_lightning.evaluate": "evaluate",
    "mfg_lightning.predict": "predict",
    "mfg_lightning.reproduce": "reproduce",
    "mfg_lightning.analyze_basis": "analyze_basis",
    "mfg_lightning.data.check": "check",
    "mfg_lightning.data.export": "export",
}


@pytest.mark.parametrize("module", list(ENTRY_POINTS))
def test_every_entry_point_checks_its_own_config(module: str) -> None:
    """The check reads the config name from the @hydra.main inside the decorator, and a
    misspelt key of that config is one line naming the key it has."""
    main = importlib.import_module(module).main
    name = inspect.getclosurevars(main.__wrapped__).nonlocals["config_name"]
    assert name == ENTRY_POINTS[module]
    given = ["dataset=synthetic"] if name == "predict" else []  # predict names its dataset
    keys = [k for k, _ in config_keys(_container(_compose(name, given)))]
    key = next(k for k in keys if k.count(".") >= 1 and not k.startswith("hydra"))
    typo = key[:-1]  # the last letter left out
    result = check_command_line(name, [*given, f"{typo}=1"], module)
    assert result.error is not None and result.error.startswith(f"{typo}=1: the config has no ")
    assert f"did you mean {key}" in result.error and "\n" not in result.error


def test_a_misspelt_key_names_the_key_it_meant() -> None:
    result = check_command_line("train", ["model.loss.ws=100"], "mfg_lightning.train")
    assert result.error == (
        "model.loss.ws=100: the config has no key model.loss.ws; did you mean model.loss.w_s?"
    )
    assert closest_keys("trainer.max_stepz", ["trainer.max_steps", "trainer.max_epochs"]) == [
        "trainer.max_steps"
    ]
    assert closest_keys("zzz", ["trainer.max_steps"]) == []


def test_whole_number_floats_are_integers_and_fractions_are_refused() -> None:
    ok = check_command_line("train", ["trainer.max_steps=1e3", "seed=3"], "mfg_lightning.train")
    assert ok.error is None and ok.argv == ["trainer.max_steps=1000", "seed=3"]
    bad = check_command_line("train", ["trainer.max_steps=2.5"], "mfg_lightning.train")
    assert bad.error.startswith("trainer.max_steps=2.5: trainer.max_steps is a whole number")
    # A float setting keeps its float, and so does a Lightning fraction-or-count (1.0: a whole
    # epoch, not one batch).
    argv = ["model.optimizer.lr=1e-3", "trainer.val_check_interval=1.0"]
    kept = check_command_line("train", argv, "mfg_lightning.train")
    assert kept.error is None and kept.argv == argv


def test_a_mandatory_key_left_unset_says_what_to_type() -> None:
    result = check_command_line("evaluate", [], "mfg_lightning.evaluate")
    assert result.error == (
        "ckpt_path is not set; type: python -m mfg_lightning.evaluate ckpt_path=<path> [...]"
    )
    assert check_command_line("evaluate", ["ckpt_path=x.ckpt"], "m").error is None


def test_sweeps_need_multirun_and_existing_keys() -> None:
    module = "mfg_lightning.train"
    assert check_command_line("train", ["-m", "model.loss.w_s=0,10"], module).error is None
    no_m = check_command_line("train", ["model.loss.w_s=0,10"], module).error
    assert no_m.startswith("model.loss.w_s=0,10: a sweep needs -m")
    typo = check_command_line("train", ["-m", "model.loss.ws=0,10"], module).error
    assert typo.endswith("did you mean model.loss.w_s?")


def test_each_entry_point_has_its_own_help() -> None:
    import mfg_lightning.evaluate as evaluate
    import mfg_lightning.train as train

    texts = {
        name: help_text(name, module.__name__, module.__doc__)
        for name, module in (("train", train), ("evaluate", evaluate))
    }
    assert texts["train"].startswith("Train MFG") and texts["evaluate"].startswith("Evaluate")
    assert "python -m mfg_lightning.evaluate" in texts["evaluate"]
    groups = {line.split(":")[0].strip() for line in texts["train"].splitlines() if ": " in line}
    assert {"dataset", "model", "trainer"} <= groups
    assert not {"layout", "reproduce"} & groups  # groups train does not take
    assert check_command_line("train", ["--help"], "mfg_lightning.train").help is not None


def test_a_misspelt_key_on_the_command_line_writes_nothing(tmp_path: Path) -> None:
    proc = run_module("mfg_lightning.train", "model.loss.ws=100", cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert proc.stderr == (
        "error: model.loss.ws=100: the config has no key model.loss.ws; "
        "did you mean model.loss.w_s?\n"
    )
    assert not any(p for p in tmp_path.iterdir() if p.name != "cache")


def test_a_run_that_fails_on_its_data_leaves_nothing(tmp_path: Path) -> None:
    """The run directory Hydra made is removed when the data are refused before any work."""
    proc = run_module(
        "mfg_lightning.train", "dataset=kitti", f"dataset.data_root={tmp_path / 'nope'}",
        "paths.log_dir=runs", cwd=tmp_path, check=False,
    )  # fmt: skip
    assert proc.returncode == 2 and proc.stderr.count("error: ") == 1, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert not list((tmp_path / "runs").rglob("*"))  # the log directory alone stays


# ------------------------------------------------------------------------------------------------
# What a failed run leaves
# ------------------------------------------------------------------------------------------------


def _event_file(folder: Path, scalars: int) -> Path:
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(folder))
    for step in range(scalars):
        writer.add_scalar("loss", 1.0 / (step + 1), step)
    writer.close()
    (path,) = folder.glob("events.out.tfevents.*")
    return path


def test_event_files_without_events_are_removed(tmp_path: Path) -> None:
    empty = _event_file(tmp_path / "run" / "tensorboard" / "a", 0)
    full = _event_file(tmp_path / "run" / "tensorboard" / "b", 3)
    assert event_count(empty) == 1 and event_count(full) == 4
    assert remove_empty_event_files(tmp_path / "run") == [empty]
    assert full.exists() and not empty.parent.exists()


@pytest.fixture
def log_file(tmp_path: Path):
    """A run directory with its log file attached to the root logger, as Hydra's job has."""
    run = tmp_path / "outputs" / "train" / "runs" / "2026"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("seed: 0\n")
    handler = logging.FileHandler(run / "train.log")
    logging.getLogger().addHandler(handler)
    yield run
    logging.getLogger().removeHandler(handler)
    handler.close()


def test_a_user_error_before_any_work_removes_the_run(log_file: Path, monkeypatch) -> None:
    monkeypatch.chdir(log_file.parents[3])
    settle_failed_run(log_file, "error: no data", ValueError("no data"), user=True)
    assert not (log_file.parents[3] / "outputs" / "train").exists()
    assert (log_file.parents[3] / "outputs").is_dir()  # the log directory stays


def test_a_failure_after_work_marks_the_run(log_file: Path, monkeypatch) -> None:
    monkeypatch.chdir(log_file.parents[3])
    (log_file / "checkpoints").mkdir()
    (log_file / "checkpoints" / "last.ckpt").write_bytes(b"x")
    _event_file(log_file / "tensorboard", 0)
    err = RuntimeError("CUDA out of memory")
    settle_failed_run(log_file, "RuntimeError: CUDA out of memory", err, user=False)
    assert (log_file / FAILED).read_text() == "RuntimeError: CUDA out of memory\n"
    assert is_failed(log_file) and not (log_file / "tensorboard").exists()
    log = (log_file / "train.log").read_text()
    assert "RuntimeError: CUDA out of memory" in log  # the error is in the run's own log
    # A multirun job is kept (the report reads its log) even after a user error.
    job = log_file.parent / "job"
    job.mkdir()
    settle_failed_run(job, "error: bad", ValueError("bad"), user=True, keep=True)
    assert is_failed(job)


def test_newest_run_skips_failed_runs(tmp_path: Path) -> None:
    import os

    runs = [tmp_path / name for name in ("a", "b", "c")]
    for i, run in enumerate(runs):
        run.mkdir()
        os.utime(run, (1000 + i, 1000 + i))
    (runs[2] / FAILED).write_text("error: x\n")
    os.utime(runs[2], (2000, 2000))
    assert newest_run(runs) == runs[1]
    assert newest_run([runs[2]]) is None
