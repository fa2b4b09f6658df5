"""Prediction without ground truth: ``mfg_lightning.predict`` on a KITTI tree without ``poses/``
(the layout of sequences 11-21), on a plain folder of images, and with depth (object masks);
the loaders' poses-optional split and its errors."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from conftest import run_module
from fake_datasets import make_kitti, tree_snapshot
from mfg_lightning.core import geometry
from mfg_lightning.core.data_errors import DataRootError
from mfg_lightning.data.image_folder import ImageFolderDataModule, NoGroundTruthError
from mfg_lightning.data.kitti import KittiDataModule
from mfg_lightning.run.prediction import MOTION_COLUMNS, PredictionError, gather
from mfg_lightning.trajectory import trajectories
from mfg_lightning.trajectory.pose_io import read_kitti_poses, read_poses, read_tum_poses

H, W = 32, 64  # the input size of debug=tiny


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("trained")
    run_module("mfg_lightning.train", "debug=tiny", "logger=none", "test=false",
               f"hydra.run.dir={tmp / 'run'}", cwd=tmp)  # fmt: skip
    return tmp / "run" / "checkpoints" / "last.ckpt"


def _kitti_without_poses(root: Path, sequences: tuple[str, ...], n_frames: int) -> Path:
    make_kitti(root, sequences=sequences, n_frames=n_frames)
    shutil.rmtree(root / "poses")  # KITTI ships poses for 00-10 only
    return root


def _motions(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array(rows[1:], np.float64)


def _check_outputs(out: Path, seq: str, n_frames: int, times: np.ndarray) -> None:
    """The trajectory files parse with the project's readers, have one pose per frame, agree
    with each other and with the per-frame motions."""
    kitti = read_kitti_poses(out / "poses" / "kitti" / f"{seq}.txt")
    assert read_poses(out / "poses" / "kitti" / f"{seq}.txt").format == "kitti"
    stamps, tum = read_tum_poses(out / "poses" / "tum" / f"{seq}.txt")
    assert kitti.shape == tum.shape == (n_frames, 4, 4)
    np.testing.assert_allclose(stamps, times, atol=1e-12)
    np.testing.assert_allclose(kitti[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(tum, kitti, atol=1e-9)  # quaternions round-trip the rotations
    header, table = _motions(out / "motions" / f"{seq}.csv")
    assert tuple(header) == MOTION_COLUMNS and table.shape == (n_frames - 1, 9)
    np.testing.assert_array_equal(table[:, 0], np.arange(n_frames - 1))
    np.testing.assert_array_equal(table[:, 1], table[:, 0] + 1)
    # the trajectory is the composition of the motions of the CSV
    motion = trajectories.motions_from_poses(torch.from_numpy(kitti))
    t, w = geometry.pose_to_motion(motion)
    np.testing.assert_allclose(t.numpy(), table[:, 3:6], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(w.numpy(), table[:, 6:9], rtol=1e-5, atol=1e-9)
    assert np.isfinite(table).all() and np.abs(table[:, 3:]).max() > 0


# --------------------------------------------------------------------------------------------
# The entry point (slow: a real tiny training first)
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_predict_on_a_kitti_tree_without_poses(ckpt: Path, tmp_path: Path) -> None:
    root = _kitti_without_poses(tmp_path / "kitti", ("11", "12"), n_frames=7)
    before = tree_snapshot(root)
    out = tmp_path / "pred"
    proc = run_module(
        "mfg_lightning.predict", f"ckpt_path={ckpt}", "dataset=kitti", f"dataset.data_root={root}",
        "dataset.test_sequences=[11,12]", f"dataset.height={H}", f"dataset.width={W}",
        "flow.preset=ultrafast", f"hydra.run.dir={out}", cwd=tmp_path,
    )  # fmt: skip
    assert "11: 7 poses" in proc.stdout and "12: 7 poses" in proc.stdout
    for seq in ("11", "12"):
        # TUM timestamps from the sequence's times.txt (0.1 s steps in the fake tree)
        _check_outputs(out, seq, 7, 0.1 * np.arange(7))
    assert not (out / "masks").exists()  # KITTI has no depth
    summary = json.loads((out / "predict.json").read_text())
    assert summary["split"] == "predict" and set(summary["sequences"]) == {"11", "12"}
    assert tree_snapshot(root) == before  # nothing written into the dataset
    # the flow went through KITTI's cache, as in training
    assert len(list((tmp_path / "cache" / "kitti_flow").glob("*/*@*/*.npy"))) == 2 * 6


@pytest.mark.slow
def test_predict_on_a_folder_of_images(ckpt: Path, tmp_path: Path) -> None:
    fake = make_kitti(tmp_path / "kitti", sequences=("00",), n_frames=11)
    frames = tmp_path / "my drive"
    frames.mkdir()
    for k in range(11):  # names whose natural order is not their string order
        shutil.copy(fake.image("00", k), frames / f"frame{k}.png")
    (frames / "notes.txt").write_text("not a frame")
    fx, fy, cx, cy = fake.intrinsics
    out = tmp_path / "pred"
    run_module(
        "mfg_lightning.predict", f"ckpt_path={ckpt}", "dataset=image_folder",
        f"dataset.data_root={frames}", f"dataset.fx={fx}", f"dataset.fy={fy}",
        f"dataset.cx={cx}", f"dataset.cy={cy}", "dataset.frame_rate=5", "dataset.sequence=drive",
        f"dataset.height={H}", f"dataset.width={W}", f"hydra.run.dir={out}", cwd=tmp_path,
    )  # fmt: skip
    _check_outputs(out, "drive", 11, np.arange(11) / 5.0)


@pytest.mark.slow
def test_predict_with_depth_writes_object_masks(ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "pred"
    run_module(
        "mfg_lightning.predict", f"ckpt_path={ckpt}", "dataset=synthetic",
        "dataset.test_sequences=1", "dataset.sequence_length=8", f"dataset.height={H}",
        f"dataset.width={W}", f"hydra.run.dir={out}", cwd=tmp_path,
    )  # fmt: skip
    _check_outputs(out, "test00", 8, np.arange(8) / 10.0)
    masks = sorted((out / "masks" / "test00").glob("*.png"))
    assert [m.name for m in masks] == [f"{k:06d}.png" for k in range(7)]
    images = [cv2.imread(str(m), cv2.IMREAD_UNCHANGED) for m in masks]
    assert all(m.shape == (H, W) and m.dtype == np.uint8 for m in images)
    assert set(np.unique(np.stack(images))) <= {0, 255}


@pytest.mark.slow
def test_predict_with_ground_truth_draws_and_scores_aligned_trajectories(
    ckpt: Path, tmp_path: Path
) -> None:
    out = tmp_path / "pred"
    common = ["dataset=synthetic", "dataset.test_sequences=1", "dataset.sequence_length=8",
              f"dataset.height={H}", f"dataset.width={W}",
              "predict.object_masks=false"]  # fmt: skip
    run_module("mfg_lightning.predict", f"ckpt_path={ckpt}", *common, "predict.align=sim3",
               f"hydra.run.dir={out}", cwd=tmp_path)  # fmt: skip
    summary = json.loads((out / "predict.json").read_text())
    assert summary["align"] == "sim3"
    metrics = summary["metrics"]
    for key in ("ate_traj", "rpe_trans", "rpe_rot", "test00/ate_traj", "test00/ate_traj_scale"):
        assert metrics[key] is not None and metrics[key] >= 0, key
    # One sequence: the pooled values are its own; the fitted scale is a similarity's.
    assert metrics["ate_traj"] == pytest.approx(metrics["test00/ate_traj"], rel=1e-12)
    assert metrics["test00/ate_traj_scale"] > 0
    for kind in ("trajectory", "drift", "error"):
        assert (out / "trajectories" / f"{kind}_test00.png").read_bytes()[:4] == b"\x89PNG"
    # A mode that does not exist is one error line, before anything is predicted.
    proc = run_module("mfg_lightning.predict", f"ckpt_path={ckpt}", *common, "predict.align=7dof",
                      f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path, check=False)  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == (
        "error: predict.align='7dof': use one of none, se3, sim3, scale, scale_7dof, sim3_scale"
    )
    assert not (tmp_path / "bad" / "predict.json").exists()


@pytest.mark.slow
def test_an_input_size_other_than_the_networks_is_one_error_line(
    ckpt: Path, tmp_path: Path
) -> None:
    root = _kitti_without_poses(tmp_path / "kitti", ("11",), n_frames=4)
    before = tree_snapshot(root)
    proc = run_module("mfg_lightning.predict", f"ckpt_path={ckpt}", "dataset=kitti",
                      f"dataset.data_root={root}", "dataset.test_sequences=[11]",
                      f"hydra.run.dir={tmp_path / 'pred'}", cwd=tmp_path, check=False)  # fmt: skip
    assert proc.returncode == 2
    (line,) = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert line == (
        f"error: dataset.height×width is 48×128 but the network of {ckpt} takes 32×64: pass "
        "dataset.height=32 dataset.width=64"
    )
    assert not (tmp_path / "pred" / "poses").exists() and tree_snapshot(root) == before


# --------------------------------------------------------------------------------------------
# Loaders without poses (fast)
# --------------------------------------------------------------------------------------------


def test_kitti_predict_split_reads_sequences_without_poses(tmp_path: Path) -> None:
    root = _kitti_without_poses(tmp_path / "kitti", ("00", "11"), n_frames=5)
    dm = KittiDataModule(root, height=H, width=W, test_sequences=["11"], train_sequences=["00"],
                         offsets=[-1, 1], cache_dir=tmp_path / "cache")  # fmt: skip
    ds = dm.dataset("predict")
    assert [(a, b) for _, a, b in ds.samples] == [(0, 1), (1, 2), (2, 3), (3, 4)]
    sample = ds[0]
    assert "pose" not in sample and sample["flow"].shape == (2, H, W)
    assert not ds.has_poses()
    np.testing.assert_allclose(ds.timestamps("11"), 0.1 * np.arange(5))
    with pytest.raises(DataRootError, match="no ground-truth poses for sequence.s. 11"):
        ds.relative_poses()
    # training and evaluation need the pose files, and say where they are missing
    for split in ("test", "train"):
        with pytest.raises(DataRootError) as err:
            dm.dataset(split)
        assert "Training and evaluation need ground-truth poses" in str(err.value)
    assert next(iter(dm.predict_dataloader()))["flow"].shape == (4, 2, H, W)


def test_kitti_predict_split_keeps_poses_when_there_are_some(tmp_path: Path) -> None:
    fake = make_kitti(tmp_path / "kitti", sequences=("09",), n_frames=4)
    dm = KittiDataModule(fake.root, height=H, width=W, test_sequences=["09"],
                         train_sequences=["00"], cache_dir=tmp_path / "cache")  # fmt: skip
    ds = dm.dataset("predict")
    assert ds.has_poses() and ds.relative_poses().shape == (3, 4, 4)


def test_image_folder_frames_in_natural_order_and_only_for_prediction(tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    image = np.zeros((20, 40, 3), np.uint8)
    for k in (1, 2, 10):
        cv2.imwrite(str(frames / f"img{k}.png"), image + k)
    camera = {"fx": 50, "fy": 50, "cx": 20, "cy": 10, "height": H, "width": W}
    dm = ImageFolderDataModule(frames, **camera, times=None, cache_dir=str(tmp_path / "cache"))
    ds = dm.dataset("predict")
    assert [ds.image_path("frames", k).name for k in range(3)] == ["img1.png", "img2.png",
                                                                   "img10.png"]  # fmt: skip
    assert ds.samples == [("frames", 0, 1), ("frames", 1, 2)]
    # intrinsics scaled from the native 40×20 to the input size like KITTI's (pixel centres)
    sx, sy = W / 40, H / 20
    expected = [50 * sx, 50 * sy, (20 + 0.5) * sx - 0.5, (10 + 0.5) * sy - 0.5]
    np.testing.assert_allclose(ds.intrinsics("frames"), expected, rtol=1e-6)
    np.testing.assert_allclose(ds.timestamps("frames"), [0.0, 0.1, 0.2])
    for split in ("train", "val", "test"):
        with pytest.raises(NoGroundTruthError, match="mfg_lightning.predict"):
            dm.dataset(split)
    # another pattern selects other files: another cache key
    other = ImageFolderDataModule(
        frames, **camera, pattern="img1*.png", cache_dir=str(tmp_path / "cache")
    )
    assert other.dataset("predict").cache.root != ds.cache.root
    (tmp_path / "times.txt").write_text("1.0\n2.0\n")
    bad = ImageFolderDataModule(
        frames, **camera, times=str(tmp_path / "times.txt"), cache_dir=str(tmp_path)
    )
    with pytest.raises(ValueError, match="2 timestamps for 3 frames"):
        bad.dataset("predict").timestamps("frames")


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"fx": None}, "dataset.fx not set"),
        ({"fy": -3.0}, "dataset.fy must be finite"),
        ({"cx": "left"}, "dataset.cx must be a number"),
    ],
)
def test_image_folder_intrinsics_are_checked(kwargs: dict, message: str) -> None:
    camera = {"fx": 50.0, "fy": 50.0, "cx": 20.0, "cy": 10.0, **kwargs}
    with pytest.raises(ValueError, match=message):
        ImageFolderDataModule("unused", **camera)


def test_image_folder_needs_frames(tmp_path: Path) -> None:
    dm = ImageFolderDataModule(tmp_path, fx=1, fy=1, cx=1, cy=1, cache_dir=str(tmp_path))
    with pytest.raises(ValueError, match=r"0 file\(s\) match dataset.pattern='\*.png'"):
        dm.dataset("predict")
    with pytest.raises(DataRootError, match="not set"):
        ImageFolderDataModule(None, fx=1, fy=1, cx=1, cy=1).dataset("predict")


def test_a_missing_pair_is_an_error_not_a_broken_trajectory() -> None:
    def batch(frames: list[int], step: int = 1) -> dict:
        f = torch.tensor(frames)
        return {"sequence": ["a"] * len(frames), "frame": f, "target": f + step,
                "t": torch.zeros(len(frames), 3), "omega": torch.zeros(len(frames), 3)}  # fmt: skip

    assert len(gather([batch([2, 3]), None, batch([0, 1])])["a"].frames) == 4  # any batch order
    with pytest.raises(PredictionError, match="no prediction from frame 2 to 3"):
        gather([batch([0, 1]), batch([3, 4])])
    with pytest.raises(PredictionError, match="a pair 0 → 2"):
        gather([batch([0, 1], step=2)])
    with pytest.raises(PredictionError, match="every sample was skipped"):
        gather([None])
