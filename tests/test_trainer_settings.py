"""The trainer settings a run checks before it builds anything: the precisions it accepts
(``*-true`` low precisions refused with one line, nothing written) and the GPU trainer configs
(cuDNN's benchmark off under ``trainer.deterministic``; ``bench/gpu_check.py`` on a CPU:
tests/test_gpu_path.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from mfg_lightning.core.config import compose
from mfg_lightning.core.errors import user_error_message
from mfg_lightning.run.precision import check_precision
from mfg_lightning.run.training import check_trainer_settings, train


@pytest.mark.parametrize("value", ["bf16-true", "16-true", "64-true", "transformer-engine"])
def test_unsupported_precisions_are_refused_naming_the_key(value: str, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=rf"^trainer\.precision={value} is refused") as err:
        check_precision(value)
    if value.endswith("-true") and value != "64-true":
        assert "poses, intrinsics and depth" in str(err.value)
    # The training run refuses it before it builds or writes anything: one error line.
    cfg = compose("train", ["debug=tiny", f"paths.output_dir={tmp_path / 'r'}"])
    cfg.trainer.precision = value
    with pytest.raises(ValueError) as err:
        train(cfg)
    assert user_error_message(err.value).startswith(f"trainer.precision={value} is refused")
    assert not (tmp_path / "r").exists()


def test_accepted_precisions_and_lightning_aliases() -> None:
    for value, name in [
        ("32-true", "32-true"),
        (32, "32-true"),
        ("bf16", "bf16-mixed"),
        ("bf16-mixed", "bf16-mixed"),
        ("16", "16-mixed"),
        ("16-mixed", "16-mixed"),
    ]:
        assert check_precision(value) == name


def _raw(node: Any, key: str) -> Any:
    """``node[key]`` as written, interpolations unresolved."""
    from omegaconf import OmegaConf

    return OmegaConf.to_container(node, resolve=False)[key]


def test_gpu_trainer_configs() -> None:
    cfg = compose("train", ["trainer=gpu", "paths.output_dir=/tmp/unused"])
    assert cfg.trainer.accelerator == "gpu" and cfg.trainer.benchmark is True
    assert cfg.dataset.pin_memory and cfg.dataset.persistent_workers
    # the workers follow the usable cores (mfg_lightning.core.machine.loader_workers), at most 6
    assert _raw(cfg.dataset, "num_workers") == "${loader_workers:6}"
    assert 0 <= cfg.dataset.num_workers <= 6
    assert cfg.dataset._target_.endswith("SyntheticDataModule")  # merged into the dataset
    user = compose("train", ["trainer=gpu", "dataset.num_workers=1", "paths.output_dir=/tmp/u"])
    assert user.dataset.num_workers == 1  # the command line wins
    ddp = compose("train", ["trainer=ddp_gpu", "paths.output_dir=/tmp/unused"])
    assert ddp.trainer.strategy.process_group_backend == "nccl"
    assert ddp.trainer.accelerator == "gpu" and ddp.dataset.pin_memory
    # several nodes: the same loader settings and cuDNN benchmark as one node, num_nodes set
    nodes = compose("train", ["trainer=ddp_slurm", "paths.output_dir=/tmp/unused"])
    assert nodes.trainer.strategy.process_group_backend == "nccl" and nodes.trainer.num_nodes == 2
    assert nodes.trainer.benchmark is True and nodes.dataset.pin_memory
    assert nodes.dataset.persistent_workers
    assert _raw(nodes.dataset, "num_workers") == _raw(ddp.dataset, "num_workers")
    assert _raw(ddp.dataset, "num_workers") == "${loader_workers:4,${trainer.devices}}"
    det = compose("train", ["trainer=gpu", "trainer.deterministic=true", "paths.output_dir=/tmp/u"])
    check_trainer_settings(det)
    assert det.trainer.benchmark is False
