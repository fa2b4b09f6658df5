"""The small module, datamodule and corrupted flow that the in-process tests of the training
module share (tests/test_module.py, tests/test_precision.py, tests/ddp_worker.py, ...)."""

from __future__ import annotations

import functools
from typing import Any

import torch

from mfg_lightning.data.synthetic import SyntheticDataModule, SyntheticDrivingDataset
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg import MFG
from mfg_lightning.models.mfg_module import MFGLitModule


def small_module(loss: MFGLoss | None = None, fused: bool = True, **kw: Any) -> MFGLitModule:
    """A 32 × 64 network of 32 hidden units, trained by Adam (lr 1e-3; ``fused``: the kernel that
    skips a non-finite step on the device), no figures."""
    net = MFG(height=32, width=64, hidden_units=32, channels=(8, 8, 8, 16, 16))
    adam = functools.partial(torch.optim.Adam, lr=1e-3, **({"fused": True} if fused else {}))
    return MFGLitModule(net, loss or MFGLoss(w_s=1.0), adam, image_log_every_n_steps=0, **kw)


def small_datamodule(cls: type = SyntheticDataModule, **overrides: Any) -> SyntheticDataModule:
    """A 32 × 64 synthetic set of one training and one test sequence of 12 frames (9 training
    samples in batches of 4, 2 validation samples)."""
    options = dict(height=32, width=64, batch_size=4, eval_batch_size=8, train_sequences=1,
                   test_sequences=1, sequence_length=12, val_fraction=0.2)  # fmt: skip
    return cls(**{**options, **overrides})


class CorruptFlow(torch.utils.data.Dataset):
    """Synthetic samples whose flow is NaN in ``rows × cols`` (both channels) and infinite at
    the ``inf`` pixels ``(channel, row, col)``: a half-corrupt flow file, say."""

    def __init__(
        self,
        inner: SyntheticDrivingDataset,
        rows: slice,
        cols: slice,
        inf: tuple[tuple[int, int, int], ...] = (),
    ) -> None:
        self.inner, self.rows, self.cols, self.inf = inner, rows, cols, inf

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, i: int) -> dict:
        s = self.inner[i]
        s["flow"][:, self.rows, self.cols] = float("nan")
        for pixel in self.inf:
            s["flow"][pixel] = float("inf")
        return s


def corrupt_datamodule(
    rows: slice, cols: slice, inf: tuple[tuple[int, int, int], ...] = ()
) -> type[SyntheticDataModule]:
    """A :class:`SyntheticDataModule` class whose every split is a :class:`CorruptFlow`."""

    class CorruptDataModule(SyntheticDataModule):
        def build_dataset(self, split: str):
            return CorruptFlow(super().build_dataset(split), rows, cols, inf)

    return CorruptDataModule
