"""Errors a user can act on: a Hydra entry point's command line checked before anything runs
(one ``error:`` line naming the closest keys, exit status 2, nothing written), whole-number
floats for integer settings, each entry point's own ``--help``, and what a failed run leaves
(nothing, or a ``FAILED`` marker, its log holding the error, no empty event files)."""

from __future__ import annotations

import importlib
import inspect
import logging
import os
import re
from pathlib import Path

import pytest

from conftest import run_module
from mfg_lightning.core.command_line import (
    _compose,
    _container,
    _locate,
    _parameters,
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


def test_a_value_of_the_wrong_type_names_the_key_what_it_got_and_what_it_takes() -> None:
    """Refused before Hydra runs (it said ``'<=' not supported between 'str' and 'int'`` in five
    lines, or ``invalid literal for int()`` without the key, and left a FAILED run)."""
    module = "mfg_lightning.train"
    refused = {
        "dataset.batch_size=abc": "dataset.batch_size=abc: dataset.batch_size takes a whole "
        "number (default 16); got 'abc', a string",
        "seed=abc": "seed=abc: seed takes a whole number (default 0); got 'abc', a string",
        "model.optimizer.lr=fast": "model.optimizer.lr=fast: model.optimizer.lr takes a number "
        "(default 0.001); got 'fast', a string",
        "keep_freed_memory=3": "keep_freed_memory=3: keep_freed_memory takes true or false "
        "(default True); got 3, a whole number",
    }
    for arg, message in refused.items():
        assert check_command_line("train", [arg], module).error == message
    # each value of a sweep too
    swept = check_command_line("train", ["-m", "dataset.batch_size=8,abc"], module).error
    assert swept == ("dataset.batch_size=8,abc: dataset.batch_size takes a whole number "
                     "(default 16); got 'abc', a string")  # fmt: skip
    assert check_command_line("train", ["-m", "dataset.batch_size=8,16"], module).error is None
    # What a setting's parameter takes wins over its default's type: Lightning's devices and
    # precision take strings, a float setting an integer, any setting null or an interpolation.
    for arg in ("trainer.devices=auto", "trainer.precision=bf16-mixed", "model.optimizer.lr=1",
                "trainer.max_epochs=null", "dataset.batch_size=${seed}",
                "dataset.train_sequences=[a,b]", "dataset.train_sequences=3"):  # fmt: skip
        assert check_command_line("train", [arg], module).error is None, arg


def test_a_setting_nothing_takes_is_refused_naming_what_takes_it() -> None:
    module = "mfg_lightning.train"
    error = check_command_line("train", ["+model.foo=1"], module).error
    assert error.startswith(
        "+model.foo=1: mfg_lightning.models.mfg_module.MFGLitModule (model) takes no setting foo;"
    )
    assert "optimizer" in error and "\n" not in error  # what it does take
    error = check_command_line("train", ["+model.loss.w_ss=1"], module).error
    assert error.endswith("(model.loss) takes no setting w_ss; did you mean w_s?")
    # Added settings that the built object takes, or that nothing builds (an interpolation's
    # source), and a strategy whose **kwargs go to another library, stay.
    for argv in (["+trainer.profiler=simple"], ["+my_root=/d", "dataset.cache_dir=${my_root}"],
                 ["trainer=ddp"]):  # fmt: skip
        assert check_command_line("train", argv, module).error is None, argv


@pytest.mark.parametrize("dataset", ["kitti", "vkitti"])
def test_a_debug_preset_that_does_not_fit_the_dataset_says_so(dataset: str) -> None:
    error = check_command_line("train", [f"dataset={dataset}", "debug=tiny"], "m").error
    assert error.startswith(f"debug=tiny does not fit dataset={dataset}: it sets ")
    assert "dataset.sequence_length" in error and error.endswith("does not take")
    assert check_command_line("train", ["debug=tiny"], "m").error is None  # synthetic: it fits
    assert (
        check_command_line("train", [f"dataset={dataset}", "debug=fast_dev_run"], "m").error is None
    )


def test_an_unwritable_run_directory_is_one_line_naming_it(tmp_path: Path) -> None:
    """A file in the way, and a directory nobody may write into (a read-only mount: as root,
    whom permissions do not stop, /sys refuses new directories to everyone)."""
    (tmp_path / "afile").write_text("")
    module = "mfg_lightning.train"
    error = check_command_line("train", [f"paths.log_dir={tmp_path}/afile/logs"], module).error
    assert error.startswith(f"hydra.run.dir={tmp_path}/afile/logs/train/runs/")
    assert f"cannot write there (Not a directory: {tmp_path}/afile)" in error
    if os.geteuid() == 0:
        locked = Path("/sys")
    else:
        locked = tmp_path / "read_only"
        locked.mkdir(mode=0o555)
    for argv in (
        [f"paths.log_dir={locked}/logs"],
        ["-m", f"paths.log_dir={locked}/logs", "seed=1,2"],
    ):
        error = check_command_line("train", argv, module).error
        setting = "hydra.sweep.dir" if "-m" in argv else "hydra.run.dir"
        assert error.startswith(f"{setting}={locked}/logs/"), error
        assert f": {locked}); choose a writable directory with paths.log_dir" in error, error
    assert check_command_line("train", [f"paths.log_dir={tmp_path}/new/logs"], module).error is None
    assert not (tmp_path / "new").exists()  # checked, not made
    # data.check writes nothing: a read-only working directory is its business
    assert check_command_line("check", ["hydra.run.dir=/sys"], "m").error is None


def test_a_setting_the_built_object_does_not_take_is_one_line_when_it_is_built() -> None:
    """Where the command line check does not see the config (a --config-dir, a notebook's
    compose()), Hydra's error while building is still one line naming the node."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from mfg_lightning.core.errors import user_error_message

    cfg = OmegaConf.create({"loss": {"_target_": "mfg_lightning.models.losses.MFGLoss", "foo": 1}})
    with pytest.raises(Exception) as caught:
        instantiate(cfg.loss)
    assert user_error_message(caught.value) == (
        "loss: MFGLoss.__init__() got an unexpected keyword argument 'foo'"
    )


#: Every Hydra entry point that takes a config.
EVERY_ENTRY_POINT = [*ENTRY_POINTS, "mfg_lightning.train_flow", "mfg_lightning.measure"]


def _mistakes(module: str) -> tuple[list[str], dict[str, str]]:
    """Mistakes in ``module``'s own config: a whole-number setting given a word, and (where the
    config builds objects) a setting added to a node whose object takes no such setting; and
    the arguments it needs first (``predict`` names its dataset)."""
    name = importlib.import_module(module).main.__wrapped__
    name = inspect.getclosurevars(name).nonlocals["config_name"]
    given = ["dataset=synthetic"] if name == "predict" else []
    container = _container(_compose(name, given))
    leaves = dict(config_keys({k: v for k, v in container.items() if k != "hydra"}))
    whole = next(k for k, v in sorted(leaves.items()) if type(v) is int)
    mistakes = {whole: f"{whole}=abc"}
    for key, value in sorted(leaves.items()):  # a config that builds nothing has no second one
        takes = key.endswith("._target_") and "${" not in str(value)
        if takes and _parameters(_locate(value)) is not None:  # not one that takes **kwargs
            built = key.removesuffix("._target_")
            mistakes[f"{built}.no_such_setting"] = f"+{built}.no_such_setting=1"
            break
    return given, mistakes


@pytest.mark.slow
@pytest.mark.parametrize("module", EVERY_ENTRY_POINT)
def test_every_entry_point_refuses_a_wrong_type_and_an_unknown_setting_in_one_line(
    module: str, tmp_path: Path
) -> None:
    """Through the real command line: exit status 2, one line naming the key, nothing written
    (no FAILED run directory)."""
    given, mistakes = _mistakes(module)
    for key, arg in mistakes.items():
        proc = run_module(module, *given, arg, cwd=tmp_path, check=False)
        errors = [line for line in proc.stderr.splitlines() if line.strip()]
        assert proc.returncode == 2, (arg, proc.stderr[-2000:])
        assert len(errors) == 1 and errors[0].startswith(f"error: {arg}: "), proc.stderr[-2000:]
        assert key.rpartition(".")[2] in errors[0]
        assert not [p for p in tmp_path.iterdir() if p.name != "cache"], arg


@pytest.mark.slow
def test_train_refuses_an_unwritable_run_directory_and_an_unfitting_preset(tmp_path: Path) -> None:
    (tmp_path / "afile").write_text("")
    cases = {
        f"paths.log_dir={tmp_path}/afile/logs": "cannot write there (Not a directory",
        "dataset=kitti debug=tiny": "debug=tiny does not fit dataset=kitti",
        "seed=abc": "seed=abc: seed takes a whole number",
    }
    for args, message in cases.items():
        proc = run_module("mfg_lightning.train", *args.split(), cwd=tmp_path, check=False)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
        (line,) = proc.stderr.splitlines()
        assert line.startswith("error: ") and message in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_the_documented_lines_are_the_lines_printed() -> None:
    """docs/configuration.md, "Mistakes on the command line": each row's line is what the check
    prints for its input (a row with a placeholder, such as a read-only mount, is left out)."""
    from conftest import REPO
    from mfg_lightning.core.config import CONFIG_DIR
    from mfg_lightning.core.errors import unknown_choice

    text = (REPO / "docs" / "configuration.md").read_text()
    section = text.split("### Mistakes on the command line")[1].split("\n#")[0]
    rows = re.findall(r"^\| `([^`]+)`( without `\w+`)? \| `error: (.+)` \|$", section, re.M)
    assert len(rows) >= 9
    for given, without, line in rows:
        if "<date>" in line:
            continue
        name, argv = ("evaluate", []) if without else ("train", given.split())
        error = unknown_choice(CONFIG_DIR, argv) or check_command_line(name, argv, "m").error
        assert error == line.replace("mfg_lightning.evaluate", "m"), given


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
