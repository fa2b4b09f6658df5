"""One batch schema (data.sample.SCHEMA): every dataset's samples and batches follow it, its
documentation and checks are made from it, and ``model_inputs`` is what the model reads."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from fake_datasets import make_kitti, make_vkitti
from mfg_lightning.data import sample as S
from mfg_lightning.data.base import collate_samples
from mfg_lightning.data.image_folder import ImageFolderDataset
from mfg_lightning.data.kitti import KittiOdometryDataset
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.data.vkitti import VirtualKittiDataset

H, W = 32, 64


def _follows_the_schema(sample: dict, height: int, width: int) -> None:
    """Every key is declared; every declared key has its shape and dtype; the required are there."""
    assert set(sample) <= set(S.SCHEMA), set(sample) - set(S.SCHEMA)
    assert set(S.REQUIRED_KEYS) <= set(sample)
    S.check_sample(sample, height, width)
    batch = collate_samples([sample, sample])
    S.check_batch(batch, height, width, needs=(S.POSE,) if S.POSE in sample else ())


def _datasets(tmp_path: Path) -> dict[str, torch.utils.data.Dataset]:
    kitti = make_kitti(tmp_path / "kitti")
    vk = make_vkitti(tmp_path / "vk", version=2)
    synthetic = SyntheticDataModule(
        height=H, width=W, train_sequences=1, test_sequences=1, sequence_length=8,
        val_fraction=0.25, cache_dir=str(tmp_path / "cache"),
    )  # fmt: skip
    rendered = SyntheticDataModule(
        height=H, width=W, train_sequences=1, test_sequences=1, sequence_length=6,
        val_fraction=0.25, cache_dir=str(tmp_path / "cache"),
        flow={"source": "dis", "preset": "fast", "height": 64, "width": 128},
    )  # fmt: skip
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        shutil.copy(kitti.image("09", k), frames / f"{k:04d}.png")
    return {
        "synthetic": synthetic.dataset("train"),
        "synthetic/rendered": rendered.dataset("test"),
        "image_folder": ImageFolderDataset(frames, kitti.intrinsics, height=H, width=W,
                                           cache_dir=tmp_path / "cache",
                                           flow={"source": "dis", "preset": "fast"}),
        "kitti": KittiOdometryDataset(kitti.root, ("09",), height=H, width=W,
                                      cache_dir=tmp_path / "cache",
                                      flow={"source": "dis", "preset": "fast"}),
        "vkitti": VirtualKittiDataset(vk.root, ("0001",), version=2, height=H, width=W),
    }  # fmt: skip


def test_every_datasets_samples_follow_the_one_schema(tmp_path: Path) -> None:
    for name, ds in _datasets(tmp_path).items():
        for i in (0, len(ds) - 1):
            sample = ds[i]
            assert sample[S.SAMPLE_ID].startswith(name.split("/")[0]), sample[S.SAMPLE_ID]
            _follows_the_schema(sample, H, W)


def test_the_documentation_is_made_from_the_schema() -> None:
    for key, field in S.SCHEMA.items():
        assert f"``{key}``" in S.__doc__
        assert (key in S.REQUIRED_KEYS) == field.required
    assert S.POSE in S.OPTIONAL_KEYS  # flow without ground truth has none
    assert S.INTRINSICS_HOST not in S.SCHEMA  # a batch-only key, declared beside it


def _batch() -> dict:
    ds = SyntheticDataModule(height=H, width=W, train_sequences=1, test_sequences=1,
                             sequence_length=6, val_fraction=0.2).dataset("test")  # fmt: skip
    return collate_samples([ds[0], ds[1]])


def test_the_checks_take_the_size_and_name_what_is_missing() -> None:
    batch = _batch()
    S.check_batch_layout(batch, H, W, needs=(S.POSE,))
    with pytest.raises(S.SampleError, match=r"'flow' has shape .* 16×64"):
        S.check_batch_layout(batch, 16, W)
    for key in (S.SEQUENCE, S.FRAME, S.TARGET, S.SAMPLE_ID):
        partial = {k: v for k, v in batch.items() if k != key}
        with pytest.raises(S.SampleError, match=f"missing .*'{key}'"):
            S.check_batch_layout(partial, H, W)
    no_pose = {k: v for k, v in batch.items() if k != S.POSE}
    S.check_batch_layout(no_pose, H, W)  # optional in the schema...
    with pytest.raises(S.SampleError, match="missing tensor 'pose'"):
        S.check_batch_layout(no_pose, H, W, needs=(S.POSE,))  # ...needed by training
    bad = dict(batch, object_mask=batch[S.FLOW_VALID].float())
    with pytest.raises(S.SampleError, match="'object_mask' is torch.float32, expected bool"):
        S.check_batch_layout(bad, H, W)


def test_model_inputs_mask_and_count_non_finite_flow() -> None:
    batch = _batch()
    batch[S.FLOW][0, :, 1, 2] = float("nan")
    batch[S.FLOW][1, 0, 3, 4] = float("inf")
    inputs = S.model_inputs(batch)
    assert int(inputs.n_bad) == 2
    assert torch.isfinite(inputs.flow).all()
    assert not inputs.valid[0, 1, 2] and not inputs.valid[1, 3, 4]
    assert (inputs.valid == (batch[S.FLOW_VALID] & torch.isfinite(batch[S.FLOW]).all(1))).all()
