"""The mfg-eval-poses command line: results, output formats and one-line input errors."""

from __future__ import annotations

import json
import math
import re
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
from mfg_lightning.metrics.pose_evaluation import evaluate_trajectory
from mfg_lightning.trajectory.pose_io import read_kitti_poses, write_kitti_poses, write_tum_poses
from mfg_lightning.trajectory.trajectories import snippets_from_poses

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
    "drift_t_err",
    "drift_r_err",
    "ate_traj",
    "ate_traj_mean",
    "ate_traj_std",
    "ate_traj_scale",
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
        "ATE per 5-frame snippet ",
        "RPE translation, Δ = 2 frames",
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
    assert result["drift_t_err"] is None and result["drift_r_err"] is None

    # Pose 8 of the estimate 20 ms late: left out at evo's default --t-max-diff (0.01 s), matched
    # within 0.03 s.
    shifted = times.copy()
    shifted[7] += 0.02
    write_tum_poses(tmp_path / "pred.tum", shifted, pred)
    argv = ["--gt", str(tmp_path / "gt.tum"), "--pred", str(tmp_path / "pred.tum"), "--json"]
    code, out, err = _run(capsys, *argv)
    assert code == 0 and err == ""
    result = json.loads(out)
    assert (result["num_poses"], result["poses_given"], result["gt_poses"]) == (59, 60, 60)
    assert result["matched_by"] == "timestamp" and result["gt_times"] == str(tmp_path / "gt.tum")
    assert result["num_pairs"] == 58 and result["num_snippets"] == 56 - 5
    code, out, _ = _run(capsys, *argv, "--t-max-diff", "0.03")
    result = json.loads(out)
    assert result["num_poses"] == 60 and result["max_time_diff"] == pytest.approx(0.02)
    # Shifted by a whole second, nothing matches: one error line that says how many did.
    code, out, err = _run(capsys, *argv, "--t-offset", "100")
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith(
        f"error: {tmp_path / 'pred.tum'}:1: only 0 of its 60 poses match the 60 of the ground "
        f"truth {tmp_path / 'gt.tum'} (by timestamp within 0.01 s after an offset of 100 s"
    )


def _assert_one_line_error(capsys, argv: list[str], location: str, words: str) -> None:
    code, out, err = _run(capsys, *argv)
    assert code == 2
    assert out == ""
    assert err.startswith(f"error: {location}: "), err
    assert words in err and err.count("\n") == 1


def test_an_early_end_is_scored_on_its_frames_and_an_extra_frame_is_an_error(files, capsys) -> None:
    gt, pred, gt_poses, pred_poses = files
    write_kitti_poses(pred, pred_poses[:150])
    code, out, err = _run(capsys, "--gt", str(gt), "--pred", str(pred), "--json")
    assert code == 0 and err == ""
    result = json.loads(out)
    assert (result["num_poses"], result["poses_given"], result["gt_poses"]) == (150, 150, 160)
    assert result["matched_by"] == "frame" and result["num_pairs"] == 149
    expected = evaluate_trajectory(gt_poses[:150], pred_poses[:150])
    assert {k: result[k] for k in METRIC_KEYS} == pytest.approx(
        {k: expected[k] for k in METRIC_KEYS}, rel=1e-12
    )
    # A frame the ground truth does not have names the estimate's line.
    _assert_one_line_error(
        capsys,
        ["--gt", str(pred), "--pred", str(gt)],
        f"{gt}:151",
        f"frame 150 is not in the ground truth {pred} (150 poses, frames 0–149)",
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
    write_kitti_poses(gt, pred_poses[:10])
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
    assert proc.stderr == (
        f"error: {pred}:11: frame 10 is not in the ground truth {gt} (10 poses, frames 0–9)\n"
    )


# ------------------------------------------------------------------------------------------------
# Alignment and many methods
# ------------------------------------------------------------------------------------------------


def _similar(poses: np.ndarray, scale: float) -> np.ndarray:
    """``poses`` in another world frame and scale, as a monocular method would give them."""
    R = Rotation.from_rotvec([0.1, 0.8, -0.05]).as_matrix()
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ R.T + np.array([2.0, 0.5, -3.0])
    return out


def test_align_choices_are_the_metric_modes() -> None:
    from mfg_lightning.evaluate_poses import _ALIGN_CHOICES
    from mfg_lightning.metrics import ALIGN_MODES

    assert _ALIGN_CHOICES == ALIGN_MODES


def test_one_file_with_sim3_alignment(files, capsys) -> None:
    from mfg_lightning.metrics import ate_traj

    gt, pred, gt_poses, pred_poses = files
    write_kitti_poses(pred, _similar(pred_poses, 0.5))
    argv = ["--gt", str(gt), "--pred", str(pred), "--align", "sim3", "--n-to-align", "100"]
    code, out, err = _run(capsys, *argv, "--json")
    assert code == 0 and err == ""
    result = json.loads(out)
    assert result["align"] == "sim3" and result["n_to_align"] == 100
    expected = ate_traj(
        torch.from_numpy(read_kitti_poses(pred)), torch.from_numpy(gt_poses), "sim3", 100
    )
    for key, value in expected.items():
        assert result[key] == pytest.approx(value.item(), rel=1e-9)
    assert result["ate_traj_scale"] == pytest.approx(2.0, rel=0.05)
    code, out, _ = _run(capsys, *argv)
    assert code == 0
    assert "sim3 alignment on the first 100 poses" in out and "fitted scale (sim3)" in out
    assert re.search(r"ATE whole trajectory +│ +160 │", out)


@pytest.fixture
def kitti_methods(tmp_path: Path) -> tuple[Path, Path, Path, dict[str, np.ndarray]]:
    """Real KITTI GT poses 09 and 10 and two methods: noisy (metric) and scaled (monocular)."""
    if not KITTI_POSES.is_dir():
        pytest.skip(f"{KITTI_POSES} not present")
    a, b = tmp_path / "a", tmp_path / "b"
    gts = {}
    for i, seq in enumerate(("09", "10")):
        gts[seq] = read_kitti_poses(KITTI_POSES / f"{seq}.txt")
        write_kitti_poses(a / f"{seq}.txt", _perturb(gts[seq], 10 + i))
        write_tum_poses(b / f"{seq}.txt", np.arange(len(gts[seq])) / 10.0,
                        _similar(_perturb(gts[seq], 20 + i), 0.3))  # fmt: skip
    return KITTI_POSES, a, b, gts


def test_many_methods_write_tables_json_and_figures(kitti_methods, tmp_path: Path, capsys) -> None:
    gt_dir, a, b, gts = kitti_methods
    out = tmp_path / "results"
    argv = ["--gt", str(gt_dir), "--pred", f"a={a}", "--pred", f"b={b}", "--seqs", "09", "10",
            "--align", "sim3", "--out", str(out)]  # fmt: skip
    code, stdout, err = _run(capsys, *argv)
    assert code == 0 and err == ""
    for stem in ("table_09", "table_10", "table_overall"):
        md = (out / f"{stem}.md").read_text()
        assert md in stdout  # the same tables on stdout
        assert "| method | ATE traj RMSE (m) |" in md and "\n| a |" in md and "\n| b |" in md
        tex = (out / f"{stem}.tex").read_text()
        assert "\\begin{tabular}{lrrrrrrrrrr}" in tex and "t\\_err (\\%)" in tex
    payload = json.loads((out / "results.json").read_text())
    assert payload["sequences"] == ["09", "10"] and payload["align"] == "sim3"
    # Every number is that of the metric functions on the same files, per sequence.
    for name, directory in (("a", a), ("b", b)):
        for seq in ("09", "10"):
            from mfg_lightning.trajectory.pose_io import read_poses

            expected = evaluate_trajectory(
                gts[seq], read_poses(directory / f"{seq}.txt").poses, align="sim3"
            )
            got = payload["methods"][name]["sequences"][seq]
            for key in METRIC_KEYS:
                assert got[key] == pytest.approx(expected[key], rel=1e-9), (name, seq, key)
        overall = payload["methods"][name]["overall"]
        assert overall["num_poses"] == 1591 + 1201 and overall["ate_traj_scale"] is None
    # The monocular method's scale is found (1 / 0.3) and its aligned error is that of the noise.
    scale_b = payload["methods"]["b"]["sequences"]["09"]["ate_traj_scale"]
    assert scale_b == pytest.approx(1 / 0.3, rel=0.05)
    rows = list(__import__("csv").reader((out / "table_09.csv").open()))
    assert rows[0][:2] == ["method", "ATE traj RMSE (m)"] and [r[0] for r in rows[1:]] == ["a", "b"]
    assert float(rows[2][4]) == pytest.approx(scale_b, rel=1e-12)  # CSV keeps full precision
    for png in ("trajectory_09", "trajectory_10", "drift_09", "drift_10", "error_09", "error_10",
                "drift_overall"):  # fmt: skip
        data = (out / f"{png}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000, png
    # --json prints the same payload.
    code, stdout, _ = _run(capsys, *argv, "--json")
    assert code == 0 and json.loads(stdout) == payload


def _gt_dir(tmp_path: Path) -> tuple[Path, dict[str, np.ndarray]]:
    gts = {"00": _drive(120, 5), "01": _drive(90, 6)}
    for seq, poses in gts.items():
        write_kitti_poses(tmp_path / "gt" / f"{seq}.txt", poses)
    return tmp_path / "gt", gts


def test_a_method_missing_a_sequence_is_an_error_unless_left_out(tmp_path: Path, capsys) -> None:
    gt_dir, gts = _gt_dir(tmp_path)
    write_kitti_poses(tmp_path / "m" / "00.txt", _perturb(gts["00"], 1))
    out = tmp_path / "out"
    argv = ["--gt", str(gt_dir), "--pred", f"m={tmp_path / 'm'}", "--out", str(out)]
    _assert_one_line_error(
        capsys, argv, f"{tmp_path / 'm' / '01.txt'}:1",
        f"method 'm' has no poses for sequence 01 (ground truth {gt_dir / '01.txt'})",
    )  # fmt: skip
    assert not out.exists()  # nothing written
    code, stdout, err = _run(capsys, *argv, "--seqs", "00")
    assert code == 0 and err == "" and "Sequence 00 (120 poses)" in stdout
    assert (out / "table_00.md").is_file() and not (out / "table_01.md").exists()


def test_directory_inputs_name_the_file_and_line(tmp_path: Path, capsys) -> None:
    gt_dir, gts = _gt_dir(tmp_path)
    m = tmp_path / "m"
    write_kitti_poses(m / "00.txt", _perturb(gts["00"], 1))
    frames = np.r_[0:40, 45:85, 95]  # holes, and a frame 01 (90 poses) does not have
    write_kitti_poses(m / "01.txt", _perturb(gts["01"], 2)[np.minimum(frames, 89)], frames)
    argv = ["--gt", str(gt_dir), "--pred", f"m={m}"]
    _assert_one_line_error(
        capsys,
        argv,
        f"{m / '01.txt'}:81",
        f"frame 95 is not in the ground truth {gt_dir / '01.txt'}",
    )
    lines = (m / "00.txt").read_text().splitlines()
    lines[6] = " ".join([*lines[6].split()[:11], "inf"])
    (m / "00.txt").write_text("\n".join(lines) + "\n")
    _assert_one_line_error(capsys, argv, f"{m / '00.txt'}:7", "non-finite number: 'inf'")


def test_arguments_that_do_not_fit_together(tmp_path: Path, capsys) -> None:
    gt_dir, gts = _gt_dir(tmp_path)
    one = tmp_path / "one.txt"
    write_kitti_poses(one, gts["00"])
    code, out, err = _run(capsys, "--gt", str(gt_dir), "--pred", f"x={one}")
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith(f"error: --pred x={one}: a file holds one sequence but 2 are evaluated")
    # A single sequence of a directory can take a file.
    code, out, _ = _run(capsys, "--gt", str(gt_dir), "--pred", f"x={one}", "--seqs", "00")
    assert code == 0 and "| x |" in out
    code, _, err = _run(capsys, "--gt", str(gt_dir), "--pred", f"x={one}", "--pred", f"x={one}")
    assert code == 2 and "two methods are named 'x'" in err
    # Results are never written into the data.
    code, _, err = _run(capsys, "--gt", str(gt_dir), "--pred", str(gt_dir), "--out",
                        str(gt_dir / "results"))  # fmt: skip
    assert code == 2 and err.startswith(f"error: --out {gt_dir / 'results'}: inside the input")
    assert not (gt_dir / "results").exists()
    assert _run(capsys, "--gt", str(one), "--pred", str(one), "--n-to-align", "0")[0] == 2
    assert _run(capsys, "--gt", str(one), "--pred", str(one), "--align", "8dof")[0] == 2


def test_a_tum_estimate_takes_the_times_txt_of_kitti_s_layout(tmp_path: Path, capsys) -> None:
    """A KITTI ground truth at <root>/poses/<seq>.txt has its clock in
    <root>/sequences/<seq>/times.txt (KITTI's real times are ~10.36 Hz, not frame / 10)."""
    from mfg_lightning.trajectory.pose_io import write_kitti_times

    gt = _drive(120, 7)
    times = 0.0965 * np.arange(120)
    write_kitti_poses(tmp_path / "dataset" / "poses" / "00.txt", gt)
    write_kitti_times(tmp_path / "dataset" / "sequences" / "00" / "times.txt", times)
    keep = np.r_[0:50, 60:120]
    write_tum_poses(tmp_path / "est" / "00.txt", times[keep], _perturb(gt, 8)[keep])
    argv = ["--gt", str(tmp_path / "dataset" / "poses"), "--pred", f"m={tmp_path / 'est'}"]
    payload = json.loads(_run(capsys, *argv, "--json")[1])
    got = payload["methods"]["m"]["sequences"]["00"]
    assert got["gt_times"] == str(tmp_path / "dataset" / "sequences" / "00" / "times.txt")
    assert (got["num_poses"], got["poses_given"], got["gt_poses"]) == (110, 110, 120)
    expected = evaluate_trajectory(gt, _perturb(gt, 8)[keep], frames=keep)
    # rel 1e-9: the estimate went through a TUM text file, whose printed digits (not the
    # arithmetic) limit the agreement (drift_r_err differed by 6e-12 relative)
    assert {k: got[k] for k in METRIC_KEYS} == pytest.approx(
        {k: expected[k] for k in METRIC_KEYS}, rel=1e-9
    )
    # The matches table says how each method's poses were matched.
    code, out, _ = _run(capsys, *argv)
    assert code == 0 and "| m | 00 | timestamp | 110 | 110 | 120 |" in out
