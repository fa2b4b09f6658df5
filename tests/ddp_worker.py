"""One process of a 2-process gloo run on the CPU, started by tests/test_gpu_path.py as torchrun
would start it (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT`` in
the environment: Lightning then joins the group instead of launching processes itself).

It trains the tiny network for a few steps under ``DDPStrategy`` with every call of
``torch.distributed.barrier`` and ``all_reduce`` made inside the module's ``training_step``
recorded (rank 1's loss is NaN in one step: both ranks must skip that step together), saves the
weights, and tests them on a one-sample test split, smaller than the number of processes, so
that rank 1 sees no test sample. It writes ``rank<r>.json`` into the folder given as its only
argument: the calls, the skipped steps and the ``test/*`` metrics.

Not a test module (no ``test_`` prefix): pytest does not collect it.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import lightning as L
import torch
import torch.distributed as dist
from lightning.pytorch.strategies import DDPStrategy
from torch.utils.data import Subset

from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.run.agreed_steps import AgreedSteps
from mfg_lightning.run.runs import set_baseline
from module_helpers import small_datamodule, small_module

#: training steps of the run; the step whose loss is NaN on rank 1 (1-based, as NaNLoss counts)
STEPS, NAN_STEP = 3, 2


class NaNOnRank1(MFGLoss):
    """The loss of call ``NAN_STEP`` is NaN on rank 1 only."""

    def __init__(self, rank: int) -> None:
        super().__init__(w_s=1.0)
        self.rank, self.calls = rank, 0

    def forward(self, *args: Any):
        terms = super().forward(*args)
        if not self.training:  # evaluation calls are not counted
            return terms
        self.calls += 1
        if self.rank == 1 and self.calls == NAN_STEP:
            return terms._replace(total=terms.total * float("nan"))
        return terms


class OneTestSample(SyntheticDataModule):
    """The tiny synthetic set with a test split of one sample."""

    def build_dataset(self, split: str):
        dataset = super().build_dataset(split)
        return Subset(dataset, [0]) if split == "test" else dataset


def datamodule() -> OneTestSample:
    return small_datamodule(OneTestSample, batch_size=2, eval_batch_size=4, sequence_length=8,
                            val_fraction=0.25)  # fmt: skip


def module(rank: int) -> MFGLitModule:
    torch.manual_seed(0)
    return small_module(NaNOnRank1(rank))


def record_collectives(model: MFGLitModule) -> dict[str, list[int]]:
    """Count, per training step, the barriers and all_reduces called from the start of
    ``training_step`` to the end of the step (the run's AgreedSteps agrees just before the
    optimiser step; DDP's gradient all-reduce runs in C++ during backward and is not counted)."""
    calls: dict[str, list[int]] = {"barrier": [], "all_reduce": []}
    inside = [False]
    for name in calls:
        original = getattr(dist, name)

        def counted(*args: Any, _name: str = name, _original: Any = original, **kwargs: Any):
            if inside[0]:
                calls[_name][-1] += 1
            return _original(*args, **kwargs)

        setattr(dist, name, counted)
    step = model.training_step

    def training_step(*args: Any, **kwargs: Any):
        for counts in calls.values():
            counts.append(0)
        inside[0] = True
        return step(*args, **kwargs)

    batch_end = model.on_train_batch_end

    def on_train_batch_end(*args: Any, **kwargs: Any):
        inside[0] = False
        return batch_end(*args, **kwargs)

    model.training_step = training_step  # type: ignore[method-assign]
    model.on_train_batch_end = on_train_batch_end  # type: ignore[method-assign]
    return calls


def main(out: Path) -> None:
    torch.set_num_threads(1)
    rank = int(os.environ["RANK"])
    model = module(rank)
    calls = record_collectives(model)
    steps = AgreedSteps()
    trainer = L.Trainer(
        callbacks=[steps],
        accelerator="cpu",
        devices=int(os.environ["WORLD_SIZE"]),
        strategy=DDPStrategy(process_group_backend="gloo"),
        max_steps=STEPS,
        limit_val_batches=0,
        log_every_n_steps=STEPS,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    dm = datamodule()
    set_baseline(model, dm)
    trainer.fit(model, datamodule=dm)
    trainer.save_checkpoint(out / "ddp.ckpt")
    skipped = steps.skipped
    trainer.test(model, datamodule=datamodule(), verbose=False)
    metrics = {
        k: (None if math.isnan(float(v)) else float(v))
        for k, v in trainer.callback_metrics.items()
        if k.startswith("test/")
    }
    result = {"calls": calls, "skipped_steps": skipped, "metrics": metrics}
    (out / f"rank{rank}.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
