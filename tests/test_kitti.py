"""KITTI odometry: calibration, poses, DIS flow and its cache, offsets, splits, errors."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from conftest import dataset_training
from fake_datasets import FakeKitti, make_kitti, tree_snapshot
from mfg_lightning.core import geometry
from mfg_lightning.core.config import compose
from mfg_lightning.core.data_errors import DataFileError, DataRootError, report_skipped
from mfg_lightning.data import kitti
from mfg_lightning.data.base import collate_samples
from mfg_lightning.data.kitti import KittiDataModule, KittiOdometryDataset
from mfg_lightning.data.sample import check_sample
from mfg_lightning.flow import io as flow_io

H, W = 48, 128


@pytest.fixture(scope="module")
def fk(tmp_path_factory: pytest.TempPathFactory) -> FakeKitti:
    return make_kitti(tmp_path_factory.mktemp("kitti"))


def _dataset(
    fake: FakeKitti, cache: Path, sequences=("09",), flow: dict | None = None, **kw
) -> KittiOdometryDataset:
    flow = {"source": "dis", "preset": "fast", **(flow or {})}
    return KittiOdometryDataset(
        fake.root, sequences, height=H, width=W, cache_dir=cache, flow=flow, **kw
    )


class _CountingEstimator(kitti.DISFlowEstimator):
    calls = 0

    def __call__(self, gray0: np.ndarray, gray1: np.ndarray) -> np.ndarray:
        type(self).calls += 1
        return super().__call__(gray0, gray1)


def test_calibration_and_intrinsics_come_from_p2(fk: FakeKitti, tmp_path: Path) -> None:
    K = kitti.read_kitti_calib(fk.root / "sequences" / "09" / "calib.txt")
    np.testing.assert_allclose(K, fk.intrinsics)
    s = _dataset(fk, tmp_path)[0]
    expected = geometry.scale_intrinsics(torch.tensor(fk.intrinsics), W / fk.width, H / fk.height)
    torch.testing.assert_close(s["intrinsics"], expected.float())


def test_calib_writer_round_trips_p2_exactly(tmp_path: Path) -> None:
    K = np.array([718.856 * 512 / 1241, 718.856 * 192 / 376, 250.5, 94.5])  # not %.12e-exact
    kitti.write_kitti_calib(tmp_path / "calib.txt", K)
    np.testing.assert_array_equal(kitti.read_kitti_calib(tmp_path / "calib.txt"), K)
    rows = {
        line.split(":")[0]: np.array(line.split(":")[1].split(), float).reshape(3, 4)
        for line in (tmp_path / "calib.txt").read_text().splitlines()
    }
    assert list(rows) == ["P0", "P1", "P2", "P3", "Tr"]
    np.testing.assert_array_equal(rows["P0"], rows["P2"])
    # the right cameras sit one baseline to the right: P[0, 3] = −fx · b
    b = kitti.KITTI_STEREO_BASELINE
    assert rows["P1"][0, 3] == rows["P3"][0, 3] == pytest.approx(-K[0] * b)
    with pytest.raises(ValueError, match="fx, fy > 0"):
        kitti.write_kitti_calib(tmp_path / "bad.txt", [0.0, 1.0, 1.0, 1.0])


def test_pose_is_camera_at_target_in_camera_at_source(fk: FakeKitti, tmp_path: Path) -> None:
    ds = _dataset(fk, tmp_path, offsets=[1, -1, 2])
    T = torch.from_numpy(fk.poses["09"])
    rel = ds.relative_poses()
    assert rel.shape == (len(ds), 4, 4)
    for i, (_, src, tgt) in enumerate(ds.samples):
        torch.testing.assert_close(
            rel[i].double(), torch.linalg.inv(T[src]) @ T[tgt], atol=1e-5, rtol=0
        )
    forward = [i for i, (_, a, b) in enumerate(ds.samples) if b == a + 1]
    # both real KITTI (09 starts driving forward) and the synthetic drive move along +z
    assert (rel[forward, 2, 3] > 0).all()
    # relative_poses() reads poses only: no flow computed, nothing cached
    assert ds.missing_flow() == list(range(len(ds)))
    torch.testing.assert_close(ds[forward[2]]["pose"], rel[forward[2]])


def test_dis_flow_matches_the_known_shift_and_is_cached(fk: FakeKitti, tmp_path: Path) -> None:
    before = tree_snapshot(fk.root)
    ds = _dataset(fk, tmp_path / "cache", offsets=[1, -1])
    ds.estimator = _CountingEstimator("fast")
    s = ds[0]
    check_sample(s, H, W)
    assert s["sample_id"] == "kitti/train/09/0->1"
    true = np.array(fk.shift) * np.array([W / fk.width, H / fk.height])
    inner = s["flow"][:, 6:-6, 10:-10]  # away from the borders, where the texture enters
    np.testing.assert_allclose(inner.mean(dim=(1, 2)).numpy(), true, atol=0.1)
    backward = ds.samples.index(("09", 3, 2))
    np.testing.assert_allclose(
        ds[backward]["flow"][:, 6:-6, 10:-10].mean((1, 2)).numpy(), -true, atol=0.1
    )
    assert _CountingEstimator.calls == 2
    # cache layout: <cache>/kitti_flow/<key>/<seq>@<computed size>/<src>_<tgt>.npy
    path = ds.cache_path(0)
    assert path.relative_to(tmp_path / "cache").parts[:1] == ("kitti_flow",)
    assert path.parent.name == f"09@{fk.height}x{fk.width}" and path.name == "000000_000001.npy"
    assert (path.parents[1] / "meta.json").is_file()
    # second access and a second dataset (a later run) read the cache: no estimator call
    torch.testing.assert_close(ds[0]["flow"], s["flow"])
    again = _dataset(fk, tmp_path / "cache", offsets=[1, -1])
    again.estimator = _CountingEstimator("fast")
    torch.testing.assert_close(again[0]["flow"], s["flow"])
    assert _CountingEstimator.calls == 2
    # a parameter that changes the flow gets its own cache directory
    other = _dataset(fk, tmp_path / "cache", flow={"params": {"patch_size": 12}})
    assert other.cache_path(0).parents[1] != path.parents[1]
    smaller = _dataset(fk, tmp_path / "cache", flow={"height": 32, "width": 100})
    assert smaller.cache_path(0).parent.name == "09@32x100"
    assert tree_snapshot(fk.root) == before  # nothing written into data_root


def test_precompute_fills_the_cache_for_every_split(fk: FakeKitti, tmp_path: Path) -> None:
    dm = KittiDataModule(
        fk.root, height=H, width=W, cache_dir=tmp_path,
        flow={"source": "dis", "preset": "ultrafast"}, train_sequences=["00", "01"],
        test_sequences=["09"], backward_flow=True,
    )  # fmt: skip
    dm.prepare_data()
    dm.setup("fit")
    dm.setup("test")
    for split in ("train", "val", "test"):
        assert dm.dataset(split).missing_flow() == []
    train = dm.dataset("train")
    pairs = {(a, b) for _, a, b in train.samples}
    assert (3, 2) in pairs and (2, 3) in pairs  # backward_flow adds t → t − 1 to training
    assert all(b == a + 1 for _, a, b in dm.dataset("test").samples)  # … and only to training
    assert dm.dataset("train").precompute_flow(progress=False) == 0  # nothing left to do


def test_splits_and_validation_tail(fk: FakeKitti, tmp_path: Path) -> None:
    dm = KittiDataModule(fk.root, height=H, width=W, cache_dir=tmp_path)
    assert dm.train_sequences == [f"{i:02d}" for i in range(9)] and dm.test_sequences == [
        "09",
        "10",
    ]
    train, val, test = (dm.dataset(s) for s in ("train", "val", "test"))
    assert {s for s, _, _ in test.samples} == {"09", "10"}
    assert {s for s, _, _ in val.samples} <= set(dm.train_sequences)
    for seq in ("00", "08"):
        t_frames = {f for s, a, b in train.samples if s == seq for f in (a, b)}
        v_frames = {f for s, a, b in val.samples if s == seq for f in (a, b)}
        assert v_frames and not t_frames & v_frames and min(v_frames) > max(t_frames)
    assert len(test) == 2 * 7


def test_central_frame_offsets(fk: FakeKitti, tmp_path: Path) -> None:
    ds = _dataset(fk, tmp_path, offsets=[-2, -1, 1, 2])
    by_frame: dict[int, list[int]] = {}
    for _, src, tgt in ds.samples:
        by_frame.setdefault(src, []).append(tgt - src)
    assert by_frame[4] == [-2, -1, 1, 2]  # a centre frame has all four neighbours
    assert by_frame[0] == [1, 2] and by_frame[7] == [-2, -1]
    assert ds.sequences() == {"09": list(range(len(ds)))}


@pytest.mark.parametrize("ext", ["flo", "png", "npy"])
def test_user_supplied_flow(fk: FakeKitti, tmp_path: Path, ext: str) -> None:
    flow_dir = tmp_path / "flow"
    flow = np.zeros((fk.height, fk.width, 2), np.float32)
    flow[..., 0], flow[..., 1] = 3.0, -1.5
    writer = {
        "flo": flow_io.write_flo,
        "png": flow_io.write_kitti_flow_png,
        "npy": flow_io.write_npy_flow,
    }[ext]
    for src in range(7):
        writer(flow_dir / "09" / f"{src:06d}_{src + 1:06d}.{ext}", flow)
    files = {"source": "files", "dir": flow_dir}
    ds = KittiOdometryDataset(
        fk.root, ["09"], height=H, width=W, cache_dir=tmp_path / "cache", flow=files
    )
    s = ds[2]
    expected = (
        torch.tensor([3.0 * W / fk.width, -1.5 * H / fk.height]).view(2, 1, 1).expand(2, H, W)
    )
    torch.testing.assert_close(s["flow"], expected)
    assert s["flow_valid"].all()
    assert not list((tmp_path / "cache").glob("kitti_flow/*/*@*/*.npy"))  # no flow computed
    # a missing file: an error naming the expected file and the naming scheme
    (flow_dir / "09" / f"000004_000005.{ext}").unlink()
    with pytest.raises(DataFileError, match=r"09/000004_000005\.<flo\|png\|npy\|npz>") as err:
        KittiOdometryDataset(fk.root, ["09"], height=H, width=W, cache_dir=tmp_path, flow=files)
    assert "<flow_dir>/<seq>/<src:06d>_<tgt:06d>.<ext>" in str(err.value)


def test_root_errors_show_the_layout(fk: FakeKitti, tmp_path: Path) -> None:
    with pytest.raises(DataRootError, match="data_root is not set") as err:
        KittiDataModule(None).dataset("train")
    assert "sequences/" in str(err.value) and "image_2/000000.png" in str(err.value)
    with pytest.raises(DataRootError, match="not a directory"):
        _dataset(FakeKitti(tmp_path / "typo", 1, 1, (0, 0), np.zeros(4)), tmp_path)
    (tmp_path / "sequences" / "03").mkdir(parents=True)
    (tmp_path / "poses").mkdir()
    with pytest.raises(DataRootError) as err:
        KittiDataModule(tmp_path, cache_dir=tmp_path).dataset("train")
    text = str(err.value)
    for entry in ("sequences/00/", "sequences/08/", "sequences/03/calib.txt", "poses/07.txt"):
        assert str(tmp_path / entry) in text, entry
    assert "└── poses/" in text and text.count("Expected layout") == 1


def test_bad_files_name_the_file_or_are_skipped(tmp_path: Path) -> None:
    fake = make_kitti(tmp_path / "root", sequences=("09",), n_frames=6)
    cache = tmp_path / "cache"
    # a truncated frame: the error names the sample and the file
    img = fake.image("09", 2)
    img.write_bytes(img.read_bytes()[:300])
    ds = _dataset(fake, cache)
    with pytest.raises(DataFileError, match=r"kitti/train/09/1->2: .*000002\.png"):
        ds[1]
    ds = _dataset(fake, cache, skip_bad_samples=True)
    with pytest.warns(UserWarning, match="skipping kitti/train/09/2->3"):
        assert ds[2] is None
    assert ds.skipped.value == 1
    assert report_skipped({"train": ds}) == {"train": 1}  # what teardown logs
    assert collate_samples([None, ds[0]])["flow"].shape == (1, 2, H, W)
    # a pose file shorter than the image list, and a missing frame
    poses = fake.root / "poses" / "09.txt"
    poses.write_text("".join(poses.read_text().splitlines(keepends=True)[:5]))
    fake.image("09", 3).unlink()
    with pytest.raises(DataFileError) as err:
        _dataset(fake, cache)
    assert "poses/09.txt: 5 poses for 5 images" in str(err.value)  # 000005.png has no pose
    assert "000003.png" in str(err.value)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        ds = _dataset(fake, cache, skip_bad_samples=True)
    assert [(a, b) for _, a, b in ds.samples] == [(0, 1), (1, 2)]


def test_configs_build_the_datamodule(fk: FakeKitti, tmp_path: Path) -> None:
    cfg = compose(
        "train", ["dataset=kitti", f"dataset.data_root={fk.root}", f"paths.cache_dir={tmp_path}"]
    )
    dm = instantiate(cfg.dataset)
    assert isinstance(dm, KittiDataModule)
    assert dm.test_sequences == ["09", "10"] and dm.offsets == [1] and not dm.backward_flow
    assert dm.dataset_kwargs["cache_dir"] == str(tmp_path)
    cfg = compose("train", ["experiment=paper_kitti", f"dataset.data_root={fk.root}"])
    assert cfg.dataset.backward_flow is True and cfg.dataset.batch_size == 1
    assert (cfg.dataset.height, cfg.dataset.width) == (48, 128)
    assert cfg.model.optimizer.lr == 1e-5 and list(cfg.model.optimizer.betas) == [0.99, 0.999]
    assert cfg.model.loss.w_s == 100
    # Table 1's *: the same setting on the motions from a centre frame to its four neighbours
    star = compose(
        "train",
        [
            "experiment=paper_kitti_central",
            f"dataset.data_root={fk.root}",
            f"paths.cache_dir={tmp_path}",
        ],
    )
    dm = instantiate(star.dataset)
    assert dm.offsets == [-2, -1, 1, 2] and not dm.backward_flow
    assert {b - a for _, a, b in dm.dataset("test").samples} == {-2, -1, 1, 2}
    assert star.model == cfg.model and star.dataset.batch_size == 1


@pytest.mark.slow
def test_training_runs_end_to_end(fk: FakeKitti, tmp_path: Path) -> None:
    dataset_training(
        tmp_path, "kitti", fk.root, "dataset.backward_flow=true", "flow.preset=ultrafast"
    )
    # run_module points MFG_CACHE_DIR (paths.cache_dir) at <tmp>/cache: the flow went there
    cache = tmp_path / "cache" / "kitti_flow"
    assert len(list(cache.glob("*/*@*/*.npy"))) == 2 * 45 + 9 + 14  # flow of every pair
    assert len(list(cache.glob("*/*_rgb/*.npy"))) == 11 * 8  # and every frame's small RGB


def _replace_p2(path: Path, index: int, value: float) -> int:
    """Set entry ``index`` of the row-major 3×4 ``P2`` in ``calib.txt``; returns P2's line."""
    lines = path.read_text().splitlines()
    number = next(i for i, line in enumerate(lines) if line.startswith("P2:"))
    P = lines[number].split()[1:]
    P[index] = repr(value)
    lines[number] = "P2: " + " ".join(P)
    path.write_text("\n".join(lines) + "\n")
    return number + 1


@pytest.mark.parametrize(
    ("index", "value", "words"),
    [
        (0, 0.0, "P2: focal lengths must be positive, got fx = 0, fy = 115.2"),
        (5, -115.2, "P2: focal lengths must be positive, got fx = 115.2, fy = -115.2"),
        (2, 400.0, "P2: principal point (cx, cy) = (400, 30.5) is outside the 128×64 image"),
    ],
)
def test_a_calib_with_a_focal_length_of_0_is_refused_naming_file_and_line(
    tmp_path: Path, index: int, value: float, words: str
) -> None:
    """``fx = 0`` passed read_kitti_calib and data.check; training then failed late without
    naming the file. Now the reader refuses it, naming the file and P2's line."""
    fake = make_kitti(tmp_path / "root", sequences=("09",), n_frames=3, width=128)
    calib = fake.root / "sequences" / "09" / "calib.txt"
    line = _replace_p2(calib, index, value)
    if index != 2:  # without the image size only the focal lengths can be checked
        with pytest.raises(DataFileError) as err:
            kitti.read_kitti_calib(calib)
        assert str(err.value) == f"{calib}:{line}: {words}"
    with pytest.raises(DataFileError) as err:
        _dataset(fake, tmp_path / "cache")
    assert str(err.value) == f"{calib}:{line}: {words}"
