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


def _replace_line(path: Path, line: int, edit) -> None:
    lines = path.read_text().splitlines()
    lines[line - 1] = " ".join(edit(lines[line - 1].split()))
    path.write_text("\n".join(lines) + "\n")


def _scale_rotation_by_5(fields: list[str]) -> list[str]:
    m = [float(v) for v in fields[1:]]
    return [fields[0]] + [repr(v * 5 if i < 11 and i % 4 != 3 else v) for i, v in enumerate(m)]


def test_check_reports_a_scaled_rotation_and_a_duplicate_frame_with_file_and_line(
    tmp_path: Path,
) -> None:
    """Frame 2's rotation block scaled by 5 in ``0002_clone.txt`` printed OK (and made the
    ground truth 5.5× too long), and a duplicate frame was merged by ``int(frame)``."""
    fake = make_vkitti(tmp_path / "vk", worlds=("0001", "0002"), n_frames=4)
    scaled = fake.extrinsics_file("0002")
    _replace_line(scaled, 4, _scale_rotation_by_5)  # line 1 is the header: frame 2 is line 4
    duplicate = fake.extrinsics_file("0001")
    _replace_line(duplicate, 4, lambda fields: ["1", *fields[1:]])
    proc = run_module(
        "mfg_lightning.data.check", "dataset=vkitti", f"dataset.data_root={fake.root}",
        "dataset.train_worlds=[0002]", "dataset.test_worlds=[0001]", cwd=tmp_path, check=False,
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr[-2000:]
    problems = [line for line in proc.stdout.splitlines() if line.startswith("PROBLEM ")]
    assert f"PROBLEM train: {scaled}:4: the 3×3 block is not a rotation" in "\n".join(problems)
    assert f"PROBLEM test: {duplicate}:4: frame 1 does not follow 1 (line 3)" in "\n".join(problems)
    assert not json.loads(proc.stdout.strip().splitlines()[-1])["ok"]


def test_check_reports_a_focal_length_of_0_with_file_and_line(tmp_path: Path) -> None:
    """``calib.txt`` with ``fx = 0`` passed ``read_kitti_calib`` and ``data.check``."""
    fake = make_kitti(tmp_path / "kitti", n_frames=4)
    calib = fake.root / "sequences" / "09" / "calib.txt"
    _replace_line(calib, 3, lambda fields: [fields[0], "0.0", *fields[2:]])  # P2 is line 3
    cfg = compose("train", ["dataset=kitti", f"dataset.data_root={fake.root}"])
    report = check_dataset(cfg.dataset, n_samples=1)
    assert not report["ok"]
    line = f"{calib}:3: P2: focal lengths must be positive, got fx = 0, fy = 180"
    assert report["splits"]["test"]["error"] == line
    assert f"test: {line}" in report["problems"]
