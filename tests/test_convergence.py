"""The convergence rule (``callbacks=convergence``) and learning curves that survive a resume."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from mfg_lightning.core.config import compose
from mfg_lightning.run.convergence import ConvergenceStop, plateau_improvement
from mfg_lightning.run.runs import read_csv_metrics
from mfg_lightning.run.training import train


def test_plateau_improvement_measures_the_best_over_the_last_window() -> None:
    curve = [(100, 1.0), (200, 0.5), (300, 0.45), (400, 0.44)]
    # at 400, window 0.25: best up to step 300 is 0.45, best now 0.44
    assert plateau_improvement(curve, 400, 0.25) == pytest.approx(0.01 / 0.45)
    # window 0.5: best up to 200 is 0.5
    assert plateau_improvement(curve, 400, 0.5) == pytest.approx(0.06 / 0.5)
    # a worse last value does not undo the best: improvement 0, never negative
    assert plateau_improvement([*curve, (500, 0.9)], 500, 0.2) == pytest.approx(0.0)
    # no reference yet; non-finite values are ignored
    assert plateau_improvement([(100, 1.0)], 100, 0.25) is None
    assert plateau_improvement([(100, math.nan), (400, 0.3)], 400, 0.25) is None
    for bad in ({"window": 0}, {"window": 1}, {"min_improvement": -1}, {"decay_fraction": 0}):
        with pytest.raises(ValueError, match="callbacks.convergence"):
            ConvergenceStop(**bad)


def _config(out: Path, steps: int, *extra: str):
    return compose(
        "train",
        [
            "debug=tiny",
            "callbacks=convergence",
            "~callbacks.rich_progress_bar",
            "++trainer.enable_progress_bar=false",
            "model.scheduler=null",
            "logger=csv",
            "model.image_log_every_n_steps=0",
            "test=false",
            "resume=true",
            f"trainer.max_steps={steps}",
            "trainer.val_check_interval=2",
            "callbacks.last_checkpoint.every_n_train_steps=2",
            "callbacks.convergence.min_steps=0",
            f"paths.output_dir={out}",
            f"paths.cache_dir={out.parent / 'cache'}",
            *extra,
        ],
    )


def _lrs(ckpt: Path) -> list[float]:
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    return [g["lr"] for g in state["optimizer_states"][0]["param_groups"]]


def test_a_plateau_starts_the_decay_and_stops_training(tmp_path: Path) -> None:
    """min_improvement 1.0: any curve has plateaued once a reference exists (step 4 with
    window 0.5 and validations every 2 steps); the decay of 1.0 × 4 steps ends at 8, where
    training stops long before max_steps, the rate falling linearly to a quarter at step 7."""
    out = tmp_path / "run"
    cfg = _config(
        out,
        40,
        "callbacks.convergence.min_improvement=1.0",
        "callbacks.convergence.window=0.5",
        "callbacks.convergence.decay_fraction=1.0",
    )
    train(cfg)
    status = json.loads((out / "convergence.json").read_text())
    assert status["converged"] is True and status["reason"] == "plateau"
    assert (status["decay_start"], status["decay_end"], status["step"]) == (4, 8, 8)
    assert [p["step"] for p in status["curve"]] == [2, 4, 6, 8]
    assert status["rule"]["min_improvement"] == 1.0
    base = float(cfg.model.optimizer.lr)
    assert _lrs(out / "checkpoints" / "last.ckpt") == pytest.approx([0.25 * base])

    # Resumed (a study that lost its stage results trains it "again"): not one more step, and
    # the checkpoints keep their weights.
    def weights() -> dict[str, tuple[int, dict[str, torch.Tensor]]]:
        loaded = {p.name: torch.load(p, map_location="cpu", weights_only=True)
                  for p in (out / "checkpoints").iterdir()}  # fmt: skip
        return {k: (v["global_step"], v["state_dict"]) for k, v in loaded.items()}

    before = weights()
    train(cfg)
    status = json.loads((out / "convergence.json").read_text())
    assert (status["reason"], status["decay_end"], status["step"]) == ("plateau", 8, 8)
    after = weights()
    assert after.keys() == before.keys()
    for name, (step, state) in before.items():
        assert after[name][0] == step == 8
        assert all(torch.equal(state[k], after[name][1][k]) for k in state)


def test_a_step_cap_shortens_the_schedule_and_reads_not_converged(tmp_path: Path) -> None:
    """min_improvement 0 is never met: the decay (half the steps so far, rounded up to the next
    validation) starts at the first validation from which it would reach max_steps (step 4 of
    6) and the run stops at 6 as "step cap", not converged. Resumed with max_steps 12, the rate
    is constant again until the cap comes near (decay 8 → 12); the earlier CSV log is kept
    beside the new one and the callback's curve carries on."""
    out = tmp_path / "run"
    extra = ("callbacks.convergence.min_improvement=0", "callbacks.convergence.decay_fraction=0.5")
    cfg = _config(out, 6, *extra)
    train(cfg)
    status = json.loads((out / "convergence.json").read_text())
    assert status["reason"] == "step cap" and not status["converged"]
    assert (status["decay_start"], status["decay_end"], status["step"]) == (4, 6, 6)
    train(_config(out, 12, *extra))
    status = json.loads((out / "convergence.json").read_text())
    assert status["reason"] == "step cap" and status["converged"] is False
    assert (status["decay_start"], status["decay_end"], status["step"]) == (8, 12, 12)
    assert [p["step"] for p in status["curve"]] == [2, 4, 6, 8, 10, 12]
    # the last update (step 11) ran at a quarter of the constant rate, restored after the resume
    assert _lrs(out / "checkpoints" / "last.ckpt") == pytest.approx([0.25 * cfg.model.optimizer.lr])
    assert (out / "csv" / "metrics.part001.csv").is_file()
    # (Lightning logs a validation at the step before its global step; the final metrics row of
    # each fit at the global step)
    steps = {int(r["step"]) for r in read_csv_metrics(out / "csv") if r.get("val/ate")}
    assert {1, 3, 5, 7, 9, 11} <= steps


def test_an_equal_budget_ignores_the_rule_and_decays_over_its_last_tenth(tmp_path: Path) -> None:
    """budget_steps 10 with decay_fraction 0.2: whatever the curve does (min_improvement 1.0
    would call any curve a plateau at step 4), the rate is constant to step 8 and falls
    linearly to 0 at 10, where training stops; the status says "budget", not converged. Resumed
    in the middle of its decay, it carries on from the same schedule."""
    out = tmp_path / "run"
    extra = (
        "callbacks.convergence.budget_steps=10",
        "callbacks.convergence.decay_fraction=0.2",
        "callbacks.convergence.min_improvement=1.0",
    )
    cfg = _config(out, 9, *extra)
    train(cfg)
    status = json.loads((out / "convergence.json").read_text())
    assert (status["reason"], status["decay_start"], status["decay_end"]) == ("budget", 8, 10)
    assert status["converged"] is False and status["rule"]["budget_steps"] == 10
    base = float(cfg.model.optimizer.lr)
    # the step-8 update ran at the full rate (a factor of 1 - 0/2), step 9 not yet taken
    assert _lrs(out / "checkpoints" / "last.ckpt") == pytest.approx([base])
    train(_config(out, 10, *extra))
    status = json.loads((out / "convergence.json").read_text())
    assert (status["reason"], status["step"]) == ("budget", 10)
    assert _lrs(out / "checkpoints" / "last.ckpt") == pytest.approx([0.5 * base])
    with pytest.raises(ValueError, match="budget_steps must be at least 2"):
        ConvergenceStop(budget_steps=1)


def test_a_scheduler_is_refused(tmp_path: Path) -> None:
    """The rule decays the rate itself: a configured schedule would fight it."""
    cfg = _config(tmp_path / "run", 4)
    cfg.model.scheduler = compose("train", []).model.scheduler
    with pytest.raises(ValueError, match="model.scheduler=null"):
        train(cfg)
