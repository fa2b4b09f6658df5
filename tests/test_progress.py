"""Training's progress bar: the run's steps when max_steps limits it, epochs when max_epochs
does."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.demos.boring_classes import BoringModel

from mfg_lightning.core.config import compose
from mfg_lightning.run.progress import RunProgressBar, steps_limit


class _Record(L.Callback):
    """What the train bar shows after every training batch: (description, completed, total)."""

    def __init__(self, bar: RunProgressBar) -> None:
        self.bar, self.seen = bar, []

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        task = self.bar.progress.tasks[self.bar.train_progress_bar_id]
        self.seen.append((task.description, task.completed, task.total))
        self.limit = steps_limit(trainer)


def _fit(tmp_path: Path, **limits: Any) -> list[tuple[str, float, float]]:
    bar = RunProgressBar()
    record = _Record(bar)  # after the bar: it sees what the bar has just drawn
    trainer = L.Trainer(
        default_root_dir=tmp_path, callbacks=[bar, record], logger=False,
        enable_checkpointing=False, enable_model_summary=False, limit_train_batches=4,
        limit_val_batches=0, accelerator="cpu", **limits,
    )  # fmt: skip
    trainer.fit(BoringModel())
    # steps_limit names max_steps exactly when the bar counts up to it.
    steps = limits.get("max_steps")
    assert record.limit == (steps if record.seen[-1][2] == steps else None)
    return record.seen


def test_a_step_limited_run_counts_its_steps(tmp_path: Path) -> None:
    seen = _fit(tmp_path, max_steps=10)
    assert len(seen) == 10
    assert [(c, t) for _, c, t in seen] == [(i, 10) for i in range(1, 11)]
    assert seen[0][0].endswith("Epoch 0 · 9 steps to go")
    assert seen[5][0].endswith("Epoch 1 · 4 steps to go")  # the bar does not restart per epoch
    assert seen[-1][0].endswith("Epoch 2 · 0 steps to go")
    assert all("-2" not in d for d, _, _ in seen)


def test_an_epoch_limited_run_counts_batches_per_epoch(tmp_path: Path) -> None:
    seen = _fit(tmp_path, max_epochs=2)
    assert [(c, t) for _, c, t in seen] == [(i, 4) for i in range(1, 5)] * 2
    assert "Epoch 0/1" in seen[0][0] and "Epoch 1/1" in seen[-1][0]
    # Both limits: whichever ends the run first.
    assert [(c, t) for _, c, t in _fit(tmp_path, max_epochs=5, max_steps=6)][-1] == (6, 6)
    assert _fit(tmp_path, max_epochs=1, max_steps=100)[-1][1:] == (4, 4)


def test_training_uses_it() -> None:
    cfg = compose("train", [])
    assert cfg.callbacks.rich_progress_bar._target_ == "mfg_lightning.run.progress.RunProgressBar"


class _LossEveryThird(BoringModel):
    """Logs ``train/loss`` at every third step only, as the MFG module logs at its logging
    steps; records what the bar shows and how often a tensor was read."""

    def training_step(self, batch: Any, batch_idx: int) -> Any:
        out = super().training_step(batch, batch_idx)
        if batch_idx % 3 == 0:
            self.log("train/loss", out["loss"])
        return out


def test_the_bar_shows_the_logged_loss_and_reads_each_value_once(
    tmp_path: Path, monkeypatch
) -> None:
    reads: list[float] = []
    original = torch.Tensor.__float__

    def counted(self: torch.Tensor) -> float:
        reads.append(original(self))
        return reads[-1]

    bar = RunProgressBar()
    shown: list[Any] = []

    class Shown(L.Callback):
        def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
            shown.append(bar.get_metrics(trainer, trainer.lightning_module).get("train/loss"))

    monkeypatch.setattr(torch.Tensor, "__float__", counted)
    trainer = L.Trainer(
        default_root_dir=tmp_path, callbacks=[bar, Shown()], logger=False,
        enable_checkpointing=False, enable_model_summary=False, limit_train_batches=9,
        limit_val_batches=0, accelerator="cpu", max_epochs=1,
    )  # fmt: skip
    trainer.fit(_LossEveryThird())
    assert all(v is not None for v in shown)
    # three values logged (batches 0, 3, 6), each read once, however often the bar asked
    assert len(reads) == 3
    assert shown == [reads[0]] * 3 + [reads[1]] * 3 + [reads[2]] * 3
