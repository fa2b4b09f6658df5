"""mfg-eval-poses with evo's flags against evo's own command-line tools on the same files.

``evo_ape`` and ``evo_rpe`` run as a user runs them (subprocess), each with ``--save_results``;
every statistic (max, mean, median, min, rmse, sse, std) and every per-element error of its
archive must be mfg-eval-poses's for the same flags, and the archive mfg-eval-poses writes must
open in ``evo_res``. Tiny TUM trajectories (40 poses) keep it to a few seconds; without evo the
module is skipped. evo is GPL: it is a test-only dependency, never imported by ``src/``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import zipfile
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mfg_lightning.evaluate_poses import main
from mfg_lightning.metrics.stats import STATISTICS
from mfg_lightning.trajectory.pose_io import write_tum_poses

pytest.importorskip("evo")
if shutil.which("evo_ape") is None or shutil.which("evo_rpe") is None:
    pytest.skip("evo's command-line tools are not on PATH", allow_module_level=True)

N = 40


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A curving, climbing ground truth (0.1 s apart) and a noisy estimate at 0.6 × its scale
    in another world frame (a monocular method's output), both TUM."""
    tmp = tmp_path_factory.mktemp("evo")
    rng = np.random.default_rng(3)
    t = np.arange(N)
    gt = np.tile(np.eye(4), (N, 1, 1))
    gt[:, :3, :3] = Rotation.from_rotvec(np.stack([0.01 * t, 0.05 * t, 0.002 * t], 1)).as_matrix()
    gt[:, :3, 3] = np.stack([8 * np.sin(0.05 * t), 0.03 * t, 8 * (1 - np.cos(0.05 * t)) + t], 1)
    noise = np.tile(np.eye(4), (N, 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.02, (N, 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, 0.15, (N, 3))
    est = gt @ noise
    R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    est[:, :3, :3] = R @ est[:, :3, :3]
    est[:, :3, 3] = 0.6 * est[:, :3, 3] @ R.T + np.array([1.0, -2.0, 0.5])
    times = 1000.0 + 0.1 * t
    write_tum_poses(tmp / "gt.tum", times, gt)
    write_tum_poses(tmp / "est.tum", times, est)
    return {"gt": tmp / "gt.tum", "est": tmp / "est.tum", "dir": tmp}


def _archive(path: Path) -> tuple[dict, dict, np.ndarray]:
    """``(info, stats, error_array)`` of an evo result archive, read as plain zip/JSON/npy."""
    with zipfile.ZipFile(path) as z:
        info = json.loads(z.read("info.json"))
        stats = json.loads(z.read("stats.json"))
        errors = np.load(BytesIO(z.read("error_array.npy")))
    return info, stats, errors


def _evo(tool: str, files: dict[str, Path], flags: list[str], name: str) -> tuple[dict, np.ndarray]:
    out = files["dir"] / f"evo_{name}.zip"
    cmd = [tool, "tum", str(files["gt"]), str(files["est"]), *flags, "--save_results", str(out),
           "--no_warnings"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr + done.stdout
    _, stats, errors = _archive(out)
    return stats, errors


def _ours(files: dict[str, Path], flags: list[str], name: str, capsys) -> tuple[dict, Path]:
    zip_path = files["dir"] / f"ours_{name}.zip"
    argv = ["--gt", str(files["gt"]), "--pred", str(files["est"]), *flags, "--json",
            "--save_results", str(zip_path)]  # fmt: skip
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 0 and err == "", err
    return json.loads(out), zip_path


#: (name, evo tool, flags given to both).
CASES = [
    ("ape_sim3", "evo_ape", ["-as"]),
    ("ape_scale_only", "evo_ape", ["-s"]),
    ("ape_origin_deg", "evo_ape", ["--align_origin", "-r", "angle_deg"]),
    ("ape_se3_n20_full", "evo_ape", ["-a", "--n_to_align", "20", "-r", "full"]),
    ("rpe_delta3", "evo_rpe", ["-as", "--delta", "3"]),
    ("rpe_all_pairs_rad", "evo_rpe", ["-a", "--delta", "3", "--all_pairs", "-r", "angle_rad"]),
    ("rpe_metres_rot", "evo_rpe", ["-as", "--delta", "2", "--delta_unit", "m", "-r", "rot_part"]),
    ("rpe_metres_all_pd", "evo_rpe",
     ["--delta", "1.5", "-u", "m", "--all_pairs", "-r", "point_distance"]),
]  # fmt: skip


@pytest.mark.parametrize(("name", "tool", "flags"), CASES, ids=[c[0] for c in CASES])
def test_evo_flags_give_evo_s_numbers(files, capsys, name: str, tool: str, flags: list[str]):
    expected, expected_errors = _evo(tool, files, flags, name)
    result, zip_path = _ours(files, flags, name, capsys)
    metric = "ape" if tool == "evo_ape" else "rpe"
    got = result["statistics"][metric]
    assert set(expected) == set(STATISTICS)
    # evo's angles come from scipy's rotation vectors, ours from the trace of the same matrix.
    tol = {"rel": 1e-9, "abs": 1e-7 if "angle_deg" in flags else 1e-9}
    for stat in STATISTICS:
        assert got[stat] == pytest.approx(expected[stat], **tol), (name, stat)
    # The archive mfg-eval-poses wrote holds the same per-element errors as evo's.
    single = zip_path.with_name(f"ours_{name}_{metric}.zip")
    info, stats, errors = _archive(single)
    np.testing.assert_allclose(errors, expected_errors, **{"rtol": 1e-9, "atol": tol["abs"]})
    assert stats == pytest.approx(got) and info["label"].startswith(metric.upper())


def test_saved_results_open_in_evo_res(files, capsys) -> None:
    _evo("evo_ape", files, ["-as"], "res")
    _, zip_path = _ours(files, ["-as"], "res", capsys)
    ours = zip_path.with_name("ours_res_ape.zip")
    done = subprocess.run(
        ["evo_res", str(ours), str(files["dir"] / "evo_res.zip"), "--use_filenames",
         "--no_warnings"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr + done.stdout
    # evo_res prints the statistics of each archive in one row (wrapped into blocks of columns);
    # the two archives' rows are the same numbers.
    values: dict[str, list[str]] = {}
    for line in done.stdout.splitlines():
        cells = line.replace("\\", "").split()
        if cells and cells[0].endswith(".zip"):
            values.setdefault(cells[0], []).extend(cells[1:])
    assert len(values) == 2 and len(set(map(tuple, values.values()))) == 1, done.stdout
    assert len(next(iter(values.values()))) == len(STATISTICS)


def test_kitti_odom_eval_names_and_unpadded_sequences(files, tmp_path: Path, capsys) -> None:
    """kitti-odom-eval's ``--align 7dof`` is ``sim3`` and ``--seqs 9`` reads ``09.txt``."""
    gt, est = tmp_path / "gt", tmp_path / "est"
    gt.mkdir()
    est.mkdir()
    shutil.copyfile(files["gt"], gt / "09.txt")
    shutil.copyfile(files["est"], est / "09.txt")
    runs = {}
    for key, flags in (("7dof", ["--seqs", "9", "--align", "7dof"]),
                       ("sim3", ["--seqs", "09", "--align", "sim3"])):  # fmt: skip
        assert main(["--gt", str(gt), "--pred", f"m={est}", *flags, "--json"]) == 0
        runs[key] = json.loads(capsys.readouterr().out)
    assert runs["7dof"]["sequences"] == ["09"] and runs["7dof"]["align"] == "sim3"
    assert runs["7dof"]["methods"] == runs["sim3"]["methods"]
