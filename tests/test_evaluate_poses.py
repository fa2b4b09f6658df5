"""The mfg-eval-poses command line: results, output formats and one-line input errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import SHARED
from mfg_lightning.evaluate_poses import main
from mfg_lightning.metrics import relative_pose_error, snippet_ate
from mfg_lightning.pose_io import read_kitti_poses, write_kitti_poses, write_tum_poses
from mfg_lightning.trajectories import snippets_from_poses

KITTI_POSES = SHARED / "data" / "kitti_odometry" / "poses"
METRIC_KEYS = {
    "ate",
    "ate_std",
    "ate_rmse",
    "rpe_trans",
    "rpe_trans_std",
    "rpe_trans_rmse",
    "rpe_rot",
    "rpe_rot_std",
    "rpe_rot_rmse",
    "kitti_t_err",
    "kitti_r_err",
}


def _drive(n: int, seed: int) -> np.ndarray:
    """About 1 m per frame forward with gentle turns."""
    rng = np.random.default_rng(seed)
    motions = np.tile(np.eye(4), (n - 1, 1, 1))
    rotvec = np.stack(
        [np.zeros(n - 1), 0.01 * np.sin(np.arange(n - 1) / 30.0), np.zeros(n - 1)], axis=1
    )
    motions[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    motions[:, 2, 3] = 1.0 + rng.normal(0, 0.05, n - 1)
    poses = [np.eye(4)]
    for m in motions:
        poses.append(poses[-1] @ m)
    return np.stack(poses)


def _perturb(poses: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = np.tile(np.eye(4), (len(poses), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 2e-3, (len(poses), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, 0.05, (len(poses), 3))
    return poses @ noise


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def files(tmp_path: Path) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    gt = _drive(160, 0)
    pred = _perturb(gt, 1)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "pred.txt", pred)
    return tmp_path / "gt.txt", tmp_path / "pred.txt", gt, pred


def test_perturbed_kitti_09_gives_every_metric(tmp_path: Path, capsys) -> None:
    if not KITTI_POSES.is_dir():
        pytest.skip(f"{KITTI_POSES} not present")
    gt_path = KITTI_POSES / "09.txt"
    gt = read_kitti_poses(gt_path)
    pred = _perturb(gt, 2)
    pred_path = tmp_path / "09_pred.txt"
    write_kitti_poses(pred_path, pred)
    code, out, err = _run(capsys, "--gt", str(gt_path), "--pred", str(pred_path), "--json")
    assert code == 0 and err == ""
    result = json.loads(out)
    assert set(result) >= METRIC_KEYS and set(result["units"]) == METRIC_KEYS
    assert all(math.isfinite(result[key]) for key in METRIC_KEYS)
    assert result["num_poses"] == 1591 and result["num_snippets"] == 1587
    assert result["num_pairs"] == 1590 and result["num_segments"] > 0
    assert result["gt_format"] == result["pred_format"] == "kitti"
    # The numbers are those of the metric functions on the same poses (up to ~1e-9: the command
    # projects the file's 6-digit rotations onto SO(3) before it forms the snippets).
    P, Q = torch.from_numpy(pred), torch.from_numpy(gt)
    ate = snippet_ate(snippets_from_poses(P), snippets_from_poses(Q))
    rpe = relative_pose_error(P, Q)
    assert result["ate"] == pytest.approx(ate["ate"].item(), rel=1e-6)
    assert result["rpe_rot"] == pytest.approx(rpe["rot"].item(), rel=1e-6)


def test_table_output(files, capsys) -> None:
    gt, pred, _, _ = files
    code, out, err = _run(capsys, "--gt", str(gt), "--pred", str(pred), "--delta", "2")
    assert code == 0 and err == ""
    for words in (
        "ATE, 5-frame snippets (156)",
        "RPE translation, Δ = 2",
        "KITTI t_err",
        "deg/100m",
    ):
        assert words in out


def test_tum_files_are_matched_by_timestamps(tmp_path: Path, capsys) -> None:
    gt = _drive(60, 3)
    pred = _perturb(gt, 4)
    times = 1305031102.0 + 0.1 * np.arange(60)
    write_tum_poses(tmp_path / "gt.tum", times, gt)
    write_tum_poses(tmp_path / "pred.tum", times, pred)
    code, out, _ = _run(
        capsys, "--gt", str(tmp_path / "gt.tum"), "--pred", str(tmp_path / "pred.tum"), "--json"
    )
    assert code == 0
    result = json.loads(out)
    assert result["gt_format"] == result["pred_format"] == "tum" and result["num_poses"] == 60
    assert result["ate"] > 0 and result["rpe_trans"] > 0
    # About 59 m of path: no complete 100 m segment, so the drift is undefined, written as null.
    assert result["num_segments"] == 0
    assert result["kitti_t_err"] is None and result["kitti_r_err"] is None

    shifted = times.copy()
    shifted[7] += 0.01
    write_tum_poses(tmp_path / "pred.tum", shifted, pred)
    code, out, err = _run(
        capsys, "--gt", str(tmp_path / "gt.tum"), "--pred", str(tmp_path / "pred.tum")
    )
    assert code == 2 and out == ""
    assert err.startswith(
        f"error: {tmp_path / 'pred.tum'}:8: timestamp 1305031102.71 differs from the ground "
        f"truth's 1305031102.7 ({tmp_path / 'gt.tum'}:8)"
    )
    assert err.count("\n") == 1


def _assert_one_line_error(capsys, argv: list[str], location: str, words: str) -> None:
    code, out, err = _run(capsys, *argv)
    assert code == 2
    assert out == ""
    assert err.startswith(f"error: {location}: "), err
    assert words in err and err.count("\n") == 1


def test_files_of_different_lengths(files, capsys) -> None:
    gt, pred, _, pred_poses = files
    write_kitti_poses(pred, pred_poses[:150])
    _assert_one_line_error(
        capsys, ["--gt", str(gt), "--pred", str(pred)], f"{pred}:151", "ends after 150 poses"
    )
    # The shorter file is named, whichever it is.
    _assert_one_line_error(
        capsys, ["--gt", str(pred), "--pred", str(gt)], f"{pred}:151", f"{gt} has 160"
    )


def test_malformed_and_non_finite_lines(files, capsys) -> None:
    gt, pred, _, _ = files
    lines = pred.read_text().splitlines()
    lines[41] = lines[41].replace(lines[41].split()[5], "1.0.0")
    pred.write_text("\n".join(lines) + "\n")
    argv = ["--gt", str(gt), "--pred", str(pred), "--json"]
    _assert_one_line_error(capsys, argv, f"{pred}:42", "not a number: '1.0.0'")
    lines[41] = " ".join([*lines[40].split()[:11], "nan"])
    pred.write_text("\n".join(lines) + "\n")
    _assert_one_line_error(capsys, argv, f"{pred}:42", "non-finite")
    _assert_one_line_error(
        capsys,
        ["--gt", str(gt.with_name("missing.txt")), "--pred", str(pred)],
        f"{gt.with_name('missing.txt')}:1",
        "cannot read file",
    )


def test_forced_format_and_bad_arguments(files, capsys) -> None:
    gt, pred, _, _ = files
    _assert_one_line_error(
        capsys,
        ["--gt", str(gt), "--pred", str(pred), "--format", "tum"],
        f"{gt}:1",
        "expected 8 numbers",
    )
    assert _run(capsys, "--help")[0] == 0
    assert _run(capsys, "--gt", str(gt), "--pred", str(pred), "--delta", "0")[0] == 2
    assert _run(capsys, "--gt", str(gt))[0] == 2


def test_runs_as_a_module(files) -> None:
    """``python -m mfg_lightning.evaluate_poses``: exit status and streams of an input error."""
    gt, pred, _, pred_poses = files
    write_kitti_poses(pred, pred_poses[:10])
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "mfg_lightning.evaluate_poses",
            "--gt",
            str(gt),
            "--pred",
            str(pred),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr == f"error: {pred}:11: file ends after 10 poses but {gt} has 160\n"
