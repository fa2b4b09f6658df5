"""``python -m mfg_lightning.data.check``: figures per split, problems listed, JSON last line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import run_module
from fake_datasets import make_kitti, make_vkitti, tree_snapshot
from mfg_lightning.core.config import compose
from mfg_lightning.data.check import check_dataset


def test_kitti_check_reports_every_split_and_computes_only_a_few_flows(tmp_path: Path) -> None:
    fake = make_kitti(tmp_path / "kitti")
    before = tree_snapshot(fake.root)
    proc = run_module(
        "mfg_lightning.data.check", "dataset=kitti", f"dataset.data_root={fake.root}",
        "flow.preset=ultrafast", "+check.samples=3", cwd=tmp_path,
    )  # fmt: skip
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["ok"] and report["problems"] == []
    splits = report["splits"]
    assert {k: v["samples"] for k, v in splits.items()} == {"train": 45, "val": 9, "test": 14}
    assert splits["test"]["per_sequence"] == {"09": 7, "10": 7}
    seq = splits["test"]["sequences"]["09"]
    assert seq["native_size"] == [64, 200] and seq["intrinsics_native"][0] == pytest.approx(180.0)
    assert seq["intrinsics_input"][0] == pytest.approx(180.0 * 128 / 200)
    assert splits["train"]["pose"]["translation_m"]["mean"] > 0
    assert splits["train"]["files_checked"] == 9 * 6  # frames 0–5 of each sequence's head
    # flow only for the few samples checked, which the report names
    flows = [sid for s in splits.values() for sid in s["flow_checked"]]
    assert len(flows) == 9 and all(sid.startswith("kitti/") for sid in flows)
    assert len(list((tmp_path / "cache").glob("kitti_flow/*/*@*/*.npy"))) == 9
    assert splits["train"]["flow"]["magnitude_px"]["mean"] == pytest.approx(1.33, abs=0.15)
    # a check writes nothing into the data or the working directory
    assert tree_snapshot(fake.root) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "kitti"]


def test_vkitti_check_lists_bad_files_without_stopping(tmp_path: Path) -> None:
    fake = make_vkitti(tmp_path / "vk", worlds=("0001", "0002", "0006"), n_frames=5)
    truncated = fake.file("flow", "0002", 1)
    truncated.write_bytes(truncated.read_bytes()[:150])
    fake.file("depth", "0006", 2).unlink()
    cfg = compose(
        "train", ["dataset=vkitti_objects", f"dataset.data_root={fake.root}",
                  "dataset.train_worlds=[0001,0006]", "dataset.test_worlds=[0002]"],
    )  # fmt: skip
    report = check_dataset(cfg.dataset, n_samples=8)
    assert not report["ok"]
    problems = "\n".join(report["problems"])
    assert "0002/clone/00001.png: truncated PNG" in problems  # the cheap check of every file
    assert "0006/clone: 1 depth file(s) missing: 00002.png" in problems
    assert "skipping vkitti/test/0002/1->2" in problems  # the full decode of the sampled ones
    test = report["splits"]["test"]
    assert test["samples"] == 4 and len(test["flow_checked"]) == 3
    assert test["sequences"]["0002"]["intrinsics_native"] == [725.0, 725.0, 620.5, 187.0]
    assert test["flow"]["depth_m"]["max"] == pytest.approx(655.35, abs=0.01)
    assert 0 < test["flow"]["object_fraction"] < 0.2
    assert 0.65 < test["pose"]["translation_m"]["mean"] < 0.75  # world 0002 drives 0.7 m/frame


def test_missing_root_is_one_error_and_a_json_line(tmp_path: Path) -> None:
    proc = run_module(
        "mfg_lightning.data.check", "dataset=vkitti", f"dataset.data_root={tmp_path / 'typo'}",
        cwd=tmp_path, check=False,
    )  # fmt: skip
    assert proc.returncode == 2
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert not report["ok"] and "is not a directory" in report["error"]
    assert "vkitti_1.3.1_flowgt/0001/clone/00000.png" in proc.stderr
    assert "Traceback" not in proc.stderr
