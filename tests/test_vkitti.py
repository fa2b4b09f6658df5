"""Virtual KITTI 1.3.1 / 2.0.3: decoding, poses, intrinsics, moving-object masks, splits, errors."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from conftest import dataset_training, run_module
from fake_datasets import FakeVkitti, make_vkitti, tree_snapshot
from mfg_lightning.core import geometry
from mfg_lightning.core.config import compose
from mfg_lightning.core.data_errors import DataFileError, DataRootError
from mfg_lightning.data import transforms, vkitti_files
from mfg_lightning.data.base import collate_samples
from mfg_lightning.data.sample import check_sample
from mfg_lightning.data.vkitti import VirtualKittiDataModule, VirtualKittiDataset
from mfg_lightning.flow.estimators import GroundTruthFlow

H, W = 48, 128


@pytest.fixture(scope="module")
def vk1(tmp_path_factory: pytest.TempPathFactory) -> FakeVkitti:
    return make_vkitti(tmp_path_factory.mktemp("vk1"), version=1)


@pytest.fixture(scope="module")
def vk2(tmp_path_factory: pytest.TempPathFactory) -> FakeVkitti:
    return make_vkitti(tmp_path_factory.mktemp("vk2"), version=2, worlds=("0001", "0002"))


def _dataset(fake: FakeVkitti, worlds=("0001",), **kw) -> VirtualKittiDataset:
    return VirtualKittiDataset(fake.root, worlds, version=fake.version, height=H, width=W, **kw)


@pytest.mark.parametrize("version", [1, 2])
def test_extrinsics_and_intrinsics_writers_round_trip_exactly(tmp_path: Path, version: int) -> None:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(version)
    mats = np.tile(np.eye(4), (5, 1, 1))  # rigid transforms, every digit random
    mats[:, :3, :3] = Rotation.random(5, random_state=version).as_matrix()
    mats[:, :3, 3] = rng.normal(size=(5, 3))
    vkitti_files.write_vkitti_extrinsics(tmp_path / "extrinsic.txt", mats, version)
    header = (tmp_path / "extrinsic.txt").read_text().splitlines()[0].split()
    ids = ["frame"] if version == 1 else ["frame", "cameraID"]  # then the 16 matrix entries
    assert header[: len(ids)] == ids and len(header) == len(ids) + 16
    back = vkitti_files.read_vkitti_extrinsics(tmp_path / "extrinsic.txt", version)
    assert sorted(back) == list(range(5))
    np.testing.assert_array_equal(np.stack([back[f] for f in range(5)]), mats)
    K = rng.uniform(100, 800, size=(5, 4))
    vkitti_files.write_vkitti_intrinsics(tmp_path / "intrinsic.txt", K)
    back_k = vkitti_files.read_vkitti_intrinsics(tmp_path / "intrinsic.txt")
    np.testing.assert_array_equal(np.stack([back_k[f] for f in range(5)]), K)
    with pytest.raises(ValueError, match=r"\(N, 4, 4\)"):
        vkitti_files.write_vkitti_extrinsics(tmp_path / "bad.txt", mats[:, :3], version)


@pytest.mark.parametrize("version", [1, 2])
def test_sample_decodes_what_was_written(vk1: FakeVkitti, vk2: FakeVkitti, version: int) -> None:
    fake = vk1 if version == 1 else vk2
    ds = _dataset(fake)
    assert len(ds) == 5  # 6 frames → 5 pairs t → t + 1
    sample = ds[2]
    check_sample(sample, H, W)
    assert sample["sample_id"] == "vkitti/train/0001/2->3"
    assert (sample["frame"], sample["target"], sample["sequence"]) == (2, 3, "0001")
    # flow and validity: the resize of the written flow, with the invalid sky masked
    flow, valid = transforms.resize_flow(fake.flow["0001"][2], fake.valid["0001"][2], H, W)
    torch.testing.assert_close(sample["flow"], transforms.flow_to_tensor(flow), atol=0.01, rtol=0)
    np.testing.assert_array_equal(sample["flow_valid"].numpy(), valid)
    sky_rows = int(np.floor(fake.sky_rows * H / fake.height))
    assert not sample["flow_valid"][: sky_rows - 1, : W // 2 - 1].any()
    # depth in metres; the sky keeps the far plane
    depth = sample["depth"]
    assert torch.allclose(depth[: sky_rows - 1], torch.tensor(655.35), atol=0.01)
    expected = transforms.resize_depth(fake.depth["0001"][2], H, W)
    np.testing.assert_allclose(depth.numpy(), expected, rtol=1e-3)
    # intrinsics: 1.3.1's fixed camera / 2.0.3's intrinsic.txt, scaled to the input size
    K_expected = geometry.scale_intrinsics(
        torch.tensor(fake.intrinsics["0001"]), W / fake.width, H / fake.height
    )
    torch.testing.assert_close(sample["intrinsics"], K_expected.float())
    if version == 1:
        assert sample["intrinsics"][0] == pytest.approx(725 * W / fake.width)
    assert sample["rgb"].shape == (3, H, W) and sample["rgb"].dtype == torch.uint8


@pytest.mark.parametrize("version", [1, 2])
def test_pose_is_camera_at_target_in_camera_at_source(
    vk1: FakeVkitti, vk2: FakeVkitti, version: int
) -> None:
    fake = vk1 if version == 1 else vk2
    ds = _dataset(fake)
    T = torch.from_numpy(fake.T_world_cam["0001"])
    for i in range(len(ds)):
        expected = torch.linalg.inv(T[i]) @ T[i + 1]
        torch.testing.assert_close(ds[i]["pose"].double(), expected, atol=1e-5, rtol=0)
    rel = ds.relative_poses()
    assert rel.shape == (5, 4, 4)
    assert (rel[:, 2, 3] > 0.5).all()  # the car drives forward: t_z > 0 (not the inverse)
    torch.testing.assert_close(rel[3], ds[3]["pose"])


@pytest.mark.parametrize("version", [1, 2])
def test_moving_object_mask_and_flow(vk1: FakeVkitti, vk2: FakeVkitti, version: int) -> None:
    fake = vk1 if version == 1 else vk2
    ds = _dataset(fake)
    for i in (0, 3):
        s = ds[i]
        truth = transforms.resize_mask(fake.moving["0001"][i], H, W)
        mask = s["object_mask"].numpy()
        iou = (mask & truth).sum() / (mask | truth).sum()
        assert iou > 0.9, iou
        # The sky's bogus-but-valid flow and its far plane never become objects.
        sky_rows = int(np.ceil(fake.sky_rows * H / fake.height))
        assert not mask[:sky_rows].any()
        # object_flow = flow − rigid flow on the mask, in input pixels; 0 elsewhere
        shift = np.array(fake.object_shift) * np.array([W / fake.width, H / fake.height])
        inner = (
            mask
            & np.roll(mask, 1, 0)
            & np.roll(mask, -1, 0)
            & np.roll(mask, 1, 1)
            & np.roll(mask, -1, 1)
        )
        obj = s["object_flow"].numpy()
        np.testing.assert_allclose(
            obj[:, inner].T, np.broadcast_to(shift, (inner.sum(), 2)), atol=0.02
        )
        assert (obj[:, ~mask] == 0).all()


def test_object_threshold_is_configurable(vk1: FakeVkitti) -> None:
    # The object moves by |(4, −1)| ≈ 4.1 native pixels: a 5-pixel threshold sees nothing.
    assert _dataset(vk1, object_threshold=5.0)[0]["object_mask"].sum() == 0
    assert _dataset(vk1, object_threshold=3.0)[0]["object_mask"].sum() > 0


def test_splits_follow_the_paper(vk1: FakeVkitti) -> None:
    ego = VirtualKittiDataModule(vk1.root, height=H, width=W)
    assert {s for s, _, _ in ego.dataset("test").samples} == {"0001"}
    assert {s for s, _, _ in ego.dataset("train").samples} == {"0002", "0006", "0018", "0020"}
    objects = VirtualKittiDataModule(vk1.root, split="objects", height=H, width=W)
    assert {s for s, _, _ in objects.dataset("train").samples} == {"0001", "0006", "0020"}
    assert {s for s, _, _ in objects.dataset("test").samples} == {"0002", "0018"}
    # validation: a tail of each training world, disjoint in frames from training
    train, val = ego.dataset("train"), ego.dataset("val")
    assert {s for s, _, _ in val.samples} == {"0002", "0006", "0018", "0020"}
    for world in ("0002", "0006"):
        train_frames = {f for s, a, b in train.samples if s == world for f in (a, b)}
        val_frames = {f for s, a, b in val.samples if s == world for f in (a, b)}
        assert not train_frames & val_frames
        assert min(val_frames) > max(train_frames)
    assert len(train) + len(val) == 4 * 5 - 4  # the pair across the cut is dropped
    assert ego.mean_motion("train")[0][2] > 0


def test_configs_build_the_datamodules(vk1: FakeVkitti) -> None:
    for name, test_worlds in (("vkitti", {"0001"}), ("vkitti_objects", {"0002", "0018"})):
        cfg = compose("train", [f"dataset={name}", f"dataset.data_root={vk1.root}"])
        dm = instantiate(cfg.dataset)
        assert isinstance(dm, VirtualKittiDataModule)
        assert (dm.height, dm.width) == (cfg.model.net.height, cfg.model.net.width) == (48, 128)
        assert set(dm.test_worlds) == test_worlds
        assert dm.dataset_kwargs["variation"] == "clone"
        assert cfg.flow.source == "ground_truth" and isinstance(dm.flow, GroundTruthFlow)
    cfg = compose("train", ["experiment=paper_vkitti_objects", f"dataset.data_root={vk1.root}"])
    assert cfg.dataset.split == "objects" and cfg.dataset.batch_size == 1
    assert cfg.model.optimizer.lr == 1e-5 and list(cfg.model.optimizer.betas) == [0.99, 0.999]


def test_loader_collates_and_writes_nothing_into_data_root(vk1: FakeVkitti) -> None:
    before = tree_snapshot(vk1.root)
    dm = VirtualKittiDataModule(vk1.root, height=H, width=W, batch_size=4)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["flow"].shape == (4, 2, H, W) and batch["object_mask"].dtype == torch.bool
    assert tree_snapshot(vk1.root) == before


def test_missing_or_wrong_root_is_one_error_with_the_layout(
    vk2: FakeVkitti, tmp_path: Path
) -> None:
    with pytest.raises(DataRootError, match="data_root is not set") as err:
        VirtualKittiDataModule(None).dataset("train")
    assert "vkitti_1.3.1_flowgt/0001/clone/00000.png" in str(err.value)
    with pytest.raises(DataRootError, match="not a directory"):
        _dataset(FakeVkitti(tmp_path / "nowhere", 1, 64, 200))
    # a 2.0.3 tree read as 1.3.1: the message lists what is missing and suggests version=2
    with pytest.raises(DataRootError) as err:
        VirtualKittiDataset(vk2.root, ["0001"], version=1)
    text = str(err.value)
    assert "vkitti_1.3.1_rgb" in text and "dataset.version=2" in text and "└──" in text


def test_bad_files_name_the_file_or_are_skipped(tmp_path: Path) -> None:
    fake = make_vkitti(tmp_path, version=1, worlds=("0001",), n_frames=5)
    # a truncated flow PNG: an error naming the file …
    flow_file = fake.file("flow", "0001", 1)
    flow_file.write_bytes(flow_file.read_bytes()[:200])
    ds = _dataset(fake)
    with pytest.raises(DataFileError, match=r"vkitti/train/0001/1->2: .*00001\.png"):
        ds[1]
    # … or, with skip_bad_samples, a warning, None (dropped by the collate) and a count
    ds = _dataset(fake, skip_bad_samples=True)
    with pytest.warns(UserWarning, match=r"skipping vkitti/train/0001/1->2"):
        assert ds[1] is None
    assert ds.skipped.value == 1
    assert collate_samples([ds[0], None])["flow"].shape[0] == 1
    # a missing depth file and an extrinsics file shorter than the image list
    fake.file("depth", "0001", 2).unlink()
    ext = fake.extrinsics_file("0001")
    ext.write_text("\n".join(ext.read_text().splitlines()[:-1]) + "\n")
    with pytest.raises(DataFileError) as err:
        _dataset(fake)
    assert "00002.png" in str(err.value) and "0001_clone.txt: no extrinsics" in str(err.value)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = _dataset(fake, skip_bad_samples=True)
    assert any("skipping affected samples" in str(w.message) for w in caught)
    # frame 2 has no depth (drops 2→3), frame 4 no pose (drops 3→4)
    assert [(a, b) for _, a, b in ds.samples] == [(0, 1), (1, 2)]


@pytest.mark.slow
def test_training_runs_end_to_end(vk1: FakeVkitti, tmp_path: Path) -> None:
    run = dataset_training(tmp_path, "vkitti", vk1.root)
    assert "VirtualKittiDataModule" in (run / "config.yaml").read_text()


@pytest.mark.parametrize("flow", ["flow=dis", "flow=exact", "flow=files flow.dir=/data/flow"])
def test_a_flow_source_it_cannot_give_is_one_error(
    vk1: FakeVkitti, tmp_path: Path, flow: str
) -> None:
    """dataset=vkitti feeds its ground-truth flow: another flow source is refused, not ignored."""
    proc = run_module(
        "mfg_lightning.train", "dataset=vkitti", f"dataset.data_root={vk1.root}", *flow.split(),
        f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path, check=False,
    )  # fmt: skip
    assert proc.returncode == 2
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    source = flow.split()[0].removeprefix("flow=")
    assert len(errors) == 1 and f"flow.source={source}: dataset=vkitti" in errors[0], proc.stderr
    assert "flow=ground_truth" in errors[0]
    assert not (tmp_path / "r" / "metrics.json").exists()


def _edit_row(path: Path, frame: int, edit, camera: int | None = None) -> int:
    """Apply ``edit(fields) -> fields`` to the row of ``frame`` (and ``camera``, 2.0.3) of a
    Virtual KITTI text file; returns its 1-based line number."""
    lines = path.read_text().splitlines()
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split()
        if int(fields[0]) == frame and (camera is None or int(fields[1]) == camera):
            lines[number - 1] = " ".join(edit(fields))
            path.write_text("\n".join(lines) + "\n")
            return number
    raise AssertionError(f"no row of frame {frame} in {path}")


def _scale_rotation(fields: list[str], by: float = 5.0) -> list[str]:
    """The 16 matrix entries are the last 16 fields; the rotation block is rows 0–2, cols 0–2."""
    head, m = fields[:-16], [float(v) for v in fields[-16:]]
    for r in range(3):
        for c in range(3):
            m[4 * r + c] *= by
    return head + [repr(v) for v in m]


@pytest.mark.parametrize(
    ("version", "edit", "words"),
    [
        (1, _scale_rotation, "the 3×3 block is not a rotation (max |RᵀR − I| = 24"),
        (2, _scale_rotation, "the 3×3 block is not a rotation (max |RᵀR − I| = 24"),
        (1, lambda f: ["1", *f[1:]], "frame 1 does not follow 1 (line 3): frame numbers must be"),
        (1, lambda f: ["1.5", *f[1:]], "frame 1.5 is not a whole number >= 0"),
        (2, lambda f: ["1", *f[1:]], "frame 1 does not follow 1 (line 4): frame numbers must be"),
        (1, lambda f: [*f[:-4], "0", "0", "0.5", "1"], "the bottom row is 0 0 0.5 1, not 0 0 0 1"),
    ],
    ids=["scaled-1", "scaled-2", "duplicate-1", "fractional-1", "duplicate-2", "bottom-row"],
)
def test_extrinsics_that_are_not_rigid_or_whose_frames_repeat_are_refused(
    tmp_path: Path, version: int, edit, words: str
) -> None:
    """Frame 2's rotation block scaled by 5 passed (``_numeric_rows`` checked finiteness only)
    and made the ground-truth translation 5.5× too long; a duplicate or fractional frame was
    merged by ``int(frame)``. Each is now refused, naming the file and the line."""
    fake = make_vkitti(tmp_path, version=version, worlds=("0001",), n_frames=4)
    ext = fake.extrinsics_file("0001")
    line = _edit_row(ext, 2, edit, camera=0 if version == 2 else None)
    with pytest.raises(DataFileError) as err:
        vkitti_files.read_vkitti_extrinsics(ext, version)
    assert str(err.value).startswith(f"{ext}:{line}: {words}"), str(err.value)
    assert "\n" not in str(err.value)
    with pytest.raises(DataFileError, match=f"^{ext}:{line}: "):
        _dataset(fake)


@pytest.mark.parametrize(
    ("column", "value", "words"),
    [
        (2, 0.0, "focal lengths must be positive, got fx = 0, fy = 160"),
        (4, 250.0, "principal point (cx, cy) = (250, 31.5) is outside the 200×64 image"),
    ],
)
def test_intrinsics_with_a_focal_length_of_0_or_outside_the_image_are_refused(
    tmp_path: Path, column: int, value: float, words: str
) -> None:
    fake = make_vkitti(tmp_path, version=2, worlds=("0001",), n_frames=4)
    intr = fake.extrinsics_file("0001").parent / "intrinsic.txt"

    def edit(fields: list[str]) -> list[str]:
        fields[column] = repr(value)
        return fields

    line = _edit_row(intr, 1, edit, camera=0)
    with pytest.raises(DataFileError, match=f"^{intr}:{line}: ") as err:
        _dataset(fake)
    assert str(err.value) == f"{intr}:{line}: {words}"
