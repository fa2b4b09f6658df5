"""A checkpoint's place in an epoch counts batches of its own size, dataset and sampler: a resume
inside that epoch with other ones is refused in one line naming the key and both values, or, with
``resume_restart_epoch=true``, starts the epoch again with the new settings.

The loader on its own, then real trainings through the entry point (a run of 8 steps, resumed
with another batch size: refused, then restarted on request).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mfg_lightning.data.resumable_loader import (
    EpochShuffleSampler,
    ResumableDataLoader,
    ResumeMismatchError,
    restarting_epochs,
)
from resume_runs import RUN, _ckpt, _train


def _stopped_in_epoch_1(data: torch.Tensor) -> dict:
    """The state of a loader of ``data`` (seed 5, batches of 4) 3 batches into epoch 1."""
    loader = ResumableDataLoader(data, seed=5, batch_size=4)
    loader.order.set_epoch(1)
    batches = iter(loader)
    for _ in range(3):
        next(batches)
    return loader.state_dict()


@pytest.mark.parametrize(
    ("other", "message"),
    [
        (
            ResumableDataLoader(torch.arange(18), seed=5, batch_size=2),
            "dataset.batch_size: the checkpoint was trained with 4, this run asks for 2",
        ),
        (
            ResumableDataLoader(torch.arange(20), seed=5, batch_size=4),
            "dataset (training samples): the checkpoint was trained with 18, this run asks for 20",
        ),
        (
            ResumableDataLoader(list(range(18)), seed=5, batch_size=4),
            "dataset: the checkpoint was trained with Tensor, this run asks for list",
        ),
        (
            ResumableDataLoader(torch.arange(18), seed=6, batch_size=4),
            "sampler (dataset.seed): the checkpoint was trained with EpochShuffleSampler(seed=5), "
            "this run asks for EpochShuffleSampler(seed=6)",
        ),
    ],
    ids=["batch_size", "samples", "dataset", "sampler"],
)
def test_a_resume_inside_an_epoch_with_other_batches_is_refused_naming_the_key(
    other: ResumableDataLoader, message: str
) -> None:
    state = _stopped_in_epoch_1(torch.arange(18))
    with pytest.raises(ResumeMismatchError) as err:
        other.load_state_dict(state)
    text = str(err.value)
    assert text.startswith(f"{message}; the checkpoint stopped 3 batches into epoch 1")
    assert "resume_restart_epoch=true" in text and "\n" not in text


def test_resume_restart_epoch_starts_the_epoch_again_and_an_epochs_end_needs_no_override() -> None:
    data = torch.arange(18)
    state = _stopped_in_epoch_1(data)
    epoch_1 = EpochShuffleSampler(18, 5).permutation(1).tolist()

    restarted = ResumableDataLoader(data, seed=5, batch_size=2)
    with restarting_epochs(True):
        restarted.load_state_dict(state)
    restarted.order.set_epoch(1)
    batches = [batch.tolist() for batch in restarted]
    assert len(batches) == 9 and [i for b in batches for i in b] == epoch_1  # whole, by 2
    with pytest.raises(ResumeMismatchError):  # the override holds inside its block only
        ResumableDataLoader(data, seed=5, batch_size=2).load_state_dict(state)

    # Saved at the end of epoch 1: nothing of it is left to skip, the new size applies at once.
    at_end = ResumableDataLoader(data, seed=5, batch_size=2)
    at_end.load_state_dict({**state, "batches": 5})
    at_end.order.set_epoch(2)
    epoch_2 = EpochShuffleSampler(18, 5).permutation(2).tolist()
    assert [i for b in at_end for i in b.tolist()] == epoch_2


@pytest.mark.slow
def test_a_training_resumed_with_another_batch_size_is_refused_then_restarts_on_request(
    tmp_path: Path,
) -> None:
    run = tmp_path / "run"
    last = run / "checkpoints" / "last.ckpt"
    # 8 steps of batches of 4 (5 an epoch): last.ckpt sits 3 batches into epoch 1
    _train(*RUN, "trainer.max_steps=8", f"hydra.run.dir={run}", cwd=tmp_path)
    other = (*RUN, "ckpt_path=last", "dataset.batch_size=2", f"hydra.run.dir={run}")
    kept = {name: (run / name).read_bytes() for name in ("config.yaml", "run_info.json")}

    refused = _train(*other, cwd=tmp_path, check=False)
    assert refused.returncode == 2, refused.stderr[-3000:]
    errors = [line for line in refused.stderr.splitlines() if line.startswith("error: ")]
    assert errors == [
        "error: dataset.batch_size: the checkpoint was trained with 4, this run asks for 2; the "
        "checkpoint stopped 3 batches into epoch 1: resume with the checkpoint's settings, or "
        "with resume_restart_epoch=true to restart that epoch from its beginning with this run's"
    ], refused.stderr[-3000:]
    assert "Traceback" not in refused.stderr
    assert _ckpt(last)["global_step"] == 8  # nothing trained, nothing saved
    # refused before anything is written: the run's record is the one it trained with
    assert {name: (run / name).read_bytes() for name in kept} == kept

    _train(*other, "resume_restart_epoch=true", "trainer.max_steps=12", cwd=tmp_path)
    saved = _ckpt(last)
    (order,) = saved["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    # steps 9-12 were the first 4 batches of 2 of epoch 1, started again from its beginning
    assert saved["global_step"] == 12
    assert (order["epoch"], order["batches"], order["batch_size"]) == (1, 4, 2)
