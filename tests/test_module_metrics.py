"""The module's logged metrics do not move when its code is reorganised.

``fixtures/module_metrics.json`` holds every metric the module logged, captured before the
module's evaluation, non-finite-loss policy and precision rules moved to their own homes:

- ``fixture``: the 0.1 run's checkpoint (``fixtures/run_v0_1``) validated and tested on its own
  dataset, in-process;
- ``tiny_run``: a seeded 4-step training (fused Adam, so the in-optimiser skip path runs, object
  motion on) of a small network on a small synthetic dataset, then its test.

They must agree to a relative 1e-6 (the CPU's results, one thread). Regenerate only on purpose:
``python tests/test_module_metrics.py`` (it rewrites the file).
"""

from __future__ import annotations

import functools
import json
import math
import sys
from pathlib import Path
from typing import Any

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from conftest import quiet_trainer

HERE = Path(__file__).resolve().parent
FIXTURE = HERE / "fixtures" / "run_v0_1"
EXPECTED = HERE / "fixtures" / "module_metrics.json"


def _metrics(trainer: Any) -> dict[str, float]:
    return {k: float(v) for k, v in sorted(trainer.callback_metrics.items())}


def fixture_metrics(cache: Path) -> dict[str, float]:
    """Validation and test metrics of the 0.1 fixture's checkpoint on its dataset."""
    from mfg_lightning.run.checkpoints import (
        dataset_config,
        load_checkpoint,
        module_from_checkpoint,
    )
    from mfg_lightning.run.runs import checkpoint_datamodule

    path = FIXTURE / "checkpoints" / "last.ckpt"
    module = module_from_checkpoint(path)
    stored = dataset_config(load_checkpoint(path), path)
    dm = checkpoint_datamodule(None, stored, path, cache_dir=str(cache))
    trainer = quiet_trainer()
    trainer.validate(module, datamodule=dm, verbose=False)
    out = _metrics(trainer)
    trainer.test(module, datamodule=dm, verbose=False)
    out.update(_metrics(trainer))
    return out


def tiny_run_metrics(root: Path) -> dict[str, float]:
    """A seeded 4-step training with validation, then its test."""
    from mfg_lightning.data.synthetic import SyntheticDataModule
    from mfg_lightning.models.losses import MFGLoss
    from mfg_lightning.models.mfg import MFG
    from mfg_lightning.models.mfg_module import MFGLitModule
    from mfg_lightning.motion.object_motion import ObjectMotionConfig

    torch.manual_seed(0)
    net = MFG(height=32, width=64, hidden_units=32, channels=(8, 8, 8, 16, 16))
    module = MFGLitModule(
        net,
        MFGLoss(w_s=1.0),
        functools.partial(torch.optim.Adam, lr=1e-3, fused=True),
        image_log_every_n_steps=0,
        object_motion=ObjectMotionConfig(),
    )
    dm = SyntheticDataModule(
        height=32, width=64, batch_size=4, eval_batch_size=8, train_sequences=1,
        test_sequences=1, sequence_length=12, val_fraction=0.2, cache_dir=str(root / "cache"),
    )  # fmt: skip
    module.set_mean_motion(*dm.mean_motion("train"))  # the baseline, given explicitly
    trainer = quiet_trainer(
        max_steps=4, log_every_n_steps=1, limit_val_batches=2, val_check_interval=2,
        default_root_dir=root,
    )  # fmt: skip
    trainer.fit(module, datamodule=dm)
    out = _metrics(trainer)
    trainer.test(module, datamodule=dm, verbose=False)
    out.update({f"test_after_fit:{k}": v for k, v in _metrics(trainer).items()})
    return out


def _compare(got: dict[str, float], expected: dict[str, float]) -> None:
    assert set(got) == set(expected)
    for key, value in expected.items():
        if math.isnan(value):
            assert math.isnan(got[key]), key
        else:
            # rel 1e-5: float32 reductions differ between CPU kinds (AVX2 against AVX-512
            # kernels) by ~1e-6 relative in a standard deviation; a real change moves far more
            assert got[key] == pytest.approx(value, rel=1e-5, abs=1e-12), key


@pytest.mark.slow
def test_the_fixture_checkpoint_scores_as_before(tmp_path: Path) -> None:
    _compare(fixture_metrics(tmp_path / "cache"), json.loads(EXPECTED.read_text())["fixture"])


@pytest.mark.slow
def test_a_tiny_run_scores_as_before(tmp_path: Path) -> None:
    _compare(tiny_run_metrics(tmp_path), json.loads(EXPECTED.read_text())["tiny_run"])


if __name__ == "__main__":
    import tempfile

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        result = {
            "fixture": fixture_metrics(Path(tmp) / "cache"),
            "tiny_run": tiny_run_metrics(Path(tmp)),
        }
    EXPECTED.write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(json.dumps(result, indent=1, sort_keys=True))
