"""mfg-eval-poses against its peers on the files they read: kitti-odom-eval's own numbers on its
published example results (frozen), and evo_ape / evo_rpe on TUM files at another rate with gaps.

The kitti-odom-eval numbers below are what its own code (github.com/Huangying-Zhan/kitti-odom-eval
at 4b850b0, ``kitti_odometry.py``, MIT) printed, run once outside the project on the example
results as it ships them (``../shared/data/kitti_odom_eval_examples``; its bundled ground truth is
``../shared/data/kitti_odometry/poses`` byte for byte), unpatched, with numpy 2.4, for each
alignment mode::

    echo y | python eval_odom.py --result result/example_0 [--align scale|scale_7dof|7dof|6dof]
    echo y | python eval_odom.py --result result/example_1 [--align …]

It prints, per sequence, ``Translational error (%)``, ``Rotational error (deg/100m)``, ``ATE
(m)``, ``RPE (m)`` and ``RPE (deg)`` (means). ``example_0`` has 13 numbers a line and starts late
(frame 2 on 09, frame 4 on 10); ``example_1`` has 12 and every frame. Its modes are
``--align none --align-origin`` (no ``--align``: it always expresses both trajectories relative to
their first frame), ``scale``, ``scale_7dof``, ``sim3`` (its ``7dof``) and ``se3`` (``6dof``);
``--raw-rotations`` computes with the rotation blocks as written and general inverses, as it
does.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import SHARED
from mfg_lightning.evaluate_poses import main
from mfg_lightning.trajectory.pose_io import (
    read_kitti_poses,
    write_kitti_poses,
    write_kitti_times,
    write_tum_poses,
)

KITTI_POSES = SHARED / "data" / "kitti_odometry" / "poses"
EXAMPLES = SHARED / "data" / "kitti_odom_eval_examples"

#: (example, kitti-odom-eval --align, sequence) → (t_err %, r_err deg/100 m, ATE m, RPE m, RPE deg)
KITTI_ODOM_EVAL = {
    ("example_0", "none", "09"): (72.1091818572665, 0.24905618674613386, 349.64043511743375, 1.0223113061968447, 0.06338860665283719),  # noqa: E501
    ("example_0", "none", "10"): (82.0699713366625, 0.30458995194529725, 425.3822009779384, 0.7328702692628457, 0.06626406473726826),  # noqa: E501
    ("example_0", "scale", "09"): (2.866391190849176, 0.24905618674613386, 10.638550474032817, 0.34090923523612165, 0.06338860665283719),  # noqa: E501
    ("example_0", "scale", "10"): (3.90214616331609, 0.30458995194529725, 12.934527718274921, 0.04553298862166571, 0.06626406473726826),  # noqa: E501
    ("example_0", "scale_7dof", "09"): (2.884112511407124, 0.24905618674613386, 10.722576040736545, 0.3434130770692031, 0.06338860665283719),  # noqa: E501
    ("example_0", "scale_7dof", "10"): (3.297839536933301, 0.30458995194529725, 18.215186625767423, 0.047352563718565985, 0.06626406473726826),  # noqa: E501
    ("example_0", "7dof", "09"): (2.884112511407124, 0.2490561867460957, 8.38661922878606, 0.3434130770692033, 0.0633886066530713),  # noqa: E501
    ("example_0", "7dof", "10"): (3.2978395369332993, 0.30458995194529487, 6.630158107185036, 0.04735256371856569, 0.06626406473782222),  # noqa: E501
    ("example_0", "6dof", "09"): (72.10918185726652, 0.2490561867460957, 215.43533486317136, 1.022311306196845, 0.0633886066530713),  # noqa: E501
    ("example_0", "6dof", "10"): (82.06997133666252, 0.30458995194529487, 201.57921166337275, 0.7328702692628457, 0.06626406473782222),  # noqa: E501
    ("example_1", "none", "09"): (2.6068429403874434, 0.28770722198664894, 17.91905484308417, 0.055702041204243026, 0.03698807262537409),  # noqa: E501
    ("example_1", "none", "10"): (2.293174110927859, 0.36933467400631914, 9.035133416415603, 0.04655480689332105, 0.042595750678703116),  # noqa: E501
    ("example_1", "scale", "09"): (2.6664416549691072, 0.28770722198664894, 17.883228009523965, 0.056530963546099294, 0.03698807262537409),  # noqa: E501
    ("example_1", "scale", "10"): (2.2838984752610934, 0.36933467400631914, 9.032281136779389, 0.04654783634012801, 0.042595750678703116),  # noqa: E501
    ("example_1", "scale_7dof", "09"): (2.527535077266191, 0.28770722198664894, 18.346247605237735, 0.05423468934767214, 0.03698807262537409),  # noqa: E501
    ("example_1", "scale_7dof", "10"): (2.221192216697036, 0.36933467400631914, 9.557379922855178, 0.04669906904008017, 0.042595750678703116),  # noqa: E501
    ("example_1", "7dof", "09"): (2.5275350772661858, 0.2877072219866253, 10.72949951877264, 0.054234689347672595, 0.03698807262502938),  # noqa: E501
    ("example_1", "7dof", "10"): (2.221192216697038, 0.3693346740063282, 3.3562345945326624, 0.046699069040076854, 0.0425957506767865),  # noqa: E501
    ("example_1", "6dof", "09"): (2.606842940387442, 0.2877072219866253, 10.880278468457115, 0.055702041204242776, 0.03698807262502938),  # noqa: E501
    ("example_1", "6dof", "10"): (2.293174110927859, 0.3693346740063282, 3.7206682022460646, 0.046554806893318784, 0.0425957506767865),  # noqa: E501
}  # fmt: skip

#: kitti-odom-eval's --align → the options of mfg-eval-poses.
MODES = {
    "none": ["--align", "none", "--align-origin"],
    "scale": ["--align", "scale"],
    "scale_7dof": ["--align", "scale_7dof"],
    "7dof": ["--align", "sim3"],
    "6dof": ["--align", "se3"],
}


def _needs_shared() -> None:
    if not (KITTI_POSES.is_dir() and EXAMPLES.is_dir()):
        pytest.skip(f"{KITTI_POSES} or {EXAMPLES} not present")


def _eval(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    code = main([*argv, "--json"])
    out, err = capsys.readouterr()
    assert code == 0 and err == "", err
    return json.loads(out)


def _examples(capsys: pytest.CaptureFixture[str], *options: str) -> dict:
    _needs_shared()
    methods = ["--pred", f"a={EXAMPLES / 'example_0'}", "--pred", f"b={EXAMPLES / 'example_1'}"]
    return _eval(capsys, "--gt", str(KITTI_POSES), *methods, "--seqs", "09", "10", *options)


def _kitti_odom_eval_numbers(result: dict) -> tuple[float, ...]:
    """A sequence's numbers in kitti-odom-eval's order and units (RPE rotation in degrees)."""
    keys = ("drift_t_err", "drift_r_err", "ate_traj", "rpe_trans")
    return (*(result[k] for k in keys), math.degrees(result["rpe_rot"]))


@pytest.mark.parametrize("mode", list(MODES))
def test_kitti_odom_eval_examples_score_as_its_own_code(capsys, mode: str) -> None:
    payload = _examples(capsys, *MODES[mode], "--raw-rotations")
    for method, example in (("a", "example_0"), ("b", "example_1")):
        for seq in ("09", "10"):
            got = payload["methods"][method]["sequences"][seq]
            expected = KITTI_ODOM_EVAL[(example, mode, seq)]
            # Its own numbers to 1e-6 (the projected default below agrees to 1e-4): the same
            # arithmetic on the same floats, up to the order of float64 sums.
            assert _kitti_odom_eval_numbers(got) == pytest.approx(expected, rel=1e-6), (
                method,
                seq,
            )
    # What was matched: the late-starting 13-column files by their frame indices.
    matched = {s: payload["methods"]["a"]["sequences"][s] for s in ("09", "10")}
    assert [(m["num_poses"], m["poses_given"], m["gt_poses"]) for m in matched.values()] == [
        (1589, 1589, 1591),
        (1197, 1197, 1201),
    ]
    assert {m["matched_by"] for m in matched.values()} == {"frame"}


def test_projected_rotations_move_only_the_rotational_rpe(capsys) -> None:
    """Without --raw-rotations the rotations are projected onto SO(3) (evo's angles): every
    number but the small-angle rotational RPE stays within 1e-4 of kitti-odom-eval's; that one
    moves by < 2 % (the arccos of 6-digit rotation blocks), towards evo's value."""
    payload = _examples(capsys, "--align", "sim3")
    for method, example in (("a", "example_0"), ("b", "example_1")):
        for seq in ("09", "10"):
            got = _kitti_odom_eval_numbers(payload["methods"][method]["sequences"][seq])
            expected = KITTI_ODOM_EVAL[(example, "7dof", seq)]
            assert got[:4] == pytest.approx(expected[:4], rel=1e-4)
            assert got[4] == pytest.approx(expected[4], rel=2e-2)
            assert got[4] != pytest.approx(expected[4], rel=1e-4)


def test_the_examples_unaligned_are_evo_s_default(capsys) -> None:
    """Plain --align none compares the late start's poses as they are (evo_ape's default):
    example_1 starts at frame 0 like the ground truth, so it is kitti-odom-eval's as well."""
    payload = _examples(capsys, "--align", "none", "--raw-rotations")
    got = _kitti_odom_eval_numbers(payload["methods"]["b"]["sequences"]["09"])
    assert got == pytest.approx(KITTI_ODOM_EVAL[("example_1", "none", "09")], rel=1e-6)
    late = payload["methods"]["a"]["sequences"]["09"]
    assert late["ate_traj"] != pytest.approx(KITTI_ODOM_EVAL[("example_0", "none", "09")][2])


# ------------------------------------------------------------------------------------------------
# evo: TUM files at another rate and with gaps, associated by timestamp
# ------------------------------------------------------------------------------------------------


def _estimate(gt: np.ndarray, seed: int) -> np.ndarray:
    """A noisy, drifting estimate in another world frame and at 0.4 × the scale (monocular)."""
    rng = np.random.default_rng(seed)
    noise = np.tile(np.eye(4), (len(gt), 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 3e-3, (len(gt), 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, 0.1, (len(gt), 3)) + np.linspace(0, 4, len(gt))[:, None]
    est = gt @ noise
    R = Rotation.from_rotvec([0.2, -0.9, 0.1]).as_matrix()
    est[:, :3, :3] = R @ est[:, :3, :3]
    est[:, :3, 3] = 0.4 * est[:, :3, 3] @ R.T + np.array([3.0, -1.0, 7.0])
    return est


@pytest.fixture(scope="module")
def tum_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """KITTI 09's first 500 frames as ground truth at ~9.65 Hz (TUM, and KITTI + times.txt), an
    estimate at half the rate with jittered timestamps, two gaps and a 0.5 s clock offset, and
    one at twice the rate (poses between frames interpolated on the path)."""
    if not KITTI_POSES.is_dir():
        pytest.skip(f"{KITTI_POSES} not present")
    tmp = tmp_path_factory.mktemp("tum")
    gt = read_kitti_poses(KITTI_POSES / "09.txt")[:500]
    times = 1317384506.0 + 0.1036 * np.arange(500)
    write_tum_poses(tmp / "gt.tum", times, gt)
    write_kitti_poses(tmp / "gt.txt", gt)
    write_kitti_times(tmp / "times.txt", times)
    rng = np.random.default_rng(7)
    keep = np.r_[0:200:2, 260:400:2, 430:500:2]  # every second frame, two gaps
    est = _estimate(gt, 8)[keep]
    stamps = times[keep] + rng.uniform(-0.004, 0.004, keep.size) + 0.5
    write_tum_poses(tmp / "half.tum", stamps, est)
    # Twice the rate: the frames, and the midpoints between them 51.8 ms later (matched to
    # nothing: further than 0.01 s from every ground-truth time).
    both = _estimate(gt, 9)
    mid = both.copy()
    mid[:-1, :3, 3] = 0.5 * (both[:-1, :3, 3] + both[1:, :3, 3])
    fast = np.stack([both, mid], axis=1).reshape(-1, 4, 4)[:-1]
    fast_t = np.stack([times, times + 0.0518], axis=1).reshape(-1)[:-1]
    write_tum_poses(tmp / "double.tum", fast_t, fast)
    return {"gt": tmp / "gt.tum", "gt_kitti": tmp / "gt.txt", "times": tmp / "times.txt",
            "half": tmp / "half.tum", "double": tmp / "double.tum"}  # fmt: skip


def _evo(ref_path: Path, est_path: Path, max_diff: float, offset: float, **align: bool) -> dict:
    """evo_ape and evo_rpe (Δ = 1 frame) of the associated trajectories, as its commands run."""
    from evo import main_ape, main_rpe
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(ref_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff, offset_2=offset)
    out = {"num_poses": ref.num_poses}
    ape = main_ape.ape(copy.deepcopy(ref), copy.deepcopy(est),
                       metrics.PoseRelation.translation_part, **align)  # fmt: skip
    out.update(ate_traj=ape.stats["rmse"], ate_traj_mean=ape.stats["mean"],
               ate_traj_std=ape.stats["std"])  # fmt: skip
    for part, relation in (("trans", metrics.PoseRelation.translation_part),
                           ("rot", metrics.PoseRelation.rotation_angle_rad)):  # fmt: skip
        rpe = main_rpe.rpe(copy.deepcopy(ref), copy.deepcopy(est), relation, delta=1,
                           delta_unit=metrics.Unit.frames, **align)  # fmt: skip
        out[f"rpe_{part}"] = rpe.stats["mean"]
        out[f"rpe_{part}_std"] = rpe.stats["std"]
        out[f"rpe_{part}_rmse"] = rpe.stats["rmse"]
    return out


#: mfg-eval-poses options → evo_ape / evo_rpe options.
EVO_MODES = {
    "none": ([], {}),
    "origin": (["--align-origin"], {"align_origin": True}),
    "se3": (["--align", "se3"], {"align": True}),
    "sim3": (["--align", "sim3"], {"align": True, "correct_scale": True}),
}


@pytest.mark.parametrize("mode", list(EVO_MODES))
def test_a_tum_file_at_half_the_rate_with_gaps_scores_as_evo(tum_files, capsys, mode) -> None:
    ours, evo_align = EVO_MODES[mode]
    expected = _evo(tum_files["gt"], tum_files["half"], 0.01, -0.5, **evo_align)
    kitti_gt = ["--gt", str(tum_files["gt_kitti"]), "--gt-times", str(tum_files["times"])]
    for gt in (["--gt", str(tum_files["gt"])], kitti_gt):
        got = _eval(capsys, *gt, "--pred", str(tum_files["half"]), "--t-offset", "-0.5", *ours)
        assert got["num_poses"] == expected["num_poses"] == 100 + 70 + 35
        assert got["poses_given"] == 205 and got["gt_poses"] == 500
        for key, value in expected.items():
            # evo's angles come from scipy's rotation vectors, ours from the trace: 1e-7 rad.
            tol = {"abs": 1e-9} if "rot" in key else {"rel": 1e-9}
            assert got[key] == pytest.approx(value, **tol), (mode, key)
    # Half the rate: no five consecutive frames, so no snippet; drift over the segments whose
    # first and last frames are matched.
    assert got["num_snippets"] == 0 and got["ate"] is None
    assert got["num_segments"] > 0 and got["gt_times"] == str(tum_files["times"])


def test_a_tum_file_at_twice_the_rate_scores_as_evo(tum_files, capsys) -> None:
    expected = _evo(tum_files["gt"], tum_files["double"], 0.02, 0.0, align=True,
                    correct_scale=True)  # fmt: skip
    got = _eval(capsys, "--gt", str(tum_files["gt"]), "--pred", str(tum_files["double"]),
                "--align", "sim3", "--t-max-diff", "0.02")  # fmt: skip
    assert got["num_poses"] == expected["num_poses"] == 500 and got["poses_given"] == 999
    for key, value in expected.items():
        assert got[key] == pytest.approx(
            value, **({"abs": 1e-9} if "rot" in key else {"rel": 1e-9})
        )
    assert got["num_snippets"] == 496  # every ground-truth frame is matched


def test_matching_too_little_is_one_error_line(tum_files, capsys) -> None:
    argv = ["--gt", str(tum_files["gt"]), "--pred", str(tum_files["half"])]  # no --t-offset
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith(f"error: {tum_files['half']}:1: only 0 of its 205 poses match the 500 ")
    # A KITTI ground truth without times: the nominal 10 Hz clock, which these times are not.
    code = main(["--gt", str(tum_files["gt_kitti"]), "--pred", str(tum_files["half"])])
    _, err = capsys.readouterr()
    assert code == 2 and "ground-truth times: frame / 10 Hz" in err
