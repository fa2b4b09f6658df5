"""The evaluate entry point on a real (tiny) training's checkpoint."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import run_module

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("trained")
    run = tmp / "run"
    run_module("mfg_lightning.train", "debug=tiny", "dataset.sequence_length=16",
               f"hydra.run.dir={run}", cwd=tmp)  # fmt: skip
    return run


def test_top_k_sweep_writes_table_plot_and_pose_files(trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    proc = run_module(
        "mfg_lightning.evaluate", f"ckpt_path={trained / 'checkpoints' / 'last.ckpt'}",
        "eval.top_k_sweep=[1.0,0.25,0.1,0.02]", f"hydra.run.dir={out}", cwd=tmp_path,
    )  # fmt: skip
    table = (out / "top_k.md").read_text()
    assert "| k (%) | ATE test00 | ATE all |" in table
    assert len([line for line in table.splitlines() if line.startswith("| ")]) == 1 + 4
    assert table in proc.stdout
    assert (out / "top_k.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    payload = json.loads((out / "metrics.json").read_text())
    assert set(payload["top_k_sweep"]) == {"1", "0.25", "0.1", "0.02"}
    assert payload["metrics"]["test/ate"] == payload["top_k_sweep"]["1"]["test/ate"]
    assert "test/test00/ate" in payload["metrics"]
    assert "test00" in (out / "sequences.md").read_text()
    # The trajectory figures of the reported model: PNGs in the run directory and TensorBoard.
    for kind in ("trajectory", "drift", "error"):
        png = (out / "trajectories" / f"{kind}_test00.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(out / "tensorboard"), size_guidance={"images": 0})
    events.Reload()
    tags = set(events.Tags()["images"])
    assert {"test/test00/trajectory", "test/test00/drift", "test/test00/error"} <= tags
    image = events.Images("test/test00/trajectory")[0]
    assert (image.width, image.height) == (768, 720)  # 6.4 × 6.0 in at 120 dpi

    # Pose files that evo reads unchanged, of the 15 test frames.
    from evo.tools import file_interface

    kitti = file_interface.read_kitti_poses_file(str(out / "poses" / "kitti" / "test00.txt"))
    tum = file_interface.read_tum_trajectory_file(str(out / "poses" / "tum" / "test00.txt"))
    gt = file_interface.read_kitti_poses_file(str(out / "poses" / "kitti" / "test00_gt.txt"))
    assert kitti.num_poses == tum.num_poses == gt.num_poses == 16
    np.testing.assert_allclose(kitti.positions_xyz, tum.positions_xyz, atol=1e-9)
    np.testing.assert_allclose(kitti.poses_se3[0], np.eye(4), atol=1e-12)
    # The files hold the trajectory metrics.json reports (k = 100 %), not the sweep's last k.
    import torch

    from mfg_lightning.metrics.rpe import relative_pose_error

    rpe = relative_pose_error(
        torch.from_numpy(np.stack(kitti.poses_se3)), torch.from_numpy(np.stack(gt.poses_se3))
    )
    per_k = {k: m["test/test00/rpe_trans"] for k, m in payload["top_k_sweep"].items()}
    # (the tiny model's k = 2 % differs from its k = 100 % by ~4e-5 relative: the files must be
    # much closer to the one than to the other)
    here = float(rpe["trans"])
    assert here == pytest.approx(per_k["1"], rel=1e-6), per_k
    assert 100 * abs(here - per_k["1"]) < abs(here - per_k["0.02"]), per_k


def test_eval_align_aligns_figures_and_whole_trajectory_metrics(
    trained: Path, tmp_path: Path
) -> None:
    out = tmp_path / "eval"
    ckpt = f"ckpt_path={trained / 'checkpoints' / 'last.ckpt'}"
    run_module("mfg_lightning.evaluate", ckpt, "eval.align=sim3", "logger=none",
               f"hydra.run.dir={out}", cwd=tmp_path)  # fmt: skip
    payload = json.loads((out / "metrics.json").read_text())
    assert payload["eval_align"] == "sim3"
    metrics = payload["metrics"]
    # The whole-trajectory metrics are those of the written (unaligned) trajectory after Sim(3).
    import torch

    from mfg_lightning.metrics import aligned_trajectory_metrics
    from mfg_lightning.trajectory.pose_io import read_kitti_poses

    pred = torch.from_numpy(read_kitti_poses(out / "poses" / "kitti" / "test00.txt"))
    gt = torch.from_numpy(read_kitti_poses(out / "poses" / "kitti" / "test00_gt.txt"))
    expected = aligned_trajectory_metrics({"test00": (pred, gt)}, "sim3")
    for key in ("ate_traj", "ate_traj_std", "rpe_trans", "rpe_rot", "test00/ate_traj",
                "test00/ate_traj_scale", "test00/rpe_trans"):  # fmt: skip
        assert metrics[f"test/{key}"] == pytest.approx(expected[key], rel=1e-6, abs=1e-9), key
    unaligned = aligned_trajectory_metrics({"test00": (pred, gt)}, "none")
    assert metrics["test/ate_traj"] != pytest.approx(unaligned["ate_traj"], rel=1e-6)
    for kind in ("trajectory", "drift", "error"):
        png = (out / "trajectories" / f"{kind}_test00.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # A mode that does not exist is one error line.
    proc = run_module("mfg_lightning.evaluate", ckpt, "eval.align=7dof",
                      f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path, check=False)  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == (
        "error: eval.align='7dof': use one of none, se3, sim3, scale, scale_7dof, sim3_scale"
    )


def test_object_motion_task_scores_ours_and_the_baseline(trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "om"
    run_module("mfg_lightning.evaluate", "task=object_motion",
               f"ckpt_path={trained / 'checkpoints' / 'last.ckpt'}", f"hydra.run.dir={out}",
               cwd=tmp_path)  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    for key in ("test/object/iou", "test/object_baseline/iou", "test/object/near/recall",
                "test/object/far/iou", "test/object/epe"):  # fmt: skip
        assert key in metrics
    table = (out / "object_motion.md").read_text()
    assert "MFG + filters" in table and "threshold baseline" in table
    assert (out / "pictures" / "object_motion.png").stat().st_size > 1000


def test_missing_checkpoint_is_one_clear_line_and_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "eval"
    proc = run_module("mfg_lightning.evaluate", f"ckpt_path={tmp_path / 'nope.ckpt'}",
                      f"hydra.run.dir={out}", cwd=tmp_path, check=False)  # fmt: skip
    assert proc.returncode == 2
    assert (
        proc.stderr.strip().splitlines()[-1]
        == f"error: checkpoint not found: {tmp_path / 'nope.ckpt'}"
    )
    assert not (out / "metrics.json").exists()


def test_checkpoint_of_another_model_size_is_refused(trained: Path, tmp_path: Path) -> None:
    import torch

    ckpt = torch.load(trained / "checkpoints" / "last.ckpt", weights_only=False)
    ckpt["hyper_parameters"]["model_config"]["net"]["hidden_units"] = 32
    bad = tmp_path / "other.ckpt"
    torch.save(ckpt, bad)
    proc = run_module("mfg_lightning.evaluate", f"ckpt_path={bad}",
                      f"hydra.run.dir={tmp_path / 'e'}", cwd=tmp_path, check=False)  # fmt: skip
    assert proc.returncode == 2
    assert "weights do not fit an MFG with hidden_units=32" in proc.stderr


def test_object_motion_needs_depth(tmp_path: Path) -> None:
    """KITTI odometry has no depth: object motion refuses it with a message that says so."""
    from fake_datasets import make_kitti

    fk = make_kitti(tmp_path / "kitti")
    run = tmp_path / "run"
    common = [f"dataset.data_root={fk.root}", "flow.preset=ultrafast"]
    run_module("mfg_lightning.train", "dataset=kitti", *common, "model.net.hidden_units=16",
               "model.net.channels=[4,4,4,4,4]", "trainer.max_steps=1",
               "trainer.limit_val_batches=1", "trainer.val_check_interval=1", "test=false",
               "logger=none", f"hydra.run.dir={run}", cwd=tmp_path)  # fmt: skip
    proc = run_module("mfg_lightning.evaluate", "task=object_motion",
                      f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}",
                      f"hydra.run.dir={tmp_path / 'e'}", cwd=tmp_path, check=False)  # fmt: skip
    assert proc.returncode == 2
    assert "object motion extraction needs depth" in proc.stderr
    assert not (tmp_path / "e" / "metrics.json").exists()
