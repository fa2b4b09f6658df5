"""Which jobs of a multirun share a training (mfg_lightning.run.shared_training): the training
config without the evaluation settings and the job's directory, and the best checkpoint picked
by the rule of Lightning's ModelCheckpoint. The multiruns themselves: tests/test_sweeps.py."""

from __future__ import annotations

import math
from pathlib import Path

from mfg_lightning.core.config import compose
from mfg_lightning.run.shared_training import best_checkpoint, shared_folder, training_id
from mfg_lightning.run.training import run_config


def _job(path: Path, *overrides: str):
    return run_config(compose("train", [f"paths.output_dir={path}", *overrides]))[0]


def test_jobs_that_differ_in_evaluation_settings_only_share_a_training(tmp_path: Path) -> None:
    base = training_id(_job(tmp_path / "1", "model.top_k=1.0"))
    # another top_k, test setting, logger, figures, and a directory that starts alike
    same = [
        _job(tmp_path / "10", "model.top_k=0.05"),
        _job(tmp_path / "2", "test=false", "logger=csv", "callbacks.figures=null"),
        _job(tmp_path / "3", "model.image_log_every_n_steps=0", "dataset.eval_batch_size=3"),
        _job(tmp_path / "4", "callbacks.model_checkpoint.monitor=val/loss"),
    ]
    assert {training_id(job) for job in same} == {base}
    for other in (["model.loss.w_s=10"], ["seed=1"], ["trainer.max_steps=5"],
                  ["model.net.hidden_units=10"]):  # fmt: skip
        assert training_id(_job(tmp_path / "5", *other)) != base, other


def test_a_rule_that_stops_on_a_validation_metric_makes_top_k_a_training_setting(
    tmp_path: Path,
) -> None:
    """Under callbacks=convergence the training stops on val/ate, which top_k changes."""
    a = _job(tmp_path / "1", "callbacks=convergence", "model.top_k=1.0")
    b = _job(tmp_path / "2", "callbacks=convergence", "model.top_k=0.05")
    assert training_id(a) != training_id(b)


def test_outside_a_multirun_every_run_trains(tmp_path: Path) -> None:
    assert shared_folder(_job(tmp_path / "1")) is None


def test_the_best_checkpoint_is_picked_as_model_checkpoint_keeps_it() -> None:
    """The first validation's, replaced only by a strictly better one (a tie keeps the
    earlier); a NaN counts as the worst; a validation without the metric is skipped."""
    paths = ["a", "b", "c", "d"]

    def pick(values, mode="min"):
        scores = [{} if v is None else {"val/ate": v} for v in values]
        return best_checkpoint(paths, scores, "val/ate", mode)

    assert pick([3.0, 2.0, 2.0, 5.0]) == "b"
    assert pick([math.nan, 9.0, math.nan, 10.0]) == "b"
    assert pick([None, 4.0, 1.0, None]) == "c"
    assert pick([1.0, 2.0, 3.0, 3.0], mode="max") == "c"
    assert pick([None] * 4) is None
