"""Seeds: the report's mean ± std across the jobs of a multirun that differ only in ``seed``
(``hparams_search=seeds``), on a real 3-seed multirun and on hand-made job directories."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from conftest import run_module
from mfg_lightning.analysis.sweep_report import write_report
from mfg_lightning.analysis.sweeps import seed_groups, swept_keys
from mfg_lightning.core.config import compose
from mfg_lightning.core.tables import pm
from test_sweeps import _fake_job, _metrics


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow
def test_three_seed_multirun_reports_mean_and_std_across_seeds(tmp_path: Path) -> None:
    sweep = tmp_path / "seeds"
    run_module(
        "mfg_lightning.train", "hparams_search=seeds", "debug=tiny", "logger=none",
        f"hydra.sweep.dir={sweep}", cwd=tmp_path,
    )  # fmt: skip
    proc = run_module("mfg_lightning.report", str(sweep), cwd=tmp_path)
    assert "1 group(s) across seeds" in proc.stdout
    report_dir = sweep / "report"
    jobs = _rows(report_dir / "report.csv")
    assert sorted(r["seed"] for r in jobs) == ["0", "1", "2"]
    (group,) = _rows(report_dir / "seeds.csv")
    assert group["n"] == "3" and group["seeds"] == "0 1 2"
    trans = np.array([float(r["test/trans_err"]) for r in jobs])
    assert float(group["trans_err mean"]) == pytest.approx(trans.mean(), rel=1e-12)
    assert float(group["trans_err std"]) == pytest.approx(trans.std(ddof=1), rel=1e-12)
    assert float(group["trans_err std"]) > 0  # the seeds train different networks
    # ... on the same data: the mean-motion baseline depends on the training and test samples
    # only, and is the same for every seed
    baseline = {r["test/baseline_trans_err"] for r in jobs}
    assert len(baseline) == 1 and float(group["test/baseline_trans_err std"]) == 0.0
    md = (report_dir / "report.md").read_text()
    assert "## Across seeds" in md
    assert "| 3 of 3 | 0 1 2 |" in md
    mean, std = float(group["trans_err mean"]), float(group["trans_err std"])
    # the project's one number format (a spread below 0.5e-4 in scientific notation, not 0.0000)
    assert pm(mean, std) in md


def test_jobs_differing_only_in_seed_are_grouped(tmp_path: Path) -> None:
    root = tmp_path / "multirun"
    values = {("10", "0"): 0.1, ("10", "1"): 0.2, ("10", "2"): 0.4, ("100", "0"): 0.3,
              ("100", "1"): 0.5}  # fmt: skip
    # (w_s=100, seed=2) has no metrics.json: a failed job
    for num, (w_s, seed) in enumerate([*values, ("100", "2")]):
        trans = values.get((w_s, seed))
        metrics = None if trans is None else _metrics(trans, 0.5, ate=trans / 10)
        overrides = ["hparams_search=seeds", f"model.loss.w_s={w_s}", f"seed={seed}"]
        _fake_job(root, str(num), overrides, metrics, w_s=float(w_s))
    report = write_report(root)
    assert report.swept == ["model.loss.w_s", "seed"]
    groups = report.seed_groups
    assert [g.overrides["model.loss.w_s"] for g in groups] == ["10", "100"]
    assert [(len(g.finished), len(g.jobs)) for g in groups] == [(3, 3), (2, 3)]
    mean, std, n = groups[0].stats("trans_err")
    assert (mean, n) == (pytest.approx(0.7 / 3), 3)
    assert std == pytest.approx(np.std([0.1, 0.2, 0.4], ddof=1))
    assert groups[1].seeds == ["0", "1"]  # the failed seed 2 is not counted
    assert groups[1].stats("ate")[:2] == (
        pytest.approx(0.04),
        pytest.approx(np.std([0.03, 0.05], ddof=1)),
    )
    md = report.markdown
    assert "| `model.loss.w_s` | n | seeds | ATE (m) |" in md
    assert "| 100 | 2 of 3 | 0 1 |" in md
    rows = _rows(report.out_dir / "seeds.csv")
    assert [r["n"] for r in rows] == ["3", "2"] and rows[1]["jobs"] == "3"
    assert float(rows[0]["test/rot_err mean"]) == pytest.approx(0.7 / 300)


def test_no_seed_table_without_a_seed_sweep(tmp_path: Path) -> None:
    root = tmp_path / "multirun"
    for num, w_s in enumerate(("10", "100")):
        _fake_job(root, str(num), [f"model.loss.w_s={w_s}", "seed=3"], _metrics(0.1, 0.5))
    jobs = write_report(root).jobs
    assert swept_keys(jobs) == ["model.loss.w_s"] and seed_groups(jobs, ["model.loss.w_s"]) == []
    assert not (root / "report" / "seeds.csv").exists()
    assert "Across seeds" not in (root / "report" / "report.md").read_text()


def test_seed_search_varies_the_seed_and_keeps_the_synthetic_scenes() -> None:
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from mfg_lightning.core.config import CONFIG_DIR

    with initialize_config_dir(version_base="1.3", config_dir=CONFIG_DIR):
        cfg = hydra_compose("train", ["hparams_search=seeds"], return_hydra_config=True)
    assert [int(s) for s in cfg.hydra.sweeper.params["seed"].split(",")] == [0, 1, 2]
    assert "seeds_" in cfg.hydra.sweep.dir
    # the run seed reaches the data order, not the scenes
    a = compose("train", ["seed=1", "paths.output_dir=unused"]).dataset
    assert a.seed == 1 and a.scene_seed == 0


def test_synthetic_samples_follow_the_scene_seed_and_the_order_follows_the_seed() -> None:
    from mfg_lightning.data.synthetic import SyntheticDataModule

    def dm(seed: int, scene_seed: int | None) -> SyntheticDataModule:
        return SyntheticDataModule(height=16, width=32, batch_size=2, train_sequences=2,
                                   test_sequences=1, sequence_length=8, seed=seed,
                                   scene_seed=scene_seed)  # fmt: skip

    a, b, c = dm(0, 0), dm(1, 0), dm(1, None)
    for split in ("train", "test"):
        assert all(
            np.array_equal(a.dataset(split)[i]["flow"], b.dataset(split)[i]["flow"])
            for i in range(len(a.dataset(split)))
        )
    order = [batch["sample_id"] for batch in a.train_dataloader()]
    assert order != [batch["sample_id"] for batch in b.train_dataloader()]
    # scene_seed=None: the scenes follow the seed (the code default, as before the split)
    assert not np.array_equal(c.dataset("test")[0]["flow"], a.dataset("test")[0]["flow"])
