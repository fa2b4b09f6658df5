"""The private Lightning attributes this project relies on still exist and still do their job.

``pyproject.toml`` bounds ``lightning`` to the tested minor releases; this is the test to run
before widening the bound. Each attribute below is read or patched by the project, and a newer
Lightning without it would turn a fix off silently (most uses fall back without an error):

* ``mfg_lightning.run.together``: ``Trainer._signal_connector`` and its ``_sigterm_notifier_fn``
  (the SIGTERM handler Lightning composes), ``received_sigterm``, the epoch loop's
  ``_broadcast_sigterm_tensor``, ``DDPStrategy._ddp_kwargs``, the launcher's ``procs`` and
  ``kill``, and the ``_child_processes`` of the ``_ChildProcessObserver`` thread;
* ``mfg_lightning.run.callbacks``: the epoch loop's ``_should_check_val_fx`` and the fit loop's
  ``_data_fetcher`` (when ``last.ckpt`` is saved);
* ``mfg_lightning.run.progress``: ``RichProgressBar``'s ``_trainer``, ``_get_train_description``,
  ``_initialize_train_progress_bar_id`` and ``_update_metrics``.
"""

from __future__ import annotations

import inspect
import os
from typing import Any

import lightning as L
import pytest
from lightning.fabric.strategies.launchers import subprocess_script as fabric_launchers
from lightning.fabric.strategies.launchers.subprocess_script import _ChildProcessObserver
from lightning.pytorch.callbacks import RichProgressBar
from lightning.pytorch.loops.training_epoch_loop import _TrainingEpochLoop
from lightning.pytorch.strategies import DDPStrategy
from lightning.pytorch.strategies.launchers import subprocess_script
from lightning.pytorch.trainer.connectors.signal_connector import _SignalConnector

from conftest import quiet_trainer
from mfg_lightning.run.callbacks import _validation_follows
from module_helpers import small_datamodule, small_module


def _source(obj: Any) -> str:
    return inspect.getsource(obj)


def test_the_signal_connector_and_the_epoch_loop_have_what_stop_together_patches() -> None:
    # StopTogether replaces _sigterm_notifier_fn: Lightning must still build its handler from it
    assert callable(getattr(_SignalConnector, "_sigterm_notifier_fn", None))
    assert "self._sigterm_notifier_fn" in _source(_SignalConnector.register_signal_handlers)
    # ... and turns off the per-step broadcast of rank 0's flag, which the loop must still call
    assert callable(getattr(_TrainingEpochLoop, "_broadcast_sigterm_tensor", None))
    assert "self._broadcast_sigterm_tensor()" in _source(_TrainingEpochLoop)
    assert callable(getattr(_TrainingEpochLoop, "_should_check_val_fx", None))

    trainer = quiet_trainer(max_steps=1)
    connector = trainer._signal_connector
    assert isinstance(connector, _SignalConnector) and connector.received_sigterm is False
    assert trainer.received_sigterm is False  # the public view of the same flag
    connector.received_sigterm = True
    assert trainer.received_sigterm is True


def test_the_ddp_strategy_and_its_launcher_have_what_ending_together_uses() -> None:
    trainer = quiet_trainer(strategy="ddp", devices=2, max_steps=1)
    strategy = trainer.strategy
    assert isinstance(strategy, DDPStrategy)
    assert isinstance(strategy._ddp_kwargs, dict)  # BuffersWhereNeeded sets a key in it
    launcher = strategy.launcher
    assert isinstance(launcher, subprocess_script._SubprocessScriptLauncher)
    assert launcher.procs == [] and callable(launcher.kill)
    # _take_over_the_watch finds Lightning's watch by its class name and empties its list: the
    # launcher must still start that class, and an empty list must end the watch
    assert "_launch_process_observer(self.procs)" in _source(launcher.launch)
    assert "_ChildProcessObserver(" in _source(fabric_launchers._launch_process_observer)
    observer = _ChildProcessObserver(main_pid=os.getpid(), child_processes=[])
    assert observer._child_processes == [] and observer._run() is True


def test_the_progress_bar_has_what_run_progress_bar_overrides_and_calls() -> None:
    for name in ("_get_train_description", "_initialize_train_progress_bar_id", "_update_metrics"):
        assert callable(getattr(RichProgressBar, name, None)), name
    assert hasattr(RichProgressBar(), "_trainer")


class _AskValidationFollows(L.Callback):
    """Records, after every training step, what LastCheckpoint learns from Lightning's private
    ``_should_check_val_fx`` (None: it could not ask, and would fall back to saving twice), and
    after which steps a validation did run."""

    def __init__(self) -> None:
        self.answers: dict[int, bool | None] = {}
        self.validated: list[int] = []

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        self.answers[trainer.global_step] = _validation_follows(trainer)

    def on_validation_start(self, trainer: L.Trainer, *args: Any) -> None:
        if not trainer.sanity_checking:
            self.validated.append(trainer.global_step)


@pytest.mark.slow
def test_last_checkpoint_can_ask_lightning_whether_a_validation_follows_a_step() -> None:
    ask = _AskValidationFollows()
    trainer = quiet_trainer(max_steps=6, val_check_interval=2, limit_val_batches=1, callbacks=[ask])
    trainer.fit(small_module(), datamodule=small_datamodule())  # 3 batches an epoch
    assert None not in ask.answers.values() and len(ask.answers) == 6
    assert [step for step, follows in ask.answers.items() if follows] == ask.validated != []


def test_reduced_epoch_logs_silences_lightnings_sync_dist_advice_for_its_names_only() -> None:
    """``models.epoch_logs.reduced_epoch_logs`` matches the advice's text as Lightning words it
    (read from its source here, so that a rewording fails this test, not the filter silently)."""
    import re
    import warnings

    from lightning.fabric.utilities.warnings import PossibleUserWarning
    from lightning.pytorch.trainer.connectors.logger_connector import result

    from mfg_lightning.models.epoch_logs import reduced_epoch_logs

    src = _source(result._ResultCollection._get_cache)
    template = re.search(r'f"(It is recommended to use `self\.log\(\{[^"]*)"', src)
    assert template, "Lightning no longer words its sync_dist advice as reduced_epoch_logs expects"

    def advice(name: str) -> str:
        return template.group(1).replace("{result_metric.meta.name!r}", repr(name))

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        reduced_epoch_logs("val/", "test/")
        for name in ("val/ate", "test/flow_epe", "train/loss"):
            warnings.warn(advice(name), PossibleUserWarning, stacklevel=1)
    assert [str(w.message) for w in seen] == [advice("train/loss")]
    with pytest.raises(ValueError, match="at least one name prefix"):
        reduced_epoch_logs()
