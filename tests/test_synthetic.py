"""The synthetic driving dataset: determinism and ground-truth consistency."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import pytest
import torch
from hydra.utils import instantiate

from conftest import KITTI_POSES, NO_KITTI_POSES
from mfg_lightning.core import geometry
from mfg_lightning.core.config import compose
from mfg_lightning.data.base import EmptySplitError
from mfg_lightning.data.sample import check_sample
from mfg_lightning.data.synthetic import SyntheticDataModule, SyntheticDrivingDataset
from mfg_lightning.run.runs import build_model, build_trainer

SHARED_POSES = KITTI_POSES


def _dm(**kw) -> SyntheticDataModule:
    base = dict(
        height=32,
        width=96,
        train_sequences=2,
        test_sequences=1,
        sequence_length=20,
        flow={"source": "exact", "noise_std": 0.0, "outlier_fraction": 0.0},
    )
    base.update(kw)
    return SyntheticDataModule(**base)


def test_samples_follow_the_schema_and_are_deterministic() -> None:
    ds = _dm().dataset("train")
    a, b = ds[3], ds[3]
    check_sample(a, 32, 96)
    for key, value in a.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, b[key]), key
    # Another datamodule with the same seed yields the same sample; another seed does not.
    assert torch.equal(_dm().dataset("train")[3]["flow"], a["flow"])
    assert not torch.equal(_dm(seed=1).dataset("train")[3]["flow"], a["flow"])


def test_flow_minus_object_motion_is_the_rigid_reprojection_flow() -> None:
    ds = _dm(scene={"moving_objects": 4}).dataset("train")
    found_objects = 0
    for i in range(0, 30, 3):
        s = ds[i]
        rigid = geometry.reprojection_flow(
            s["depth"][None].double(), s["pose"][None].double(), s["intrinsics"][None].double()
        )[0]
        v = s["flow_valid"]
        residual = (s["flow"] - s["object_flow"]).double() - rigid
        assert residual[:, v].abs().max() < 1e-3
        # Off the moving objects, the object flow is zero.
        assert s["object_flow"][:, ~s["object_mask"]].abs().max() == 0
        found_objects += int(s["object_mask"].any())
    assert found_objects > 0


def test_ground_truth_pose_matches_the_trajectory() -> None:
    dm = _dm()
    ds = dm.dataset("test")
    seq, src, tgt = ds.samples[5]
    traj = ds.trajectories[seq]
    expected = torch.linalg.inv(traj[src]) @ traj[tgt]
    torch.testing.assert_close(ds[5]["pose"].double(), expected, atol=1e-6, rtol=0)
    # Driving forward: t_z > 0 on average.
    assert dm.mean_motion("train")[0][2] > 0


def test_splits_are_disjoint_and_test_is_ordered_sequences() -> None:
    dm = _dm(val_fraction=0.25)
    train, val, test = (dm.dataset(s) for s in ("train", "val", "test"))
    train_keys = {(s, a) for s, a, _ in train.samples}
    val_keys = {(s, a) for s, a, _ in val.samples}
    assert not train_keys & val_keys
    assert {s for s, _, _ in test.samples}.isdisjoint({s for s, _, _ in train.samples})
    for indices in test.sequences().values():
        frames = [test.samples[i][1] for i in indices]
        assert frames == sorted(frames) and frames == list(
            range(frames[0], frames[0] + len(frames))
        )


def test_central_frame_offsets() -> None:
    dm = _dm(offsets=[-2, -1, 1, 2], val_fraction=0.25)
    ds = dm.dataset("test")
    assert {b - a for _, a, b in ds.samples} == {-2, -1, 1, 2}
    # dataset.offsets, as dataset=kitti's, sets every split; the default stays t -> t + 1
    for split in ("train", "val"):
        assert {b - a for _, a, b in dm.dataset(split).samples} == {-2, -1, 1, 2}, split
    for split in ("train", "val", "test"):
        assert {b - a for _, a, b in _dm().dataset(split).samples} == {1}, split
    with pytest.raises(ValueError, match="dataset.offsets must be distinct non-zero"):
        _dm(offsets=[0, 1])


def test_frame_stride_thins_training_only(tmp_path: Path) -> None:
    """``dataset.frame_stride=3``: train keeps the source frames 0, 3, 6, … of every trajectory
    with all offsets; validation and test keep every frame (validation's frame-by-frame ATE needs
    five consecutive frames); train+val, which prepare_data fills, is their union; the flow cache
    is the same as at stride 1 (same worlds, same pairs)."""
    full = _dm(offsets=[-2, -1, 1, 2], val_fraction=0.25)
    thin = _dm(offsets=[-2, -1, 1, 2], val_fraction=0.25, frame_stride=3)
    want = [s for s in full.build_dataset("train").samples if s[1] % 3 == 0]
    assert thin.build_dataset("train").samples == want
    assert want and len(want) < len(full.build_dataset("train").samples)
    assert thin.build_dataset("val").samples == full.build_dataset("val").samples
    sources = sorted({k for _, k, _ in thin.build_dataset("val").samples})
    assert sources == list(range(sources[0], sources[-1] + 1)) and len(sources) >= 5
    union = thin.build_dataset("train").samples + thin.build_dataset("val").samples
    assert sorted(union) == sorted(thin.build_dataset("train+val").samples)
    assert thin.dataset("test").samples == full.dataset("test").samples
    dis = {"source": "dis", "height": 64, "width": 192}
    roots = {
        _dm(flow=dis, frame_stride=s, cache_dir=str(tmp_path)).build_dataset("train").cache.root
        for s in (1, 3)
    }
    assert len(roots) == 1
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="dataset.frame_stride must be a positive integer"):
            _dm(frame_stride=bad)


class _RecordOffsets(L.Callback):
    """The ``target - frame`` offsets of every training batch."""

    def __init__(self) -> None:
        self.offsets: list[int] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self.offsets += (batch["target"] - batch["frame"]).tolist()


@pytest.mark.slow
@pytest.mark.parametrize("flow", [["flow=exact"], ["flow=dis", "flow.height=64", "flow.width=128"]])
def test_training_on_plus_minus_one_and_two_offsets(tmp_path: Path, flow: list[str]) -> None:
    """The reproduction study's synthetic training on ±1, ±2 offsets, with exact and with DIS
    flow: a short real training whose training samples carry those offsets."""
    cfg = compose(
        "train",
        ["debug=tiny", "dataset.offsets=[-2,-1,1,2]", "logger=none", "callbacks=none", *flow,
         f"paths.output_dir={tmp_path}", f"paths.cache_dir={tmp_path / 'cache'}"],
    )  # fmt: skip
    dm = instantiate(cfg.dataset)
    recorder = _RecordOffsets()
    trainer = build_trainer(cfg, [recorder], [])
    trainer.fit(build_model(cfg), datamodule=dm)
    assert trainer.global_step == cfg.trainer.max_steps
    assert len(recorder.offsets) == cfg.trainer.max_steps * cfg.dataset.batch_size
    assert set(recorder.offsets) <= {-2, -1, 1, 2} and len(set(recorder.offsets)) > 1
    assert {b - a for _, a, b in dm.dataset("train").samples} == {-2, -1, 1, 2}


def test_noise_and_outliers_corrupt_the_flow() -> None:
    clean = _dm().dataset("train")[0]
    noisy = _dm(flow={"noise_std": 1.0, "outlier_fraction": 0.1}).dataset("train")[0]
    diff = (clean["flow"] - noisy["flow"]).norm(dim=0)
    assert 0.5 < diff.median() < 2.0
    assert (diff > 5).float().mean() > 0.02


@pytest.mark.skipif(not SHARED_POSES.is_dir(), reason=NO_KITTI_POSES)
def test_real_kitti_trajectories() -> None:
    dm = _dm(
        trajectory="kitti",
        poses_dir=str(SHARED_POSES),
        train_sequences=["00"],
        test_sequences=["09"],
        max_frames=30,
    )
    s = dm.dataset("test")[0]
    check_sample(s, 32, 96)
    assert s["sequence"] == "09"
    assert s["pose"][2, 3] > 0  # KITTI's car drives forward along +z


def test_bad_settings_give_clear_errors(tmp_path) -> None:
    with pytest.raises(ValueError, match="dataset.trajectory"):
        _dm(trajectory="circle")
    with pytest.raises(ValueError, match="poses_dir"):
        _dm(trajectory="kitti", train_sequences=["00"]).dataset("train")
    with pytest.raises(FileNotFoundError, match="07.txt"):
        _dm(trajectory="kitti", poses_dir=str(tmp_path), train_sequences=["07"]).dataset("train")
    bad = tmp_path / "00.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ValueError, match=r"00.txt:2"):
        _dm(trajectory="kitti", poses_dir=str(tmp_path), train_sequences=["00"]).dataset("train")
    with pytest.raises(EmptySplitError, match="val split"):
        _dm(val_fraction=0.0).dataset("val")


def test_dataset_index_errors() -> None:
    ds = SyntheticDrivingDataset(
        {"a": torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)}, {"a": (0, 1)}, 8, 8
    )
    assert len(ds) == 2
    with pytest.raises(IndexError, match="out of range"):
        ds[2]
