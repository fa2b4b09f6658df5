"""Pose files: exact round trips, the distributed KITTI file, and every kind of bad input."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import KITTI_POSES, NO_KITTI_POSES
from mfg_lightning.trajectory import pose_io
from mfg_lightning.trajectory.pose_io import (
    PoseFileError,
    detect_pose_format,
    read_kitti_poses,
    read_kitti_times,
    read_poses,
    read_tum_poses,
    write_kitti_poses,
    write_tum_poses,
)

KITTI_LINES = (
    "1.000000e+00 1.197625e-11 1.704638e-10 5.551115e-17 1.197625e-11 1.000000e+00 "
    "3.562503e-10 0.000000e+00 1.704638e-10 3.562503e-10 1.000000e+00 2.220446e-16\n"
    "9.999268e-01 -3.092411e-03 1.169425e-02 2.138869e-02 3.079219e-03 9.999946e-01 "
    "1.146026e-03 -8.456433e-03 -1.169773e-02 -1.109933e-03 9.999310e-01 2.880714e-01\n"
)
TUM_TEXT = (
    "# ground truth trajectory\n"
    "# timestamp tx ty tz qx qy qz qw\n"
    "1305031102.175304 1.2334 -0.0113 1.6941 0.7907 0.4393 -0.1770 -0.3879\n"
    "1305031102.211214 1.2335 -0.0112 1.6923 0.7908 0.4393 -0.1772 -0.3877\n"
)


def _random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 100, (n, 3))
    return poses


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ------------------------------------------------------------------------------------------------
# Reading what is distributed, and round trips
# ------------------------------------------------------------------------------------------------


def test_reads_kitti_lines_as_distributed(tmp_path: Path) -> None:
    path = _write(tmp_path / "09.txt", KITTI_LINES)
    poses = read_kitti_poses(path)
    assert poses.shape == (2, 4, 4) and poses.dtype == np.float64
    assert poses[1, 0, 1] == -3.092411e-03 and poses[1, 2, 3] == 2.880714e-01
    np.testing.assert_array_equal(poses[:, 3], [[0, 0, 0, 1], [0, 0, 0, 1]])
    assert detect_pose_format(path) == "kitti"


def test_reads_the_real_kitti_09_file(tmp_path: Path) -> None:
    if not KITTI_POSES.is_dir():
        pytest.skip(NO_KITTI_POSES)
    source = KITTI_POSES / "09.txt"
    poses = read_kitti_poses(source)
    assert poses.shape == (1591, 4, 4)
    np.testing.assert_array_equal(
        poses[:, :3, :].reshape(-1, 12), np.loadtxt(source, dtype=np.float64)
    )
    out = tmp_path / "09_copy.txt"
    write_kitti_poses(out, poses)
    np.testing.assert_array_equal(read_kitti_poses(out), poses)


def test_kitti_round_trip_is_exact(tmp_path: Path) -> None:
    poses = _random_poses(30, 0)
    path = tmp_path / "poses.txt"
    write_kitti_poses(path, poses)
    np.testing.assert_array_equal(read_kitti_poses(path), poses)
    write_kitti_poses(path, poses[:, :3, :])  # (N, 3, 4) is accepted too
    np.testing.assert_array_equal(read_kitti_poses(path), poses)
    assert all(len(line.split()) == 12 for line in path.read_text().splitlines())


def test_reads_kitti_files_with_a_frame_index_first(tmp_path: Path) -> None:
    """kitti-odom-eval's first layout: the frame index, then the pose; a late start, holes."""
    rows = KITTI_LINES.splitlines()
    path = _write(tmp_path / "09.txt", f"2 {rows[0]}\n7.0 {rows[1]}\n")
    assert detect_pose_format(path) == "kitti"
    pose_file = read_poses(path)
    assert pose_file.format == "kitti" and pose_file.frames is not None
    np.testing.assert_array_equal(pose_file.frames, [2, 7])
    np.testing.assert_array_equal(pose_file.frame_indices(), [2, 7])
    np.testing.assert_array_equal(
        pose_file.poses, read_kitti_poses(_write(tmp_path / "p", KITTI_LINES))
    )
    plain = read_poses(tmp_path / "p", "kitti")
    assert plain.frames is None
    np.testing.assert_array_equal(plain.frame_indices(), [0, 1])
    # Written back with its frames, exactly.
    poses = _random_poses(4, 3)
    write_kitti_poses(tmp_path / "w.txt", poses, [0, 5, 6, 40])
    again = read_poses(tmp_path / "w.txt")
    np.testing.assert_array_equal(again.frames, [0, 5, 6, 40])
    np.testing.assert_array_equal(again.poses, poses)
    with pytest.raises(ValueError, match="increasing"):
        write_kitti_poses(tmp_path / "x.txt", poses, [0, 5, 5, 6])


@pytest.mark.parametrize(
    ("lines", "line", "words"),
    [
        (["2.5 {0}", "3 {1}"], 1, "frame index 2.5 is not a whole number >= 0"),
        (["-1 {0}", "3 {1}"], 1, "frame index -1.0 is not a whole number >= 0"),
        (["4 {0}", "4 {1}"], 2, "frame index 4 does not follow 4 (line 1): frame indices must"),
        (["4 {0}", "{1}"], 2, "expected 13 numbers (a frame index and a row-major 3×4 pose)"),
        (["{0}", "4 {1}"], 2, "expected 12 numbers (a row-major 3×4 pose), found 13"),
    ],
)
def test_bad_frame_indices_name_the_line(tmp_path: Path, lines, line: int, words: str) -> None:
    rows = KITTI_LINES.splitlines()
    path = _write(tmp_path / "bad.txt", "\n".join(x.format(*rows) for x in lines) + "\n")
    with pytest.raises(PoseFileError) as info:
        read_poses(path)
    assert str(info.value).startswith(f"{path}:{line}: {words}"), str(info.value)


def test_reads_tum_with_comments_as_distributed(tmp_path: Path) -> None:
    path = _write(tmp_path / "groundtruth.txt", TUM_TEXT)
    assert detect_pose_format(path) == "tum"
    pose_file = read_poses(path)
    assert pose_file.format == "tum"
    assert pose_file.lines.tolist() == [3, 4]
    assert pose_file.timestamps is not None and pose_file.timestamps[0] == 1305031102.175304
    quat = np.array([0.7907, 0.4393, -0.1770, -0.3879])
    expected = Rotation.from_quat(quat / np.linalg.norm(quat)).as_matrix()
    np.testing.assert_allclose(pose_file.poses[0, :3, :3], expected, atol=1e-15)
    np.testing.assert_array_equal(pose_file.poses[0, :3, 3], [1.2334, -0.0113, 1.6941])


def test_tum_round_trip(tmp_path: Path) -> None:
    poses = _random_poses(25, 1)
    times = 1305031102.0 + 0.033 * np.arange(25)
    path = tmp_path / "traj.tum"
    write_tum_poses(path, times, poses)
    read_times, read = read_tum_poses(path)
    np.testing.assert_array_equal(read_times, times)
    np.testing.assert_array_equal(read[:, :3, 3], poses[:, :3, 3])
    # Rotations pass through a quaternion: equal to rounding.
    np.testing.assert_allclose(read[:, :3, :3], poses[:, :3, :3], atol=1e-14)
    assert detect_pose_format(path) == "tum"


def test_reads_kitti_times(tmp_path: Path) -> None:
    path = _write(tmp_path / "times.txt", "0.000000e+00\n1.036712e-01\n2.073425e-01\n")
    np.testing.assert_array_equal(read_kitti_times(path), [0.0, 1.036712e-01, 2.073425e-01])


def test_kitti_times_round_trip_is_exact(tmp_path: Path) -> None:
    times = np.arange(7) / 10.0  # 10 Hz, as the export writes them
    pose_io.write_kitti_times(tmp_path / "times.txt", times)
    np.testing.assert_array_equal(read_kitti_times(tmp_path / "times.txt"), times)
    with pytest.raises(ValueError, match="finite"):
        pose_io.write_kitti_times(tmp_path / "bad.txt", [0.0, float("nan")])
    assert not (tmp_path / "bad.txt").exists()


def test_crlf_blank_lines_and_missing_final_newline_are_fine(tmp_path: Path) -> None:
    text = KITTI_LINES.replace("\n", "\r\n", 1).rstrip("\n")
    path = _write(tmp_path / "poses.txt", "\n" + text)
    pose_file = read_poses(path, "kitti")
    assert len(pose_file) == 2 and pose_file.lines.tolist() == [2, 3]


# ------------------------------------------------------------------------------------------------
# Bad input: one line naming file and line, nothing half-written
# ------------------------------------------------------------------------------------------------


def _kitti_rows(n: int) -> list[str]:
    return [" ".join(repr(v) for v in p[:3].reshape(-1).tolist()) for p in _random_poses(n, 2)]


def _bad_cases() -> list[tuple[str, str, str, int, str]]:
    """(name, text, format, expected line, expected words in the reason)."""
    rows = _kitti_rows(4)
    tum = TUM_TEXT.splitlines()
    not_rotation = " ".join(["2.0"] * 12)
    return [
        (
            "malformed",
            "\n".join([*rows[:2], rows[2].replace(rows[2].split()[3], "abc"), rows[3]]),
            "kitti",
            3,
            "not a number: 'abc'",
        ),
        (
            "too few columns",
            "\n".join([*rows[:3], " ".join(rows[3].split()[:11])]),
            "kitti",
            4,
            "expected 12 numbers",
        ),
        (
            "too many columns",
            "\n".join([rows[0], rows[1] + " 1.0"]),
            "kitti",
            2,
            "expected 12 numbers",
        ),
        (
            "nan",
            "\n".join([rows[0], rows[1].replace(rows[1].split()[3], "nan")]),
            "kitti",
            2,
            "non-finite number: 'nan'",
        ),
        (
            "inf",
            "\n".join([rows[0], rows[1].replace(rows[1].split()[11], "-inf")]),
            "kitti",
            2,
            "non-finite number: '-inf'",
        ),
        ("not a rotation", "\n".join([rows[0], not_rotation]), "kitti", 2, "not a rotation"),
        ("empty", "", "kitti", 1, "empty file"),
        ("only comments", "# nothing\n\n  \n", "auto", 1, "empty file"),
        ("unknown columns", "1 2 3 4 5 6 7\n", "auto", 1, "cannot tell the format"),
        (
            "tum columns",
            "\n".join([*tum[:3], " ".join(tum[3].split()[:7])]),
            "tum",
            4,
            "expected 8 numbers",
        ),
        ("tum quaternion", "\n".join([*tum[:2], "1.0 0 0 0 0 0 0 0"]), "tum", 3, "norm 0"),
        (
            "tum inf time",
            "\n".join([*tum[:3], tum[3].replace(tum[3].split()[0], "inf")]),
            "auto",
            4,
            "non-finite",
        ),
        ("binary", "\n".join([rows[0], "\udcff"]), "kitti", 2, "not UTF-8"),
    ]


@pytest.mark.parametrize("case", _bad_cases(), ids=lambda c: c[0])
def test_bad_input_names_file_and_line(tmp_path: Path, case: tuple) -> None:
    _, text, fmt, line, words = case
    path = tmp_path / "bad.txt"
    path.write_bytes(text.encode("utf-8", errors="surrogateescape"))
    with pytest.raises(PoseFileError) as info:
        read_poses(path, fmt)
    message = str(info.value)
    assert message.startswith(f"{path}:{line}: "), message
    assert words in message
    assert "\n" not in message
    assert info.value.line == line and info.value.path == str(path)
    assert isinstance(info.value, ValueError)


def test_missing_file_and_bad_times(tmp_path: Path) -> None:
    missing = tmp_path / "nope.txt"
    with pytest.raises(PoseFileError, match=rf"^{missing}:1: cannot read file: No such file"):
        read_poses(missing)
    with pytest.raises(PoseFileError, match=r":2: expected 1 number \(a time"):
        read_kitti_times(_write(tmp_path / "times.txt", "0.0\n0.1 0.2\n"))


def test_failed_writes_leave_the_previous_file(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "poses.txt"
    original = _random_poses(3, 3)
    write_kitti_poses(path, original)
    before = path.read_bytes()
    bad = _random_poses(3, 4)
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_kitti_poses(path, bad)
    with pytest.raises(ValueError, match="timestamps"):
        write_tum_poses(path, np.arange(2.0), original)
    with pytest.raises(ValueError, match="N >= 1"):
        write_kitti_poses(path, np.zeros((0, 4, 4)))

    # A failure after the text is written (here: the final rename) must not leave a temp file
    # nor touch the target.
    def fail(*args: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(pose_io.os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_kitti_poses(path, _random_poses(3, 5))
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["poses.txt"]


def test_writes_keep_the_permissions_of_the_file_they_replace(tmp_path: Path) -> None:
    path = tmp_path / "poses.txt"
    write_kitti_poses(path, _random_poses(2, 6))
    path.chmod(0o640)
    write_kitti_poses(path, _random_poses(2, 7))
    assert path.stat().st_mode & 0o777 == 0o640
