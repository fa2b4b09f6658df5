"""Export of the synthetic worlds in the published layouts: round trips through the project's
own readers (KITTI odometry, Virtual KITTI 1.3.1 and 2.0.3), the checker, trainings on exported
trees, and what the entry point refuses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from conftest import dataset_training, run_module
from fake_datasets import synthetic_drive, tree_snapshot
from mfg_lightning.core import geometry
from mfg_lightning.core.config import compose
from mfg_lightning.data import export as export_module
from mfg_lightning.data import kitti, vkitti, vkitti_files
from mfg_lightning.data.check import check_dataset, check_split
from mfg_lightning.data.transforms import resize_intrinsics
from mfg_lightning.flow import io as flow_io
from mfg_lightning.scene.camera import kitti_like_intrinsics
from mfg_lightning.scene.render import FAR_PLANE, exact_flow, render_frame
from mfg_lightning.scene.worlds import World
from mfg_lightning.trajectory import pose_io

H, W = 64, 192  # the tests' render size (version=1 is always 1242 × 375)
FRAMES = 5


@pytest.fixture(scope="module")
def poses_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """KITTI pose files 03 and 07 whose first pose is not the identity (the export must make
    it one)."""
    root = tmp_path_factory.mktemp("poses")
    offset = geometry.se3_exp(torch.tensor([1.0, -0.2, 3.0, 0.0, 0.4, 0.0], dtype=torch.float64))
    for name, turn in (("03", 0.01), ("07", -0.02)):
        poses = offset.numpy()[None] @ synthetic_drive(12, yaw_rate=turn)
        pose_io.write_kitti_poses(root / f"{name}.txt", poses)
    return root


def _export_cfg(out: Path, poses_dir: Path, *overrides: str, train=("03",), test=("07",)):
    return compose(
        "export",
        [
            f"out={out}",
            "dataset.trajectory=kitti",
            f"dataset.poses_dir={poses_dir}",
            f"dataset.train_sequences=[{','.join(train)}]",
            f"dataset.test_sequences=[{','.join(test)}]",
            f"dataset.max_frames={FRAMES}",
            *overrides,
        ],
    )


def _source_worlds(poses_dir: Path, frames: int = FRAMES) -> dict[str, tuple[World, torch.Tensor]]:
    """The worlds the export renders, built independently: KITTI name → (world, raw poses)."""
    out = {}
    for name, seed in (("03", 0), ("07", 7919)):  # test trajectories get the test seed
        poses = torch.from_numpy(pose_io.read_kitti_poses(poses_dir / f"{name}.txt"))[:frames]
        out[name] = (World.generate(poses, seed=seed, name=name), poses)
    return out


@pytest.fixture(scope="module")
def kitti_tree(tmp_path_factory: pytest.TempPathFactory, poses_dir: Path) -> Path:
    out = tmp_path_factory.mktemp("export") / "kitti"
    export_module.export(_export_cfg(out, poses_dir, "height=64", "width=192"), progress=False)
    return out


@pytest.fixture(scope="module")
def vkitti2_tree(tmp_path_factory: pytest.TempPathFactory, poses_dir: Path) -> Path:
    out = tmp_path_factory.mktemp("export") / "vkitti2"
    cfg = _export_cfg(out, poses_dir, "layout=vkitti", "version=2", "height=64", "width=192")
    export_module.export(cfg, progress=False)
    return out


@pytest.fixture(scope="module")
def vkitti1_tree(tmp_path_factory: pytest.TempPathFactory, poses_dir: Path) -> Path:
    out = tmp_path_factory.mktemp("export") / "vkitti1"
    # 1.3.1's camera is 1242 × 375: one world of three frames keeps this quick
    cfg = _export_cfg(out, poses_dir, "layout=vkitti", "dataset.max_frames=3", train=())
    export_module.export(cfg, progress=False)
    return out


# --------------------------------------------------------------------------------------------
# KITTI odometry
# --------------------------------------------------------------------------------------------


def test_kitti_tree_round_trips_poses_intrinsics_and_images(
    kitti_tree: Path, poses_dir: Path, tmp_path: Path
) -> None:
    seqs = kitti_tree / "sequences"
    assert sorted(p.name for p in seqs.iterdir()) == ["03", "07"]  # the KITTI names kept
    assert sorted(p.name for p in (seqs / "03" / "image_2").iterdir()) == [
        f"{k:06d}.png" for k in range(FRAMES)
    ]
    np.testing.assert_array_equal(pose_io.read_kitti_times(seqs / "03" / "times.txt"), [
        0.0, 0.1, 0.2, 0.3, 0.4
    ])  # fmt: skip
    K = kitti_like_intrinsics(H, W).numpy()
    np.testing.assert_array_equal(kitti.read_kitti_calib(seqs / "07" / "calib.txt"), K)
    worlds = _source_worlds(poses_dir)
    for name, (world, raw) in worlds.items():
        written = pose_io.read_kitti_poses(kitti_tree / "poses" / f"{name}.txt")
        np.testing.assert_allclose(written[0], np.eye(4), atol=1e-15)  # first pose: identity
        expected = (geometry.invert_pose(raw[0])[None] @ raw).numpy()
        np.testing.assert_allclose(written, expected, atol=1e-12)
        for k in (0, FRAMES - 1):  # PNG is lossless: the rendered frame, bit for bit
            rgb = render_frame(world, k, torch.from_numpy(K), H, W).rgb.permute(1, 2, 0).numpy()
            read = flow_io.read_rgb(seqs / name / "image_2" / f"{k:06d}.png")
            np.testing.assert_array_equal(read, rgb)

    # dataset=kitti reads the same relative poses and intrinsics
    cfg = compose("train", [
        "dataset=kitti", f"dataset.data_root={kitti_tree}", "dataset.train_sequences=[03]",
        "dataset.test_sequences=[07]", f"paths.cache_dir={tmp_path}", "flow.preset=ultrafast",
    ])  # fmt: skip
    dm = instantiate(cfg.dataset)
    test = dm.dataset("test")
    raw = worlds["07"][1]
    expected = geometry.relative_pose(raw[:-1], raw[1:])
    # (the dataset keeps float32 poses)
    torch.testing.assert_close(test.relative_poses().double(), expected, atol=1e-6, rtol=0)
    hw_in = (cfg.dataset.height, cfg.dataset.width)  # scaled from P2 to the model input
    torch.testing.assert_close(test.intrinsics("07"), resize_intrinsics(K, (H, W), hw_in))
    report = check_dataset(cfg.dataset, n_samples=2)
    assert report["ok"], report["problems"]
    assert report["splits"]["test"]["sequences"]["07"]["native_size"] == [H, W]


def test_procedural_trajectories_are_numbered_train_then_test(tmp_path: Path) -> None:
    cfg = compose("export", [
        f"out={tmp_path / 'k'}", "dataset.train_sequences=2", "dataset.test_sequences=1",
        "dataset.sequence_length=6",
    ])  # fmt: skip
    dm = instantiate(cfg.dataset, flow={"source": "exact"})
    names = [(s.name, s.world) for s in export_module.synthetic_sequences(dm, "kitti")]
    assert names == [("00", "train00"), ("01", "train01"), ("02", "test00")]
    vk = [(s.name, s.world) for s in export_module.synthetic_sequences(dm, "vkitti")]
    assert vk == [("0001", "test00"), ("0002", "train00"), ("0006", "train01")]
    # the layouts' defaults are the paper's splits: 00-08 + 09, 10 and test 0001 + 4 training
    for layout, counts in (("kitti", (9, 2)), ("vkitti", (4, 1))):
        d = compose("export", [f"layout={layout}"]).dataset
        assert (d.train_sequences, d.test_sequences) == counts


# --------------------------------------------------------------------------------------------
# Virtual KITTI
# --------------------------------------------------------------------------------------------


def _vkitti_dataset(root: Path, version: int, world: str, hw: tuple[int, int]):
    return vkitti.VirtualKittiDataset(
        root, [world], version=version, height=hw[0], width=hw[1], load_rgb=True
    )


@pytest.mark.parametrize("version", [1, 2])
def test_vkitti_tree_round_trips_flow_depth_poses_and_masks(
    request: pytest.FixtureRequest, poses_dir: Path, version: int
) -> None:
    root = request.getfixturevalue(f"vkitti{version}_tree")
    hw = export_module.VKITTI_SIZE if version == 1 else (H, W)
    K = geometry.scale_intrinsics(
        torch.tensor(vkitti.VKITTI1_INTRINSICS, dtype=torch.float64), hw[1] / 1242, hw[0] / 375
    )
    manifest = json.loads((root / export_module.MANIFEST).read_text())
    assert manifest["complete"] and manifest["size"] == list(hw)
    assert list(manifest["sequences"]) == (["0001"] if version == 1 else ["0001", "0002"])
    n = 3 if version == 1 else FRAMES
    world, raw = _source_worlds(poses_dir, n)["07"]  # the test trajectory is world 0001
    ds = _vkitti_dataset(root, version, "0001", hw)  # read at the native size: no resizing
    assert len(ds) == n - 1  # every pair t → t+1
    step = 2 * np.array([hw[1] - 1, hw[0] - 1]) / 65535  # one code of the flow encoding
    moving = 0
    for i in range(len(ds)):
        s = ds[i]
        k = s["frame"]
        frame = render_frame(world, k, K, *hw)
        exact = exact_flow(world, k, k + 1, K, *hw, source=frame)
        depth = frame.depth.numpy()
        flow = exact["flow"].permute(1, 2, 0).numpy()
        in_range = (np.abs(flow) <= np.array([hw[1] - 1, hw[0] - 1])).all(axis=2)
        valid = exact["flow_valid"].numpy() & (depth < FAR_PLANE) & in_range
        # flow: the exact values to half a code; invalid (B = 0) in the sky and beyond the
        # encoding's range ±(W − 1), ±(H − 1)
        np.testing.assert_array_equal(s["flow_valid"].numpy(), valid)
        err = np.abs(s["flow"].permute(1, 2, 0).numpy() - flow)[valid]
        assert (err <= step / 2 + 1e-4).all(), err.max(axis=0)
        # depth: centimetres, the sky at the far plane
        np.testing.assert_allclose(s["depth"].numpy(), depth, atol=0.005 + 1e-4, rtol=0)
        assert (s["depth"].numpy()[depth >= FAR_PLANE] == np.float32(FAR_PLANE)).all()
        # poses and intrinsics as rendered
        expected = geometry.relative_pose(raw[k], raw[k + 1])
        torch.testing.assert_close(s["pose"].double(), expected, atol=1e-6, rtol=0)
        torch.testing.assert_close(s["intrinsics"], K.float())
        # moving-object masks: those of the exact flow and depth, but for pixels whose residual
        # is within the encodings' error of the threshold; never a static pixel
        ref, residual = vkitti.moving_object_mask(
            flow, valid, depth, depth >= FAR_PLANE, expected.numpy(), K.numpy(), 1.0
        )
        differ = s["object_mask"].numpy() != ref
        assert (np.abs(np.linalg.norm(residual, axis=2)[differ] - 1.0) < 0.05).all()
        assert not (s["object_mask"].numpy() & ~exact["object_mask"].numpy()).any()
        moving += int(s["object_mask"].sum())
        if version == 1:  # 1.3.1's PNG is lossless (2.0.3's JPEG is checked below)
            np.testing.assert_array_equal(s["rgb"].numpy(), frame.rgb.numpy())
    assert moving > 0  # the masks compared were not empty
    if version == 2:
        jpg = flow_io.read_rgb(ds.layout.file("rgb", "0001", "clone", 0)).astype(int)
        rgb = render_frame(world, 0, K, *hw).rgb.permute(1, 2, 0).numpy().astype(int)
        assert np.abs(jpg - rgb).mean() < 4.0
        intrinsics = vkitti_files.read_vkitti_intrinsics(ds.layout.intrinsics_file("0001", "clone"))
        assert sorted(intrinsics) == list(range(FRAMES))
        np.testing.assert_array_equal(intrinsics[0], K.numpy())


@pytest.mark.parametrize("version", [1, 2])
def test_dataset_vkitti_and_the_checker_read_the_exported_tree(
    request: pytest.FixtureRequest, version: int
) -> None:
    root = request.getfixturevalue(f"vkitti{version}_tree")
    if version == 1:  # one world: the checker's report on it as one split
        report, problems = check_split(_vkitti_dataset(root, 1, "0001", (48, 128)), 2)
        assert not problems and report["samples"] == 2
        assert report["sequences"]["0001"]["native_size"] == list(export_module.VKITTI_SIZE)
        return
    cfg = compose("train", [
        "dataset=vkitti", f"dataset.data_root={root}", "dataset.version=2",
        "dataset.train_worlds=[0002]",
    ])  # fmt: skip
    report = check_dataset(cfg.dataset, n_samples=2)
    assert report["ok"], report["problems"]
    assert report["splits"]["test"]["sequences"]["0001"]["native_size"] == [H, W]


# --------------------------------------------------------------------------------------------
# The output directory
# --------------------------------------------------------------------------------------------


def _tiny(out: Path, poses_dir: Path, *extra: str):
    return _export_cfg(
        out, poses_dir, "height=16", "width=32", "dataset.max_frames=2", *extra, test=()
    )


def test_refuses_a_non_empty_out_and_overwrites_only_a_previous_export(
    tmp_path: Path, poses_dir: Path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    before = tree_snapshot(out)
    for overwrite in ("overwrite=false", "overwrite=true"):
        with pytest.raises(ValueError, match="not empty"):
            export_module.export(_tiny(out, poses_dir, overwrite), progress=False)
        assert tree_snapshot(out) == before  # nothing written, nothing removed
    (out / "notes.txt").unlink()
    export_module.export(_tiny(out, poses_dir, "dataset.train_sequences=[03,07]"), progress=False)
    assert sorted(p.name for p in (out / "sequences").iterdir()) == ["03", "07"]
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="overwrite=true"):
        export_module.export(_tiny(out, poses_dir), progress=False)
    export_module.export(_tiny(out, poses_dir, "overwrite=true"), progress=False)
    # the previous export is gone (no stale 07), the user's file is kept
    assert sorted(p.name for p in (out / "sequences").iterdir()) == ["03"]
    assert sorted(p.name for p in (out / "poses").iterdir()) == ["03.txt"]
    assert (out / "notes.txt").read_text() == "mine"


def test_an_interrupted_export_leaves_only_whole_files(
    tmp_path: Path, poses_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    real = flow_io.write_vkitti_depth
    calls = []

    def interrupted(path, depth):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C in the middle of the second frame
        real(path, depth)

    monkeypatch.setattr(flow_io, "write_vkitti_depth", interrupted)
    cfg = _tiny(out, poses_dir, "layout=vkitti", "version=2")
    with pytest.raises(KeyboardInterrupt):
        export_module.export(cfg, progress=False)
    files = [p for p in out.rglob("*") if p.is_file()]
    assert not [p for p in files if p.name.endswith(".tmp")]
    for p in files:
        if p.suffix in (".png", ".jpg"):
            flow_io.read_rgb(p) if "rgb" in p.name else flow_io._decode_png(p)
    assert not json.loads((out / export_module.MANIFEST).read_text())["complete"]
    monkeypatch.undo()
    export_module.export(_tiny(out, poses_dir, "layout=vkitti", "version=2", "overwrite=true"))
    assert json.loads((out / export_module.MANIFEST).read_text())["complete"]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["layout=vkitti", "width=64"], "version=1"),
        (["layout=vkitti", "version=3"], "version=3"),
        (["height=8"], "height=8"),
        (
            [
                "layout=vkitti",
                "dataset.trajectory=procedural",
                "dataset.train_sequences=5",
                "dataset.test_sequences=1",
            ],
            "6 trajectories",
        ),
        (["dataset.test_sequences=[03]"], "both dataset.train_sequences"),
    ],
)
def test_bad_settings_are_named(
    tmp_path: Path, poses_dir: Path, overrides: list[str], message: str
) -> None:
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=message):
        export_module.export(_export_cfg(out, poses_dir, *overrides), progress=False)
    assert not out.exists()


def test_only_the_synthetic_worlds_are_exported(tmp_path: Path) -> None:
    cfg = compose("export", ["dataset=kitti", f"out={tmp_path / 'out'}"])
    with pytest.raises(ValueError, match="dataset=synthetic"):
        export_module.export(cfg, progress=False)


def test_out_must_be_set(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="out is not set"):
        export_module.export(compose("export", []), progress=False)


@pytest.mark.slow
def test_entry_point_errors_are_one_line_and_exit_2(tmp_path: Path) -> None:
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    proc = run_module(
        "mfg_lightning.data.export", f"out={tmp_path / 'full'}", cwd=tmp_path, check=False
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: out=") and "not empty" in lines[0]


# --------------------------------------------------------------------------------------------
# Trainings on exported trees
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_kitti_trains_on_an_exported_tree_with_flow_from_its_images(
    tmp_path: Path, poses_dir: Path
) -> None:
    work = tmp_path / "work"
    work.mkdir()
    out = tmp_path / "tree"
    run_module(
        "mfg_lightning.data.export", f"out={out}", "height=64", "width=192",
        "dataset.trajectory=kitti", f"dataset.poses_dir={poses_dir}",
        "dataset.train_sequences=[03]", "dataset.test_sequences=[07]", "dataset.max_frames=6",
        cwd=work,
    )  # fmt: skip
    assert tree_snapshot(work) == {}  # nothing written but into out
    dataset_training(
        tmp_path, "kitti", out, "dataset.train_sequences=[03]", "dataset.test_sequences=[07]",
        "flow=dis", "flow.preset=ultrafast",
    )  # fmt: skip
    # DIS ran on the exported images at their size: the flow of every test pair (07: 5) and
    # of the training and validation pairs of 03 (the pair across the cut is dropped) is cached
    cache = tmp_path / "cache" / "kitti_flow"
    assert len(list(cache.glob("*/07@64x192/*.npy"))) == 5
    assert len(list(cache.glob("*/03@64x192/*.npy"))) == 4


@pytest.mark.slow
def test_vkitti_trains_on_an_exported_tree(vkitti2_tree: Path, tmp_path: Path) -> None:
    run = dataset_training(
        tmp_path, "vkitti", vkitti2_tree, "dataset.version=2", "dataset.train_worlds=[0002]"
    )
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert "VirtualKittiDataModule" in (run / "config.yaml").read_text()
    # evaluated on the test world, whose ground-truth moving objects came from the files
    assert np.isfinite(metrics["test/0001/ate"]) and metrics["test/object/gt_pixels"] > 0
