"""Matching estimated poses to ground truth: evo's timestamp association, frame indices, times."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mfg_lightning.trajectory.association import (
    MatchOptions,
    SequenceMatcher,
    associate_timestamps,
    find_times,
    ground_truth_times,
    match_poses,
)
from mfg_lightning.trajectory.pose_io import (
    PoseFileError,
    read_poses,
    write_kitti_poses,
    write_kitti_times,
    write_tum_poses,
)


def _evo_rows(gt: np.ndarray, est: np.ndarray, max_diff: float, offset: float):
    """The rows evo's associate_trajectories keeps of each trajectory."""
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    def traj(stamps: np.ndarray) -> PoseTrajectory3D:
        # The row number as the x position tells which poses were kept.
        xyz = np.zeros((stamps.size, 3))
        xyz[:, 0] = np.arange(stamps.size)
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (stamps.size, 1))  # evo: w first
        return PoseTrajectory3D(xyz, quat, stamps)

    ref, est_ = sync.associate_trajectories(traj(gt), traj(est), max_diff=max_diff, offset_2=offset)
    return ref.positions_xyz[:, 0].astype(int), est_.positions_xyz[:, 0].astype(int)


@pytest.mark.parametrize("seed", range(6))
def test_timestamp_association_is_evo_s(seed: int) -> None:
    rng = np.random.default_rng(seed)
    gt = np.cumsum(rng.uniform(0.05, 0.15, 80))
    # Fewer or more poses than the ground truth, jittered, some far from any ground-truth time.
    n = (40, 160, 80)[seed % 3]
    est = np.sort(rng.uniform(gt[0] - 1.0, gt[-1] + 1.0, n))
    if seed % 2:
        est = np.unique(np.round(gt[rng.choice(80, n // 2, replace=False)] + 0.25, 3))
    for max_diff, offset in ((0.01, 0.0), (0.03, -0.25), (0.06, 0.1)):
        got = associate_timestamps(gt, est, max_diff, offset)
        expected = _evo_rows(gt, est, max_diff, offset)
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_array_equal(got[1], expected[1])


def test_ties_go_to_the_earlier_pose_as_in_evo() -> None:
    gt = np.array([0.0, 1.0, 2.0, 3.0])
    est = np.array([0.5, 2.5])  # exactly between two ground-truth times
    got = associate_timestamps(gt, est, max_diff=0.5)
    np.testing.assert_array_equal(got[0], [0, 2])
    np.testing.assert_array_equal(got[0], _evo_rows(gt, est, 0.5, 0.0)[0])


def _poses(n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n, dtype=np.float64)
    return poses


def test_kitti_files_match_by_frame_index(tmp_path: Path) -> None:
    write_kitti_poses(tmp_path / "gt.txt", _poses(20))
    write_kitti_poses(tmp_path / "late.txt", _poses(20)[[3, 4, 5, 9, 12]], [3, 4, 5, 9, 12])
    gt, late = read_poses(tmp_path / "gt.txt"), read_poses(tmp_path / "late.txt")
    match = match_poses(gt, late)
    assert match.by == "frame" and match.num_matched == 5 and match.num_gt == 20
    np.testing.assert_array_equal(match.gt_rows, [3, 4, 5, 9, 12])
    np.testing.assert_array_equal(match.pred_rows, np.arange(5))
    write_kitti_poses(tmp_path / "bad.txt", _poses(3), [3, 19, 20])
    with pytest.raises(PoseFileError, match=r"bad.txt:3: frame 20 is not in the ground truth"):
        match_poses(gt, read_poses(tmp_path / "bad.txt"))


def test_ground_truth_times_from_times_txt_or_a_nominal_clock(tmp_path: Path) -> None:
    root = tmp_path / "dataset"
    write_kitti_poses(root / "poses" / "09.txt", _poses(5))
    gt = read_poses(root / "poses" / "09.txt")
    assert find_times("09", gt.path) is None
    stamps, source = ground_truth_times(gt, None, 10.0)
    np.testing.assert_array_equal(stamps, np.arange(5) / 10.0)
    assert source == "frame / 10 Hz"
    write_kitti_times(root / "sequences" / "09" / "times.txt", 0.1036 * np.arange(5))
    found = find_times("09", gt.path)
    assert found == root / "sequences" / "09" / "times.txt"
    stamps, source = ground_truth_times(gt, found)
    assert stamps[1] == 0.1036 and source == str(found)
    # --gt-times: a directory of <seq>.txt or <seq>/times.txt, or the file for one sequence.
    assert find_times("09", gt.path, root / "sequences") == found
    assert find_times("09", gt.path, found, single=True) == found
    assert find_times("10", gt.path, root / "sequences") is None
    write_kitti_times(tmp_path / "short.txt", np.arange(4.0))
    with pytest.raises(PoseFileError, match=r"short.txt:5: 4 timestamps for the 5 poses of"):
        ground_truth_times(gt, tmp_path / "short.txt")
    write_kitti_times(tmp_path / "back.txt", np.array([0.0, 0.1, 0.3, 0.2, 0.4]))
    with pytest.raises(PoseFileError, match=r"back.txt:4: timestamp 0.2 does not follow 0.3"):
        ground_truth_times(gt, tmp_path / "back.txt")


def test_sequence_matcher_refuses_too_few_matches_and_unknown_times(tmp_path: Path) -> None:
    write_kitti_poses(tmp_path / "gt.txt", _poses(10))
    gt = read_poses(tmp_path / "gt.txt")
    write_tum_poses(tmp_path / "est.tum", np.array([0.0, 0.1, 0.5]), _poses(3))
    est = read_poses(tmp_path / "est.tum")
    match = SequenceMatcher("gt", gt, MatchOptions(minimum=3), single=True)(est)
    assert match.num_matched == 3 and match.times == "frame / 10 Hz"
    assert match.summary()["poses_given"] == 3 and match.max_time_diff == 0.0
    # 50 ms late, the last pose matches no ground-truth time at evo's 0.01 s.
    write_tum_poses(tmp_path / "late.tum", np.array([0.0, 0.1, 0.55]), _poses(3))
    late = read_poses(tmp_path / "late.tum")
    with pytest.raises(PoseFileError, match=r"late.tum:1: only 2 of its 3 poses match the 10 of"):
        SequenceMatcher("gt", gt, MatchOptions(minimum=3), single=True)(late)
    shifted = SequenceMatcher("gt", gt, MatchOptions(offset=-0.05, minimum=1), single=True)(late)
    np.testing.assert_array_equal(shifted.gt_rows, [5])
    with pytest.raises(ValueError, match=r"--gt-times .*: no times for sequence gt"):
        SequenceMatcher("gt", gt, MatchOptions(gt_times=tmp_path / "none"), single=False)(est)
    write_tum_poses(tmp_path / "back.tum", np.array([0.0, 0.2, 0.1]), _poses(3))
    with pytest.raises(PoseFileError, match=r"back.tum:3: timestamp 0.1 does not follow 0.2"):
        SequenceMatcher("gt", gt, MatchOptions(), single=True)(read_poses(tmp_path / "back.tum"))
