"""``last.ckpt`` by wall time: saved every few minutes as well as every N steps (a test clock
moves 30 s a step), and the period each trainer config sets (by steps on a CPU, by time alone
on a GPU)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import pytest

from conftest import quiet_trainer
from mfg_lightning.core.config import compose
from mfg_lightning.run.callbacks import LastCheckpoint


class Clock(L.Callback):
    """A test clock that moves ``seconds`` at the end of every training step."""

    def __init__(self, seconds: float) -> None:
        self.now, self.seconds = 0.0, seconds

    def __call__(self) -> float:
        return self.now

    def on_train_batch_end(self, *args: Any) -> None:
        self.now += self.seconds


@pytest.mark.parametrize(
    ("every_n_train_steps", "saved"), [(0, [2, 4, 6, 7]), (3, [2, 3, 5, 6, 7])]
)
def test_last_checkpoint_is_saved_by_wall_time_as_well_as_by_step(
    tmp_path: Path, every_n_train_steps: int, saved: list[int]
) -> None:
    """A step every 30 s and a save every minute: steps 2, 4, 6 by time, 7 at the end; with a
    save every 3 steps as well, 3 and 6 by step and 2 and 5 by time (the minute counts from the
    latest save, whichever made it)."""
    from test_precision import _dm, _module

    clock = Clock(30.0)
    last = LastCheckpoint(tmp_path, every_n_train_steps=every_n_train_steps, every_minutes=1)
    last.clock = clock
    steps: list[int] = []
    save = last._save

    def recorded(trainer: L.Trainer) -> None:
        steps.append(trainer.global_step)
        save(trainer)

    last._save = recorded  # type: ignore[method-assign]
    trainer = quiet_trainer(
        max_steps=7, limit_val_batches=0, enable_checkpointing=True, callbacks=[clock, last]
    )
    trainer.fit(_module(), datamodule=_dm())
    assert steps == saved
    assert (tmp_path / "last.ckpt").is_file()


@pytest.mark.parametrize(
    ("config", "overrides", "steps"),
    [
        ("train", [], 300),
        ("train", ["trainer=gpu"], 0),
        ("train", ["trainer=ddp_slurm"], 0),
        ("train", ["trainer=gpu", "callbacks.last_checkpoint.every_n_train_steps=50"], 50),
        ("train_flow", [], 80),
    ],
)
def test_last_checkpoint_period_settings(config: str, overrides: list[str], steps: int) -> None:
    """Every 5 minutes everywhere; also every N steps on a CPU (about a minute of training
    there), by time only on a GPU; a step period given on the command line applies anywhere."""
    from hydra.utils import instantiate

    cfg = compose(config, ["paths.output_dir=/tmp/unused", *overrides])
    last = instantiate(cfg.callbacks.last_checkpoint)
    assert last.every_seconds == 300.0 and last.every_n_train_steps == steps
    with pytest.raises(ValueError, match="every_minutes must be positive"):
        LastCheckpoint("/tmp/unused", every_minutes=0)
