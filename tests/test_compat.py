"""A run directory written by release 0.1 (before the package was laid out in folders) still
loads and evaluates with the same metrics.

``tests/fixtures/run_v0_1/`` is such a run, as ``python -m mfg_lightning.train debug=tiny``
wrote it at commit 499cc69 (a 16 × 32 input and 16 hidden units so that it stays small; machine
paths replaced by relative ones), and ``expected_evaluate_metrics.json`` what
``python -m mfg_lightning.evaluate ckpt_path=<run>/checkpoints/last.ckpt`` printed for it then.
Its configs name classes by their 0.1 modules (``mfg_lightning.losses.MFGLoss``,
``mfg_lightning.object_motion.ObjectMotionConfig``, ``mfg_lightning.callbacks.LastCheckpoint``).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import run_module
from mfg_lightning.run import checkpoints
from mfg_lightning.run.checkpoints import (
    MOVED_MODULES,
    load_checkpoint,
    module_from_checkpoint,
    moved_target,
    with_moved_targets,
)

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "run_v0_1"


@pytest.fixture
def run_v0_1(tmp_path: Path) -> Path:
    """A copy of the fixture run (the original stays untouched)."""
    return Path(shutil.copytree(FIXTURE, tmp_path / "run_v0_1"))


def _targets(node: object) -> list[str]:
    if isinstance(node, dict):
        own = [node["_target_"]] if isinstance(node.get("_target_"), str) else []
        return own + [t for v in node.values() for t in _targets(v)]
    if isinstance(node, list):
        return [t for v in node for t in _targets(v)]
    return []


def test_the_fixture_names_the_old_modules() -> None:
    """Otherwise the tests below would not test the rename map."""
    ckpt = load_checkpoint(FIXTURE / "checkpoints" / "last.ckpt")
    assert ckpt["mfg_model_config"]["loss"]["_target_"] == "mfg_lightning.losses.MFGLoss"
    assert ckpt["mfg_model_config"]["object_motion"]["_target_"] == (
        "mfg_lightning.object_motion.ObjectMotionConfig"
    )
    config = OmegaConf.to_container(OmegaConf.load(FIXTURE / "config.yaml"))
    assert "mfg_lightning.callbacks.LastCheckpoint" in _targets(config)


def _rebuilds_with_its_weights(path: Path) -> Any:
    """The module rebuilt from checkpoint ``path``, its state exactly the stored one."""
    module = module_from_checkpoint(path)
    stored = load_checkpoint(path)["state_dict"]
    assert set(module.state_dict()) == set(stored)
    for name, value in module.state_dict().items():
        assert torch.equal(value, stored[name]), name
    return module


def test_checkpoint_of_0_1_rebuilds_with_its_weights() -> None:
    module = _rebuilds_with_its_weights(FIXTURE / "checkpoints" / "last.ckpt")
    assert type(module.loss_fn).__module__ == "mfg_lightning.models.losses"
    assert module.model_config["loss"]["_target_"] == "mfg_lightning.models.losses.MFGLoss"


def test_every_project_target_of_a_0_1_run_config_resolves() -> None:
    """The run directory's config.yaml: every class it names, read through the rename map, is
    importable; the ones a checkpoint may build are on the allow-list."""
    from hydra.utils import get_class

    config = with_moved_targets(
        OmegaConf.to_container(OmegaConf.load(FIXTURE / "config.yaml")), "config.yaml"
    )
    project = [t for t in _targets(config) if t.startswith("mfg_lightning.")]
    assert len(project) >= 6
    for target in project:
        get_class(target)
    for key in ("dataset", "model", "object_motion"):
        checkpoints.check_targets(config[key], "config.yaml", key)  # raises if one is refused
    with pytest.raises(checkpoints.UnsafeConfigError, match="mfg_lightning.losses.MFGLoss"):
        # read without the rename map, the old name is refused (it no longer resolves)
        old = OmegaConf.to_container(OmegaConf.load(FIXTURE / "config.yaml"))
        checkpoints.check_targets(old["model"], "config.yaml", "model")


def test_moved_targets_map_module_prefixes_only() -> None:
    assert moved_target("mfg_lightning.losses.MFGLoss") == "mfg_lightning.models.losses.MFGLoss"
    assert moved_target("mfg_lightning.data.flow_io.read_flow") == "mfg_lightning.flow.io.read_flow"
    # a module that did not move, and one whose name only starts like a moved one
    assert moved_target("mfg_lightning.data.kitti.KittiDataModule") == (
        "mfg_lightning.data.kitti.KittiDataModule"
    )
    assert moved_target("mfg_lightning.object_motion_viz.save_png") == (
        "mfg_lightning.pictures.object_motion.save_png"
    )
    assert moved_target("torch.optim.Adam") == "torch.optim.Adam"
    for old, new in MOVED_MODULES.items():
        assert old != new and new.startswith("mfg_lightning.")


def test_run_directory_of_0_1_evaluates_with_the_same_metrics(
    run_v0_1: Path, tmp_path: Path
) -> None:
    _evaluates_as_expected(run_v0_1, FIXTURE / "expected_evaluate_metrics.json", tmp_path)


def _evaluates_as_expected(
    run: Path, expected_file: Path, tmp_path: Path, rel: float = 1e-5, abs_: float = 1e-7
) -> dict:
    """``evaluate`` on a run directory's ``last.ckpt``: the metrics written are those of
    ``expected_file`` within ``rel`` / ``abs_`` (NaN / None where they were undefined);
    returns them."""
    out = tmp_path / "eval"
    run_module(
        "mfg_lightning.evaluate", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
        "logger=none", f"hydra.run.dir={out}", cwd=tmp_path,
    )  # fmt: skip
    got = json.loads((out / "metrics.json").read_text())["metrics"]
    expected = json.loads(expected_file.read_text())
    assert set(got) == set(expected)
    for key, value in expected.items():
        if value is None or (isinstance(value, float) and math.isnan(value)):
            assert got[key] is None or math.isnan(got[key]), key
        else:
            assert got[key] == pytest.approx(value, rel=rel, abs=abs_), key
    return got


def test_run_config_of_0_1_gives_the_dataset_of_a_checkpoint_without_one(run_v0_1: Path) -> None:
    """Checkpoints older still carry no ``mfg_dataset_config``: the run's config.yaml (of 0.1)
    gives the dataset, as before the move."""
    path = run_v0_1 / "checkpoints" / "last.ckpt"
    ckpt = load_checkpoint(path)
    stored = ckpt.pop("mfg_dataset_config")
    from_run = checkpoints.dataset_config(ckpt, path)
    assert from_run is not None
    assert (
        from_run["_target_"]
        == stored["_target_"]
        == "mfg_lightning.data.synthetic.SyntheticDataModule"
    )
    for key in ("height", "width", "sequence_length", "offsets", "flow"):
        assert from_run[key] == stored[key], key


def test_loader_settings_alone_apply_to_the_checkpoints_own_dataset() -> None:
    """``trainer=gpu`` sets ``dataset.num_workers`` / ``pin_memory`` / ``persistent_workers``
    without a ``dataset=``: evaluate still builds the dataset the checkpoint was trained on."""
    from mfg_lightning.run.runs import checkpoint_datamodule

    path = FIXTURE / "checkpoints" / "last.ckpt"
    stored = checkpoints.dataset_config(load_checkpoint(path), path)
    partial = OmegaConf.create({"num_workers": 0, "pin_memory": True})
    dm = checkpoint_datamodule(partial, stored, path, eval_batch_size=3)
    assert type(dm).__name__ == "SyntheticDataModule"
    assert (dm.height, dm.width, dm.eval_batch_size) == (16, 32, 3)
    assert dm.pin_memory is True


#: A run directory of the format before the training module was split into its model, its
#: evaluation (metrics.motion_eval), its non-finite-loss policy (now run.agreed_steps) and the
#: precision rules (run.precision): ``python -m mfg_lightning.train debug=tiny dataset.height=16
#: dataset.width=32 model.net.hidden_units=16 model.net.channels=[4,4,8,8,8] logger=csv`` at
#: commit 2e171c7 (machine paths replaced by relative ones), and what ``mfg_lightning.evaluate``
#: printed for its ``last.ckpt`` then.
FIXTURE_0_2 = Path(__file__).resolve().parent / "fixtures" / "run_v0_2"


def test_checkpoint_of_0_2_rebuilds_with_its_weights_and_baseline() -> None:
    module = _rebuilds_with_its_weights(FIXTURE_0_2 / "checkpoints" / "last.ckpt")
    assert bool(module.has_mean_motion)  # the baseline travels with the weights


def test_run_directory_of_0_2_evaluates_with_the_same_metrics(tmp_path: Path) -> None:
    run = Path(shutil.copytree(FIXTURE_0_2, tmp_path / "run_v0_2"))
    expected = FIXTURE_0_2 / "expected_evaluate_metrics.json"
    got = _evaluates_as_expected(run, expected, tmp_path, rel=1e-6, abs_=1e-9)
    assert "test/ate" in got and "test/baseline_trans_err" in got


def test_the_run_configs_model_keywords_are_still_accepted() -> None:
    """Every constructor keyword a stored model config names (0.1's and 0.2's) still builds."""
    for fixture in (FIXTURE, FIXTURE_0_2):
        config = with_moved_targets(
            OmegaConf.to_container(OmegaConf.load(fixture / "config.yaml")), "config.yaml"
        )
        checkpoints.check_targets(config["model"], "config.yaml", "model")
        # read as the project reads an older config (its null top_k is 1.0 now)
        module = instantiate(checkpoints.with_legacy_settings(config["model"], "config.yaml"))
        assert module.top_k == 1.0 and module.hparams.get("fp16_init_scale") in (None, 16.0)
        # the checkpoints are still chosen by the validation ATE the module logs
        assert config["callbacks"]["model_checkpoint"]["monitor"] == "val/ate"
