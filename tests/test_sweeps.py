"""Sweeps: real multiruns through the Hydra entry point, the report over them, and the sweep and
launcher configs (hparams_search, joblib, SLURM)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir

from conftest import run_module
from mfg_lightning.analysis.sweep_figures import SWEEP_FIGURES
from mfg_lightning.analysis.sweep_report import write_report
from mfg_lightning.analysis.sweeps import NotAMultirunError, collect_jobs, swept_keys
from mfg_lightning.core.config import CONFIG_DIR, processes_cpus
from mfg_lightning.report import main


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def _compose_with_hydra(overrides: list[str]):
    with initialize_config_dir(version_base="1.3", config_dir=CONFIG_DIR):
        return compose("train", overrides=overrides, return_hydra_config=True)


# --------------------------------------------------------------------------------------------
# Real multiruns (slow)
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_two_by_two_multirun_and_its_report(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    run_module("mfg_lightning.train", "-m", "debug=tiny", "model.loss.w_s=0,100",
               "model.top_k=1.0,0.5", f"hydra.sweep.dir={sweep}", cwd=tmp_path)  # fmt: skip
    jobs = sorted(p.name for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert jobs == ["0", "1", "2", "3"]
    assert len(list((sweep / ".trainings").glob("*.json"))) == 2  # one per w_s

    proc = run_module("mfg_lightning.report", str(sweep), cwd=tmp_path)
    out = sweep / "report"
    rows = _rows(out / "report.csv")
    assert len(rows) == 4
    assert {r["status"] for r in rows} == {"ok"}
    # the swept values, read back from each job's overrides and config
    assert {(r["model.loss.w_s"], r["model.top_k"]) for r in rows} == {
        ("0", "1.0"),
        ("0", "0.5"),
        ("100", "1.0"),
        ("100", "0.5"),
    }
    assert {float(r["w_s"]) for r in rows} == {0.0, 100.0}
    for r in rows:
        assert float(r["trans_err"]) >= 0 and float(r["rot_err"]) >= 0
        assert 0.0 <= float(r["active_fraction"]) <= float(r["top_k"])
        assert float(r["train_seconds"]) > 0
        assert int(r["global_step"]) == 4
        # every metric of metrics.json is a column too
        assert r["test/trans_err"] == r["trans_err"]
    md = (out / "report.md").read_text()
    assert md.count("| ok |") == 4
    assert "`model.loss.w_s`" in md and "`model.top_k`" in md
    assert "Common overrides: `debug=tiny`" in md
    assert "active units (%)" in md and "train time (s)" in md
    for name in SWEEP_FIGURES:
        png = out / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert "| job | status |" in proc.stdout
    assert not list(out.glob(".*.tmp"))  # atomic writes leave no temporary files


def _job_metrics(sweep: Path) -> dict[tuple[str, ...], dict]:
    """Every job's metrics.json ``metrics``, by its swept values."""
    found = {}
    for job in sweep.iterdir():
        if (job / "metrics.json").is_file():
            overrides = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text())
            swept = tuple(
                sorted(o for o in overrides if o.startswith(("model.loss.w_s", "model.top_k")))
            )
            found[swept] = json.loads((job / "metrics.json").read_text())["metrics"]
    return found


@pytest.fixture(scope="module")
def independent_sparsity_jobs(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The 2 × 3 grid's jobs each trained on its own (``share_trainings=false``)."""
    tmp = tmp_path_factory.mktemp("independent")
    run_module("mfg_lightning.train", "-m", "hparams_search=sparsity", "debug=tiny",
               *SPARSITY_GRID, "share_trainings=false", f"hydra.sweep.dir={tmp / 'sweep'}",
               cwd=tmp, timeout=900)  # fmt: skip
    return _job_metrics(tmp / "sweep")


#: 2 w_s × 3 top_k
SPARSITY_GRID = ("model.loss.w_s=0,100", "model.top_k=1.0,0.5,0.25")
SWEPT = ("model.loss.w_s=", "model.top_k=")


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["basic", "joblib"])
def test_the_sparsity_search_trains_once_per_w_s_and_every_job_reports_as_if_alone(
    tmp_path: Path, launcher: str, independent_sparsity_jobs: dict
) -> None:
    """``hparams_search=sparsity`` on a 2 × 3 grid: 2 trainings (one per w_s, the top_k jobs
    share it), and every job's metrics.json equals that of the job trained on its own, to the
    bit (each job picks its own best checkpoint by its own val/ate, at its own top_k)."""
    sweep = tmp_path / "sweep"
    run_module("mfg_lightning.train", "-m", "hparams_search=sparsity", "debug=tiny",
               *SPARSITY_GRID, f"hydra/launcher={launcher}", f"hydra.sweep.dir={sweep}",
               cwd=tmp_path, timeout=900)  # fmt: skip
    assert len(list((sweep / ".trainings").glob("*.json"))) == 2
    trained = [job for job in sweep.iterdir() if (job / "checkpoints").is_dir()]
    assert len(trained) == 2
    evaluated = [job for job in sweep.iterdir() if (job / "metrics.json").is_file()]
    assert len(evaluated) == 6
    for job in evaluated:
        info = json.loads((job / "metrics.json").read_text())
        assert info["global_step"] == 4 and info["train_seconds"] > 0
    shared = _job_metrics(sweep)
    assert shared.keys() == independent_sparsity_jobs.keys() and len(shared) == 6
    for swept, metrics in shared.items():
        assert metrics == independent_sparsity_jobs[swept], swept
    # the top_k jobs of one w_s differ in what they evaluate
    assert len({m["test/active_fraction"] for m in shared.values()}) > 2


@pytest.mark.slow
def test_a_crashed_job_is_reported_as_failed_and_the_rest_still_tabulated(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    # hparams_search=sparsity with its lists replaced from the command line: two jobs, and
    # top_k=0 is rejected when the model is built, so job 0 crashes; the sweep goes on to job 1
    # and fails at the end.
    proc = run_module(
        "mfg_lightning.train",
        "-m",
        "hparams_search=sparsity",
        "debug=tiny",
        "model.loss.w_s=10",
        "model.top_k=0,0.5",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode != 0
    assert (sweep / "1" / "metrics.json").is_file()
    assert not (sweep / "0" / "metrics.json").exists()
    assert "top_k" in proc.stderr

    out = tmp_path / "report"
    proc = run_module("mfg_lightning.report", str(sweep), "--out", str(out), cwd=tmp_path)
    assert "1 of 2 jobs failed" in proc.stderr
    rows = {r["job"]: r for r in _rows(out / "report.csv")}
    assert rows["1"]["status"] == "ok" and float(rows["1"]["trans_err"]) >= 0
    assert rows["0"]["status"] == "failed"
    # the job's own error message, read from its train.log
    assert "top_k" in rows["0"]["reason"] and "train.log" in rows["0"]["reason"]
    assert rows["0"]["model.top_k"] == "0"
    md = (out / "report.md").read_text()
    assert "**failed**" in md and "Failed jobs (1 of 2)" in md
    # one top-k value and one w_s value finished: no curve to draw, and the report says so
    assert "Plot not drawn: `error_vs_top_k.png`" in md


@pytest.mark.slow
def test_optuna_search_runs_and_its_best_trial_is_reported(tmp_path: Path) -> None:
    sweep = tmp_path / "optuna"
    run_module(
        "mfg_lightning.train",
        "hparams_search=optuna",  # hydra.mode=MULTIRUN in the config: no -m needed
        "debug=tiny",
        # a validation tail long enough for 5-frame snippets, so val/ate (the objective) exists
        "dataset.val_fraction=0.5",
        "hydra.sweeper.n_trials=2",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
    )
    results = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert set(results["best_params"]) == {"model.loss.w_s", "model.optimizer.lr"}
    assert 1 <= results["best_params"]["model.loss.w_s"] <= 1000
    report = write_report(sweep)
    assert len(report.jobs) == 2 and report.n_failed == 0
    assert set(report.swept) == {"model.loss.w_s", "model.optimizer.lr"}
    assert "Optuna best:" in report.markdown
    best = min(j.metrics["val/ate"] for j in report.jobs)
    assert best == pytest.approx(results["best_value"])


# --------------------------------------------------------------------------------------------
# The report on hand-made directories (fast)
# --------------------------------------------------------------------------------------------


def _fake_job(
    root: Path,
    name: str,
    overrides: list[str],
    metrics: dict | None,
    w_s: float = 100.0,
    top_k: float | None = None,
) -> Path:
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (job / ".hydra" / "hydra.yaml").write_text(
        yaml.safe_dump({"hydra": {"job": {"num": int(name)}}})
    )
    config = {"seed": 0, "model": {"top_k": top_k, "loss": {"w_s": w_s}, "optimizer": {"lr": 1e-3}}}
    (job / "config.yaml").write_text(yaml.safe_dump(config))
    if metrics is not None:
        payload = {"metrics": metrics, "train_seconds": 12.5, "global_step": 150}
        (job / "metrics.json").write_text(json.dumps(payload))
    return job


def _metrics(trans: float, active: float, ate: float | None = None) -> dict:
    m = {"test/trans_err": trans, "test/rot_err": trans / 100, "test/active_fraction": active}
    if ate is not None:
        m.update({"test/ate": ate, "test/ate_std": ate / 2, "test/rpe_trans": 2 * ate})
    return m


def test_failure_reasons_come_from_the_job_directory(tmp_path: Path) -> None:
    root = tmp_path / "multirun"
    _fake_job(root, "0", ["model.loss.w_s=0"], _metrics(0.1, 0.6, ate=0.02), w_s=0)
    _fake_job(root, "1", ["model.loss.w_s=10"], _metrics(0.1, 0.3, ate=0.03), w_s=10)
    crashed = _fake_job(root, "2", ["model.loss.w_s=100"], None)
    (crashed / "train.log").write_text(
        "Traceback (most recent call last):\n  File x\nRuntimeError: CUDA out of memory\n"
    )
    garbled = _fake_job(root, "3", ["model.loss.w_s=1000"], None)
    (garbled / "metrics.json").write_text("{not json")
    _fake_job(root, "4", ["model.loss.w_s=5"], None)
    logged = _fake_job(root, "5", ["model.loss.w_s=7"], None)
    (logged / "train.log").write_text(
        "[2026-01-01 10:00:00,000][mfg_lightning.train][ERROR] - model.top_k must be in (0, 1]\n"
    )
    # an error record of a job that went on to finish does not make it failed
    noisy = _fake_job(root, "6", ["model.loss.w_s=3"], _metrics(0.1, 0.4, ate=0.02), w_s=3)
    (noisy / "train.log").write_text("[t][mfg_lightning.data][ERROR] - skipped one sample\n")
    (root / "multirun.yaml").write_text("hydra: {}\n")

    jobs = collect_jobs(root)
    assert [j.name for j in jobs] == ["0", "1", "2", "3", "4", "5", "6"]
    assert [j.status for j in jobs] == ["ok", "ok", "failed", "failed", "failed", "failed", "ok"]
    assert jobs[2].reason == "train.log: RuntimeError: CUDA out of memory"
    assert jobs[3].reason.startswith("unreadable metrics.json")
    assert jobs[4].reason.startswith("no metrics.json")
    assert jobs[5].reason == "train.log: model.top_k must be in (0, 1]"
    assert swept_keys(jobs) == ["model.loss.w_s"]

    report = write_report(root)
    md = report.markdown
    # ATE (mean ± std) and RPE columns appear because some job has them
    assert "ATE (m)" in md and "0.0200 ± 0.01" in md and "RPE trans (m)" in md
    assert "RuntimeError: CUDA out of memory" in md
    assert "Failed jobs (4 of 7)" in md
    assert set(report.plots) == {"error_vs_w_s.png", "active_fraction_vs_w_s.png"}
    assert "error_vs_top_k.png" in report.skipped_plots
    assert len(_rows(report.csv_path)) == 7


def test_report_without_ate_has_no_ate_column(tmp_path: Path) -> None:
    root = tmp_path / "multirun"
    _fake_job(root, "0", ["model.top_k=1.0"], _metrics(0.2, 0.5), top_k=1.0)
    _fake_job(root, "1", ["model.top_k=0.05"], _metrics(0.3, 0.05), top_k=0.05)
    report = write_report(root, tmp_path / "out")
    assert "ATE" not in report.markdown and "RPE" not in report.markdown
    assert set(report.plots) == {"error_vs_top_k.png"}
    assert [j.top_k_percent() for j in report.jobs] == [100.0, 5.0]


def test_all_jobs_failed_writes_the_report_and_exits_1(tmp_path: Path, capsys) -> None:
    root = tmp_path / "multirun"
    _fake_job(root, "0", ["model.loss.w_s=1"], None)
    assert main([str(root)]) == 1
    assert "no job finished" in capsys.readouterr().err
    assert (root / "report" / "report.md").is_file()


@pytest.mark.parametrize("case", ["missing", "empty", "single_run", "no_jobs"])
def test_not_a_multirun_directory_is_a_clear_error(tmp_path: Path, case: str, capsys) -> None:
    target = tmp_path / "dir"
    expected = {
        "missing": "is not a directory",
        "empty": "is empty",
        "single_run": "is a single run directory",
        "no_jobs": "holds no job directories",
    }[case]
    if case != "missing":
        target.mkdir()
    if case == "single_run":
        (target / ".hydra").mkdir()
        (target / "metrics.json").write_text("{}")
    if case == "no_jobs":
        (target / "notes.txt").write_text("hello")
    with pytest.raises(NotAMultirunError, match=expected):
        collect_jobs(target)
    assert main([str(target)]) == 2
    assert expected in capsys.readouterr().err
    assert not (target / "report").exists()


# --------------------------------------------------------------------------------------------
# Configs
# --------------------------------------------------------------------------------------------


def test_sparsity_search_config_sweeps_w_s_and_top_k() -> None:
    cfg = _compose_with_hydra(["hparams_search=sparsity"])
    params = cfg.hydra.sweeper.params
    w_s = [float(v) for v in params["model.loss.w_s"].split(",")]
    top_k = [float(v) for v in params["model.top_k"].split(",")]
    assert len(w_s) >= 3 and 0.0 in w_s and 100.0 in w_s  # none, and the paper's value
    assert 1.0 in top_k and 0.05 in top_k and 0.005 in top_k  # the paper's k range
    assert all(0 < k <= 1 for k in top_k)
    assert cfg.hydra.mode.name == "MULTIRUN"
    assert "sparsity_" in cfg.hydra.sweep.dir


def test_optuna_search_config_minimises_val_ate_over_w_s_and_lr() -> None:
    cfg = _compose_with_hydra(["hparams_search=optuna"])
    sweeper = cfg.hydra.sweeper
    assert sweeper._target_.endswith("OptunaSweeper")
    assert cfg.optimized_metric == "val/ate"
    assert str(sweeper.direction) in ("minimize", "Direction.minimize")
    assert sweeper.params["model.loss.w_s"].startswith("tag(log")
    assert "model.optimizer.lr" in sweeper.params
    assert 1 <= sweeper.n_trials <= 20


@pytest.mark.parametrize(
    "launcher,target",
    [
        ("joblib", "JoblibLauncher"),
        ("submitit_slurm", "SlurmLauncher"),
        ("submitit_local", "LocalLauncher"),
        ("slurm", "SlurmLauncher"),
    ],
)
def test_launcher_configs_compose(launcher: str, target: str) -> None:
    cfg = _compose_with_hydra([f"hydra/launcher={launcher}", "hparams_search=sparsity"])
    assert cfg.hydra.launcher._target_.endswith(target)
    assert cfg.hydra.sweeper.params["model.loss.w_s"]  # the search survives the launcher


def test_project_slurm_launcher_sets_resources_on_top_of_the_plugin() -> None:
    cfg = _compose_with_hydra(
        ["hydra/launcher=slurm", "hydra.launcher.partition=gpu", "hydra.launcher.mem_gb=32"]
    )
    launcher = cfg.hydra.launcher
    assert launcher.partition == "gpu" and launcher.mem_gb == 32
    assert launcher.gpus_per_node == 1 and launcher.cpus_per_task >= 1
    assert launcher.timeout_min > 0
    # inherited from the plugin's submitit_slurm
    assert launcher.submitit_folder.endswith(".submitit/%j")


@pytest.mark.parametrize(("overrides", "cpus"), [([], 1), (["trainer=gpu"], None),
                                                 (["trainer=gpu", "dataset.num_workers=6"], 7),
                                                 (["dataset.num_workers=3"], 4)])  # fmt: skip
def test_slurm_jobs_ask_for_the_cores_their_trainer_starts(
    overrides: list[str], cpus: int | None
) -> None:
    """sbatch --cpus-per-task is the training process plus its loader workers, so a GPU job's 6
    workers do not share 4 cores (the launcher's earlier fixed value). trainer=gpu's workers
    follow the cores of the machine composing (None: 1 + loader_workers(6) here)."""
    from mfg_lightning.core.machine import loader_workers

    cfg = _compose_with_hydra(["hydra/launcher=slurm", *overrides])
    cpus = 1 + loader_workers(6) if cpus is None else cpus
    assert cfg.hydra.launcher.cpus_per_task == cpus == 1 + cfg.dataset.num_workers
    with pytest.raises(ValueError, match="num_workers"):
        processes_cpus(-1)
