"""Property-based tests (hypothesis) of the training step: every corrupt batch pushed through
a real ``Trainer.fit`` of the module (extreme or non-finite values in flow, pose, intrinsics or
depth; a tensor of the wrong shape or dtype) is either refused with a :class:`SampleError`
naming its samples, or masked / skipped so that every weight stays finite."""

from __future__ import annotations

import functools
import logging
import warnings
from typing import Any

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from conftest import quiet_trainer
from fuzz_readers import FUZZ
from mfg_lightning.data.base import collate_samples
from mfg_lightning.data.sample import SampleError
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg import MFG
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.run.agreed_steps import AgreedSteps, NonFiniteLossError

# --------------------------------------------------------------------------------------------
# Corrupt batches through a real training step
# --------------------------------------------------------------------------------------------

H, W, B = 32, 64, 2


@functools.lru_cache(maxsize=1)
def _clean_batch() -> dict[str, Any]:
    dm = SyntheticDataModule(
        height=H, width=W, train_sequences=1, test_sequences=1, sequence_length=6, val_fraction=0.2
    )
    return collate_samples([dm.dataset("train")[i] for i in range(B)])


def _copy(batch: dict[str, Any]) -> dict[str, Any]:
    return {k: v.clone() if isinstance(v, torch.Tensor) else list(v) for k, v in batch.items()}


_VALUES = st.sampled_from(
    [float("nan"), float("inf"), -float("inf"), 3.0e38, -3.0e38, 1e30, 1e20, 1e10, 0.0, -1e-30]
)


@st.composite
def corrupt_batches(draw: st.DrawFn) -> dict[str, Any]:
    """A synthetic batch with one or two corruptions: extreme or non-finite values in a random
    region of flow, pose, intrinsics or depth, or a tensor of the wrong shape or dtype."""
    batch = _copy(_clean_batch())
    for _ in range(draw(st.integers(1, 2))):
        kind = draw(st.sampled_from(["values", "values", "values", "shape", "dtype"]))
        key = draw(st.sampled_from(["flow", "pose", "intrinsics", "depth", "flow_valid"]))
        t = batch[key]
        if kind == "values" and t.dtype.is_floating_point and t.numel():  # (not emptied above)
            region = tuple(
                slice(draw(st.integers(0, n - 1)), draw(st.integers(1, n))) for n in t.shape
            )
            t[region] = draw(_VALUES)
        elif kind == "shape":
            dim = draw(st.integers(0, t.ndim - 1))
            size = draw(st.sampled_from([0, 1, 3, t.shape[dim] + 1]))
            if size <= t.shape[dim]:
                batch[key] = t.narrow(dim, 0, size)
            else:
                batch[key] = torch.cat([t, t.narrow(dim, 0, 1)], dim)
            if draw(st.booleans()):
                batch[key] = batch[key].unsqueeze(0)
        elif kind == "dtype":
            batch[key] = t.to(draw(st.sampled_from([torch.float64, torch.float16, torch.int32])))
    return batch


def _module() -> MFGLitModule:
    torch.manual_seed(0)
    net = MFG(height=H, width=W, hidden_units=32, channels=(8, 8, 8, 16, 16))
    return MFGLitModule(
        net,
        MFGLoss(w_s=100.0),
        functools.partial(torch.optim.Adam, lr=1e-3),
        image_log_every_n_steps=0,
        max_consecutive_nonfinite=2,
    )


@FUZZ
@given(batch=corrupt_batches())
def test_corrupt_batches_are_refused_or_masked_and_never_reach_the_weights(batch) -> None:
    model = _module()
    # Two steps on the same corrupt batch: the second one would see what the first did.
    loader = torch.utils.data.DataLoader([batch, batch], batch_size=None, collate_fn=lambda b: b)
    trainer = quiet_trainer(max_steps=2, limit_val_batches=0, callbacks=[AgreedSteps()])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            trainer.fit(model, train_dataloaders=loader)
        except SampleError as err:
            # Refused where it entered, naming the samples of the batch.
            assert "synthetic/" in str(err)
        except NonFiniteLossError as err:
            # Every step's loss was non-finite (e.g. a NaN pose): stopped, naming the samples.
            assert "synthetic/" in str(err)
    for name, p in model.named_parameters():
        assert torch.isfinite(p).all(), f"non-finite weight {name}"


@pytest.fixture(autouse=True)
def _quiet() -> Any:
    """Lightning's info lines and the module's masking warnings, once per example, are noise."""
    loggers = [logging.getLogger(n) for n in ("lightning", "lightning.pytorch", "mfg_lightning")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    yield
    for lg, level in zip(loggers, levels, strict=True):
        lg.setLevel(level)
