"""Checkpoints: rebuilt from their own config, read safely (no pickle payload runs, no config
target outside the allow-list is built), for every entry point that reads one."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from omegaconf import OmegaConf

from conftest import REPO, run_module
from mfg_lightning.core.config import compose
from mfg_lightning.run.checkpoints import (
    CheckpointError,
    CheckpointSizeError,
    ModelSize,
    UnsafeConfigError,
    allowed_targets,
    check_targets,
    config_group_targets,
    dataset_config,
    load_checkpoint,
    module_from_checkpoint,
)
from mfg_lightning.run.runs import build_model


class WritesAFile:
    """A pickle payload: unpickling it calls ``Path.write_text(marker, ...)``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "the checkpoint ran code"))


def _tiny_checkpoint(path: Path) -> dict:
    """A checkpoint as train writes it (weights and resolved model config), without training."""
    cfg = compose("train", ["debug=tiny", f"paths.output_dir={path.parent}"])
    module = build_model(cfg)
    ckpt = {
        "state_dict": module.state_dict(),
        "hyper_parameters": {"model_config": module.model_config},
    }
    torch.save(ckpt, path)
    return ckpt


def test_module_from_checkpoint_rebuilds_it(tmp_path: Path) -> None:
    ckpt = _tiny_checkpoint(tmp_path / "tiny.ckpt")
    module = module_from_checkpoint(tmp_path / "tiny.ckpt", expected=ModelSize(64, 32, 64))
    assert not module.training
    for key, value in ckpt["state_dict"].items():
        torch.testing.assert_close(module.state_dict()[key], value)


def test_checkpoint_of_another_model_size_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "tiny.ckpt"
    ckpt = _tiny_checkpoint(path)
    # the caller expects the quick-start size
    with pytest.raises(CheckpointSizeError) as err:
        module_from_checkpoint(path, expected=ModelSize(1000, 48, 128))
    message = str(err.value)
    assert str(path) in message
    assert (
        "hidden_units=64, input 32×64" in message and "hidden_units=1000, input 48×128" in message
    )
    # weights that do not fit the checkpoint's own config (a config from another run)
    ckpt["hyper_parameters"]["model_config"]["net"]["hidden_units"] = 32
    torch.save(ckpt, path)
    with pytest.raises(CheckpointSizeError) as err:
        module_from_checkpoint(path)
    message = str(err.value)
    assert str(path) in message
    assert "hidden_units=32" in message and "weights with hidden_units=64" in message
    # not a checkpoint of this project at all
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(CheckpointError, match="not written by mfg_lightning.train"):
        module_from_checkpoint(tmp_path / "other.ckpt")
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        module_from_checkpoint(tmp_path / "missing.ckpt")


def test_every_target_of_the_project_configs_is_allowed() -> None:
    """The allow-list is the config groups' classes: a config group whose class is missing from
    it could not be evaluated, and a new dataset is allowed by its config file alone."""
    from hydra.utils import get_object

    groups = ("model", "dataset", "flow", "object_motion")
    files = [f for g in groups for f in sorted((REPO / "conf" / g).glob("*.yaml"))]
    assert files

    def targets(node):
        if isinstance(node, dict):
            if isinstance(node.get("_target_"), str):
                yield node["_target_"]
            for value in node.values():
                yield from targets(value)
        elif isinstance(node, list):
            for value in node:
                yield from targets(value)

    found = {t for f in files for t in targets(yaml.safe_load(f.read_text()) or {})}
    assert "mfg_lightning.models.mfg_module.MFGLitModule" in found
    assert "mfg_lightning.models.mfg.MFG" in found  # nested under model.net
    assert config_group_targets() == found
    for target in found:
        assert get_object(target) in allowed_targets(), target
    assert get_object("torch.optim.AdamW") in allowed_targets()
    assert get_object("torch.optim.lr_scheduler.OneCycleLR") in allowed_targets()
    # a class the project has but no config group builds is not allowed
    assert get_object("mfg_lightning.run.callbacks.LastCheckpoint") not in allowed_targets()


@pytest.mark.parametrize(
    "target",
    ["builtins.open", "subprocess.run", "os.system", "pathlib.Path.write_text", "no.such.thing"],
)
def test_targets_outside_the_allow_list_are_refused_at_any_depth(target: str) -> None:
    cfg = {
        "_target_": "mfg_lightning.models.mfg_module.MFGLitModule",
        "loss": {
            "_target_": "mfg_lightning.models.losses.MFGLoss",
            "extra": [{"_target_": target}],
        },
    }
    with pytest.raises(UnsafeConfigError) as err:
        check_targets(cfg, "somewhere.ckpt")
    assert "somewhere.ckpt" in str(err.value)
    assert f"loss.extra[0]._target_ = {target!r}" in str(err.value)
    # an alias of an allowed class resolves to it and passes
    check_targets({"_target_": "torch.optim.adam.Adam", "_partial_": True}, "x")


def test_a_pickle_payload_is_never_unpickled(tmp_path: Path) -> None:
    path = tmp_path / "evil.ckpt"
    marker = tmp_path / "marker.txt"
    ckpt = _tiny_checkpoint(path)
    torch.save({**ckpt, "payload": WritesAFile(marker)}, path)
    with pytest.raises(CheckpointError, match="other than tensors and plain data") as err:
        load_checkpoint(path)
    assert str(path) in str(err.value) and "Unsupported global: GLOBAL" in str(err.value)
    assert not marker.exists()


def test_checkpoints_written_by_training_load_safely(trained: Path) -> None:
    """A real training's checkpoint (Lightning's loops, callbacks, optimiser and scheduler state)
    holds only tensors and plain data, and its stored configs pass the allow-list. (The
    module's one tiny training, :func:`trained`, serves the crafted checkpoints below too.)"""
    path = trained / "checkpoints" / "last.ckpt"
    ckpt = torch.load(path, map_location="cpu", weights_only=True)  # no allow-listed types
    assert ckpt["hyper_parameters"]["model_config"]["net"]["hidden_units"] == 64
    module = module_from_checkpoint(path)
    assert module.dataset_config["_target_"].endswith("SyntheticDataModule")


def test_the_dataset_config_falls_back_to_the_run_directory(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    path = run / "checkpoints" / "last.ckpt"
    ckpt = _tiny_checkpoint(path)
    assert dataset_config(ckpt, path) is None
    cfg = compose("train", ["debug=tiny", f"paths.output_dir={run}"])
    dataset = OmegaConf.to_container(cfg.dataset, resolve=True)
    (run / "config.yaml").write_text(yaml.safe_dump({"dataset": dataset}))
    assert dataset_config(ckpt, path)["height"] == 32


# --------------------------------------------------------------------------------------------
# Crafted checkpoints against every entry point that reads one
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real tiny run directory (checkpoints and config.yaml)."""
    root = tmp_path_factory.mktemp("trained")
    run_module("mfg_lightning.train", "debug=tiny", f"hydra.run.dir={root / 'run'}", cwd=root)
    return root / "run"


def _crafted(trained: Path, tmp_path: Path, kind: str) -> tuple[Path, Path]:
    """A copy of the run directory whose checkpoint (or config.yaml) is crafted to write
    ``marker`` if any of it ran."""
    run = tmp_path / "shared_run"
    shutil.copytree(trained, run)
    path = run / "checkpoints" / "last.ckpt"
    marker = tmp_path / "marker.txt"
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    opener = {"_target_": "builtins.open", "file": str(marker), "mode": "w"}
    if kind == "pickle":
        ckpt["payload"] = WritesAFile(marker)
    elif kind == "model_target":
        ckpt["hyper_parameters"]["model_config"]["loss"]["w_t"] = opener
    elif kind == "run_config_target":
        del ckpt["mfg_dataset_config"]
        cfg = yaml.safe_load((run / "config.yaml").read_text())
        cfg["dataset"]["flow_writer"] = opener
        (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    torch.save(ckpt, path)
    return path, marker


ENTRY_POINTS = {
    "evaluate": ("mfg_lightning.evaluate",),
    "analyze_basis": ("mfg_lightning.analyze_basis",),
    "train": ("mfg_lightning.train", "debug=tiny", "trainer.max_steps=6"),
    "predict": (
        "mfg_lightning.predict",
        "dataset=synthetic",
        "dataset.height=32",
        "dataset.width=64",
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("entry", "kind"),
    [
        ("evaluate", "pickle"),
        ("evaluate", "model_target"),
        ("evaluate", "run_config_target"),
        ("analyze_basis", "pickle"),
        ("analyze_basis", "model_target"),
        ("analyze_basis", "run_config_target"),
        ("train", "pickle"),
        ("predict", "pickle"),
        ("predict", "model_target"),
    ],
)
def test_crafted_checkpoints_end_in_one_error_line(
    trained: Path, tmp_path: Path, entry: str, kind: str
) -> None:
    path, marker = _crafted(trained, tmp_path, kind)
    module, *extra = ENTRY_POINTS[entry]
    proc = run_module(
        module,
        *extra,
        f"ckpt_path={path}",
        f"hydra.run.dir={tmp_path / 'out'}",
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-3000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr[-3000:]
    assert (
        str(path if kind != "run_config_target" else path.parents[1] / "config.yaml") in errors[0]
    )
    assert "Traceback" not in proc.stderr
    assert not marker.exists()


def test_checkpoints_of_earlier_versions_still_load(tmp_path: Path) -> None:
    """Before configs were kept plain, ``hyper_parameters`` held Hydra's optimiser and scheduler
    partials and OmegaConf nodes; those few types stay readable (and none of them is called)."""
    from hydra.utils import instantiate

    path = tmp_path / "old.ckpt"
    ckpt = _tiny_checkpoint(path)
    cfg = OmegaConf.create(
        {
            "optimizer": {"_target_": "torch.optim.Adam", "_partial_": True, "betas": [0.9, 0.99]},
            "scheduler": {
                "_target_": "torch.optim.lr_scheduler.CosineAnnealingLR",
                "_partial_": True,
                "T_max": 4,
            },
        }
    )
    old = {
        "optimizer": instantiate(cfg.optimizer, _convert_="none"),
        "scheduler": instantiate(cfg.scheduler),
        "betas": cfg.optimizer.betas,
        "top_k": None,
    }
    # and their model config beside them, under mfg_model_config
    stored = ckpt["hyper_parameters"]["model_config"]
    torch.save({**ckpt, "hyper_parameters": old, "mfg_model_config": stored}, path)
    loaded = load_checkpoint(path)
    assert loaded["hyper_parameters"]["optimizer"].func is torch.optim.Adam
    assert list(loaded["hyper_parameters"]["betas"]) == [0.9, 0.99]
    module_from_checkpoint(path)


def test_settings_newer_than_a_checkpoint_keep_its_old_behaviour(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A checkpoint written before a setting existed is rebuilt with the value it was trained
    with, whatever today's default, and the log says so."""
    path = tmp_path / "old.ckpt"
    ckpt = _tiny_checkpoint(path)
    for key in ("init", "align_corners", "input_scale"):
        del ckpt["hyper_parameters"]["model_config"]["net"][key]
    del ckpt["hyper_parameters"]["model_config"]["loss"]["balance_squared"]
    torch.save(ckpt, path)
    with caplog.at_level("WARNING", logger="mfg_lightning.run.checkpoints"):
        module = module_from_checkpoint(path)
    assert module.net.align_corners is False and module.net.input_scale == 1.0
    assert module.loss_fn.balance_squared is True
    assert module.model_config["net"]["init"] == "torch"
    assert "predates model.net.init, model.net.align_corners" in caplog.text
    # a checkpoint that has them is read as stored, silently
    caplog.clear()
    ckpt = _tiny_checkpoint(path)
    ckpt["hyper_parameters"]["model_config"]["net"]["align_corners"] = True
    torch.save(ckpt, path)
    with caplog.at_level("WARNING", logger="mfg_lightning.run.checkpoints"):
        assert module_from_checkpoint(path).net.align_corners is True
    assert "predates" not in caplog.text


def test_dataset_configs_from_before_the_flow_group_read_their_flow(tmp_path: Path) -> None:
    """Checkpoints written before ``conf/flow`` stored the flow settings as dataset keys."""
    from mfg_lightning.data.synthetic import SyntheticDataModule
    from mfg_lightning.run.checkpoints import with_legacy_dataset_settings

    path = tmp_path / "old.ckpt"
    ckpt = _tiny_checkpoint(path)
    cfg = compose("train", ["debug=tiny", f"paths.output_dir={tmp_path}"])
    old = OmegaConf.to_container(cfg.dataset, resolve=True)
    del old["flow"]
    old.update(noise_std=0.5, outlier_fraction=0.02)
    ckpt["mfg_dataset_config"] = old
    read = dataset_config(ckpt, path)
    assert read["flow"] == {"source": "exact", "noise_std": 0.5, "outlier_fraction": 0.02}
    assert "noise_std" not in read
    dm = SyntheticDataModule(**{k: v for k, v in read.items() if k != "_target_"})
    assert dm.flow.noise_std == 0.5
    kitti = {"_target_": "mfg_lightning.data.kitti.KittiDataModule", "dis_preset": "fast"}
    kitti.update(dis_params=None, flow_height=None, flow_width=None, flow_dir=None)
    dis = {"source": "dis", "preset": "fast", "params": None, "height": None, "width": None}
    assert with_legacy_dataset_settings(kitti, path)["flow"] == dis
    kitti["flow_dir"] = "/data/flow"
    files = {"source": "files", "dir": "/data/flow"}
    assert with_legacy_dataset_settings(kitti, path)["flow"] == files


def test_synthetic_test_offsets_is_read_as_offsets(tmp_path: Path, caplog) -> None:
    """Synthetic configs stored before ``dataset.offsets`` (one name with KITTI's) had
    ``test_offsets``: read as ``offsets``, with a warning."""
    from mfg_lightning.data.synthetic import SyntheticDataModule

    path = tmp_path / "old.ckpt"
    ckpt = _tiny_checkpoint(path)
    cfg = compose("train", ["debug=tiny", f"paths.output_dir={tmp_path}"])
    old = OmegaConf.to_container(cfg.dataset, resolve=True)
    del old["offsets"]
    old["test_offsets"] = [-2, -1, 1, 2]
    ckpt["mfg_dataset_config"] = old
    with caplog.at_level("WARNING", logger="mfg_lightning.run.checkpoints"):
        read = dataset_config(ckpt, path)
    assert read["offsets"] == [-2, -1, 1, 2] and "test_offsets" not in read
    assert "dataset.test_offsets is now dataset.offsets" in caplog.text
    dm = SyntheticDataModule(**{k: v for k, v in read.items() if k != "_target_"})
    assert {b - a for _, a, b in dm.dataset("test").samples} == {-2, -1, 1, 2}


def test_random_bytes_are_called_corrupt_and_a_payload_unsafe(tmp_path: Path) -> None:
    """Random bytes given to ``evaluate ckpt_path=`` were described as a file that "holds Python
    objects … could run code", and ``train`` said "truncated?". What ``evaluate``
    (:func:`load_checkpoint`) and ``train`` (``resolve_ckpt_path``) read now says corrupt for
    bytes that are not a checkpoint, and unsafe for a pickle that would run code."""
    import pickle

    from mfg_lightning.run.training import resolve_ckpt_path

    rng = np.random.default_rng(0)
    random = tmp_path / "random.ckpt"
    random.write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    for read in (load_checkpoint, lambda p: resolve_ckpt_path(str(p), tmp_path)):
        with pytest.raises(CheckpointError) as err:
            read(random)
        message = str(err.value)
        assert f"checkpoint {random} is corrupt: not a readable checkpoint" in message
        assert "unsafe" not in message and "run code" not in message
    # a checkpoint cut short is corrupt too, in one line without torch's advice
    whole = tmp_path / "whole.ckpt"
    _tiny_checkpoint(whole)
    cut = tmp_path / "cut.ckpt"
    cut.write_bytes(whole.read_bytes()[:-100])
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(cut)
    assert str(err.value) == (
        f"checkpoint {cut} is corrupt: not a readable checkpoint (truncated, or not written by "
        "torch.save: PytorchStreamReader failed reading zip archive: failed finding central "
        "directory); it was not loaded"
    )
    # a bare pickle (no zip archive) that would run code is unsafe in every protocol, read by
    # either; torch's safe loader stops at protocol 4's first opcode before it sees the global
    marker = tmp_path / "marker.txt"
    for protocol in range(pickle.HIGHEST_PROTOCOL + 1):
        bare = tmp_path / f"bare{protocol}.ckpt"
        bare.write_bytes(pickle.dumps({"state_dict": WritesAFile(marker)}, protocol=protocol))
        for read in (load_checkpoint, lambda p: resolve_ckpt_path(str(p), tmp_path)):
            with pytest.raises(CheckpointError, match=f"checkpoint {bare} is unsafe: it holds"):
                read(bare)
    assert not marker.exists()
