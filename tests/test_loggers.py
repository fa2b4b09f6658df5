"""Loggers other than TensorBoard: CSV, MLflow (SQLite store in the run directory), W&B offline
and ``logger=many``, each read back with its own reader after a real short training.

W&B runs offline with every directory it writes in the test's temporary directory: no network,
nothing in the user's home.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import run_module
from mfg_lightning.core.config import compose

FINAL = ("test/trans_err", "test/rot_err", "test/ate", "val/trans_err")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One tiny training logging to TensorBoard + CSV (logger=many), MLflow and W&B at once."""
    pytest.importorskip("mlflow")
    pytest.importorskip("wandb")
    tmp = tmp_path_factory.mktemp("loggers")
    wandb_home = tmp / "wandb_home"
    env = {
        "WANDB_MODE": "offline",
        "WANDB_SILENT": "true",
        "WANDB_DIR": str(wandb_home / "dir"),
        "WANDB_CACHE_DIR": str(wandb_home / "cache"),
        "WANDB_CONFIG_DIR": str(wandb_home / "config"),
        "WANDB_DATA_DIR": str(wandb_home / "data"),
        "WANDB_ARTIFACT_DIR": str(wandb_home / "artifacts"),
    }
    with pytest.MonkeyPatch.context() as mp:
        for key, value in env.items():
            mp.setenv(key, value)
        run_module("mfg_lightning.train", "debug=tiny", "logger=[many,mlflow,wandb]",
                   f"hydra.run.dir={tmp / 'run'}", cwd=tmp)  # fmt: skip
    return tmp / "run"


def _final(run_dir: Path) -> dict[str, float]:
    metrics = json.loads((run_dir / "metrics.json").read_text())["metrics"]
    return {k: metrics[k] for k in FINAL}


@pytest.mark.slow
def test_csv_logger_has_the_steps_the_settings_and_the_final_metrics(run: Path) -> None:
    with (run / "csv" / "metrics.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [float(r["train/loss"]) for r in rows if r["train/loss"]]  # every logged step
    last = rows[-1]  # the final metrics, in one row at the last step
    assert int(last["step"]) == 4
    for key, value in _final(run).items():
        assert float(last[key]) == pytest.approx(value, rel=1e-6), key
    hparams = yaml.safe_load((run / "csv" / "hparams.yaml").read_text())
    assert hparams["model.loss.w_s"] == 100 and hparams["seed"] == 0
    assert hparams["dataset._target_"].endswith("SyntheticDataModule")


@pytest.mark.slow
def test_mlflow_logger_writes_a_sqlite_store_in_the_run_directory(run: Path) -> None:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{run / 'mlflow.db'}")
    (experiment,) = [e for e in client.search_experiments() if e.name == "mfg_lightning"]
    assert experiment.artifact_location.startswith(str(run))
    (mlrun,) = client.search_runs([experiment.experiment_id])
    assert mlrun.info.status == "FINISHED"
    params = mlrun.data.params
    assert float(params["model.loss.w_s"]) == 100 and params["seed"] == "0"
    for key, value in _final(run).items():
        assert mlrun.data.metrics[key] == pytest.approx(value, rel=1e-6), key
    history = client.get_metric_history(mlrun.info.run_id, "train/loss")
    assert sorted(m.step for m in history) == [0, 1, 2, 3]
    assert not (run.parent / "mlruns").exists()  # nothing in the working directory


@pytest.mark.slow
def test_wandb_logger_writes_an_offline_run_read_back_by_wandb(run: Path) -> None:
    (wandb_file,) = (run / "wandb").glob("offline-run-*/run-*.wandb")
    # wandb's own reader of the transaction log
    proc = subprocess.run(
        [sys.executable, "-m", "wandb", "leet", "inspect", "--summary", "--json", str(wandb_file)],
        capture_output=True, text=True, timeout=120, check=True,
        env={"PATH": "/usr/bin:/bin", "HOME": str(run.parent / "wandb_home"),
             "WANDB_MODE": "offline"},
    )  # fmt: skip
    summary = json.loads(proc.stdout)
    assert summary["state"] == "finished" and summary["exit_code"] == 0
    assert summary["project"] == "mfg_lightning"
    assert summary["config"]["model.loss.w_s"] == 100 and summary["config"]["seed"] == 0
    for key, value in _final(run).items():
        assert summary["summary"][key] == pytest.approx(value, rel=1e-6), key
    assert not any((run.parent / "wandb_home").rglob("*.wandb"))  # the run is in the run dir


@pytest.mark.slow
def test_many_keeps_tensorboard_with_its_hparams_view(run: Path) -> None:
    tags: set[str] = set()
    for events in sorted((run / "tensorboard").glob("events.out.*")):
        acc = EventAccumulator(str(events))
        acc.Reload()
        tags |= set(acc.Tags()["scalars"])
        try:
            tags |= set(acc.PluginTagToContent("hparams"))
        except KeyError:
            continue
    assert "train/loss" in tags and "_hparams_/session_start_info" in tags


@pytest.mark.parametrize(
    "option,names",
    [
        ("csv", ["csv"]),
        ("wandb", ["wandb"]),
        ("mlflow", ["mlflow"]),
        ("many", ["tensorboard", "csv"]),
    ],
)
def test_logger_configs_compose(option: str, names: list[str], tmp_path: Path) -> None:
    cfg = compose("train", [f"logger={option}", f"paths.output_dir={tmp_path}"])
    assert list(cfg.logger) == names
    for name in names:
        assert cfg.logger[name]._target_.startswith("lightning.pytorch.loggers.")
    if option == "mlflow":
        assert cfg.logger.mlflow.tracking_uri == f"sqlite:///{tmp_path}/mlflow.db"
    if option == "wandb":
        assert cfg.logger.wandb.offline is True


def test_a_wandb_run_left_open_by_a_failed_job_is_finished(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Lightning's WandbLogger reuses any open W&B run: a job of a multirun that failed must not
    leave its run for the next job to log into."""
    wandb = pytest.importorskip("wandb")
    from mfg_lightning.run.runs import finish_stale_logger_runs

    for name in ("DIR", "CACHE_DIR", "CONFIG_DIR", "DATA_DIR", "ARTIFACT_DIR"):
        monkeypatch.setenv(f"WANDB_{name}", str(tmp_path / name.lower()))
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = wandb.init(mode="offline", dir=str(tmp_path), project="stale")
    assert wandb.run is not None
    finish_stale_logger_runs()
    assert wandb.run is None
    summary = subprocess.run(
        [sys.executable, "-m", "wandb", "leet", "inspect", "--summary", "--json",
         str(Path(run.dir).parent)],
        capture_output=True, text=True, timeout=120, check=True,
        env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "WANDB_MODE": "offline"},
    )  # fmt: skip
    assert json.loads(summary.stdout)["exit_code"] == 1  # recorded as failed
    finish_stale_logger_runs()  # nothing open: nothing to do
