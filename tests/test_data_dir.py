"""Data in one place: ``paths.data_dir`` (``$MFG_DATA_DIR``, else ``./data``) holds the datasets,
the dataset configs default their ``data_root`` below it, and a git-ignored
``conf/local/default.yaml`` can set it once for a machine."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.utils import instantiate

from conftest import REPO, run_module
from fake_datasets import make_kitti
from mfg_lightning.core.config import CONFIG_DIR, compose
from mfg_lightning.core.data_errors import DataRootError


def test_dataset_configs_default_below_the_data_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MFG_DATA_DIR", str(tmp_path))
    for name, sub in (
        ("kitti", "kitti/dataset"),
        ("vkitti", "vkitti"),
        ("vkitti_objects", "vkitti"),
    ):
        cfg = compose("train", [f"dataset={name}"])
        assert cfg.paths.data_dir == str(tmp_path)
        assert cfg.dataset.data_root == f"{tmp_path}/{sub}", name
    # unset: ./data, read from the directory the command starts in
    monkeypatch.delenv("MFG_DATA_DIR")
    assert compose("train", ["dataset=kitti"]).dataset.data_root == "data/kitti/dataset"
    # a data_root given on the command line still wins
    cfg = compose("train", ["dataset=kitti", "dataset.data_root=/elsewhere/kitti/dataset"])
    assert cfg.dataset.data_root == "/elsewhere/kitti/dataset"


def test_a_kitti_tree_in_the_data_dir_is_found_without_data_root(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # KITTI odometry's zips unpacked in data/kitti/: data/kitti/dataset/{sequences,poses}
    fake = make_kitti(tmp_path / "data" / "kitti" / "dataset")  # 00–10, 8 frames each
    monkeypatch.setenv("MFG_DATA_DIR", str(tmp_path / "data"))
    cfg = compose("train", ["dataset=kitti", f"paths.cache_dir={tmp_path / 'cache'}"])
    datamodule = instantiate(cfg.dataset)
    test = datamodule.build_dataset("test")
    assert len(test) == 2 * 7  # 09 and 10, pairs 0→1 … 6→7
    assert Path(cfg.dataset.data_root) == fake.root
    # the entry point a user types, in a fresh process, reads the variable the same way
    proc = run_module(
        "mfg_lightning.data.check", "dataset=kitti", "flow.preset=ultrafast", "+check.samples=1",
        cwd=tmp_path,
    )  # fmt: skip
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["ok"] and report["data_root"] == str(fake.root)
    assert report["splits"]["test"]["samples"] == 14


def test_a_missing_tree_names_the_path_and_what_to_type(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MFG_DATA_DIR", str(tmp_path / "nowhere"))
    cfg = compose("train", ["dataset=kitti", f"paths.cache_dir={tmp_path / 'cache'}"])
    with pytest.raises(DataRootError) as err:
        instantiate(cfg.dataset).build_dataset("train")
    text = str(err.value)
    missing = tmp_path / "nowhere" / "kitti" / "dataset"
    assert f"dataset.data_root={missing} is not a directory" in text
    assert "dataset.data_root=/data/kitti/dataset" in text and "MFG_DATA_DIR" in text
    # a relative default is shown with the directory it is read from
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MFG_DATA_DIR")
    cfg = compose("train", ["dataset=vkitti", f"paths.cache_dir={tmp_path / 'cache'}"])
    with pytest.raises(DataRootError, match=rf"data/vkitti \(relative to {tmp_path}\)"):
        instantiate(cfg.dataset).build_dataset("train")


def test_conf_local_is_optional_git_ignored_and_overrides(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The repository's conf/local/ holds no YAML of its own: a user's file there is ignored by git.
    local = REPO / "conf" / "local"
    assert (local / ".gitkeep").is_file()
    ignored = subprocess.run(
        ["git", "check-ignore", "-q", "conf/local/default.yaml"], cwd=REPO, check=False
    )
    assert ignored.returncode == 0
    # On a copy of the configs (not to disturb other tests): a local file sets paths.data_dir
    # for every entry point that reads data, and the command line still wins over it. The
    # tests compose no local file (conftest: MFG_LOCAL_CONFIG=none); this one does, as a user.
    monkeypatch.delenv("MFG_LOCAL_CONFIG")
    conf = tmp_path / "conf"
    shutil.copytree(CONFIG_DIR, conf)
    (conf / "local" / "default.yaml").write_text(
        "# @package _global_\npaths:\n  data_dir: /mnt/datasets\n"
    )
    with initialize_config_dir(version_base="1.3", config_dir=str(conf)):
        for name in ("train", "check", "evaluate", "predict"):
            cfg = hydra_compose(config_name=name, overrides=["dataset=kitti", "ckpt_path=x"])
            assert cfg.dataset.data_root == "/mnt/datasets/kitti/dataset", name
        for name in ("analyze_basis", "export"):
            assert hydra_compose(config_name=name).paths.data_dir == "/mnt/datasets", name
        cfg = hydra_compose(config_name="train", overrides=["dataset=kitti", "paths.data_dir=/d"])
        assert cfg.dataset.data_root == "/d/kitti/dataset"
