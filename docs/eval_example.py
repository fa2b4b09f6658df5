"""Regenerate the pose-evaluation example of ``docs/evaluate_poses.md`` (``docs/img/eval_*.png``
and its table).

Two made-up "methods" on the real KITTI ground truth of sequences 09 and 10: ``stereo`` composes
the true frame-to-frame motions with small errors (metric scale, slow drift); ``mono`` has larger
rotation errors and is known only up to scale, in its own world frame (a monocular method's
output). Both are evaluated with ``mfg-eval-poses --align sim3`` exactly as a user would run it.

    python docs/eval_example.py [--poses ../shared/data/kitti_odometry/poses]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mfg_lightning.evaluate_poses import main
from mfg_lightning.trajectory.pose_io import read_kitti_poses, write_kitti_poses, write_tum_poses

REPO = Path(__file__).resolve().parents[1]


def drifting(gt: np.ndarray, seed: int, rot_sigma: float, trans_sigma: float) -> np.ndarray:
    """The true motions composed with Gaussian errors (rad per frame, m per frame)."""
    rng = np.random.default_rng(seed)
    motions = np.linalg.inv(gt[:-1]) @ gt[1:]
    noise = np.tile(np.eye(4), (len(motions), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, rot_sigma, (len(motions), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, trans_sigma, (len(motions), 3))
    poses = [np.eye(4)]
    for m in motions @ noise:
        poses.append(poses[-1] @ m)
    return np.stack(poses)


def monocular(poses: np.ndarray, scale: float) -> np.ndarray:
    """``poses`` at another scale in another world frame."""
    R = Rotation.from_rotvec([0.0, 0.6, 0.0]).as_matrix()
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ R.T
    return out


def run(poses_dir: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for i, seq in enumerate(("09", "10")):
            gt = read_kitti_poses(poses_dir / f"{seq}.txt")
            write_kitti_poses(tmp / "stereo" / f"{seq}.txt", drifting(gt, 100 + i, 1e-3, 0.02))
            mono = monocular(drifting(gt, 200 + i, 2e-3, 0.03), 0.25)
            write_tum_poses(tmp / "mono" / f"{seq}.txt", np.arange(len(gt)) / 10.0, mono)
        out = tmp / "out"
        argv = ["--gt", str(poses_dir), "--pred", f"stereo={tmp / 'stereo'}",
                "--pred", f"mono={tmp / 'mono'}", "--seqs", "09", "10", "--align", "sim3",
                "--out", str(out)]  # fmt: skip
        if main(argv) != 0:
            raise SystemExit("mfg-eval-poses failed")
        img = REPO / "docs" / "img"
        for name in ("trajectory_09", "drift_overall"):
            shutil.copyfile(out / f"{name}.png", img / f"eval_{name}.png")
        print((out / "table_overall.md").read_text())


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--poses", type=Path, default=REPO.parent / "shared" / "data" / "kitti_odometry" / "poses"
    )
    run(parser.parse_args().poses)
