"""Evaluate an estimated trajectory file against ground truth: ATE, RPE and KITTI drift.

Usage::

    mfg-eval-poses --gt poses/09.txt --pred 09_pred.txt [--format auto|kitti|tum] [--json]
                   [--delta 1] [--snippet-length 5]
    python -m mfg_lightning.evaluate_poses ...

Both files hold camera-to-world poses (KITTI: 12 numbers per line; TUM: ``timestamp tx ty tz qx
qy qz qw``; see :mod:`mfg_lightning.pose_io`). Reported (``../shared/docs/protocols.md``):

* ATE over snippets (Zhou et al. 2017; Table 1): all overlapping snippets of ``--snippet-length``
  frames, ground truth and estimate each re-expressed relative to the snippet's first frame,
  translation and scale aligned; mean ± population std of ``sqrt(Σ‖·‖²)/L``, and the mean
  conventional RMSE;
* RPE (Sturm et al. 2012; Table 2) with a gap of ``--delta`` frames: translation (pose units) and
  rotation (radians), mean, std and RMSE;
* KITTI odometry drift (Geiger et al. 2012): ``t_err`` in %, ``r_err`` in deg/100 m; undefined
  (null) for paths shorter than 100 m. RPE and drift use the poses as they are (no scale
  alignment), so monocular estimates must be in metres for them to mean anything.

Matching poses: the i-th pose of one file is compared with the i-th pose of the other; the files
must have the same number of poses. When both are TUM files their timestamps must also agree pose
by pose (to 1 µs); no association by nearest timestamp and no interpolation is done, so evaluate
estimates written for exactly the ground truth's frames.

Output: a table, or with ``--json`` one JSON object (NaN written as null). Any problem with the
input files prints one line ``error: <file>:<line>: <reason>`` to stderr and exits with status 2
before anything is written to stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence

import numpy as np

from mfg_lightning.pose_io import PoseFile, PoseFileError, read_poses

__all__ = ["evaluate_trajectory", "main", "match_pose_files"]

# TUM files are written with microsecond timestamps (or coarser).
_TIMESTAMP_TOLERANCE = 1e-6

UNITS: dict[str, str] = {
    "ate": "m",
    "ate_std": "m",
    "ate_rmse": "m",
    "rpe_trans": "m",
    "rpe_trans_std": "m",
    "rpe_trans_rmse": "m",
    "rpe_rot": "rad",
    "rpe_rot_std": "rad",
    "rpe_rot_rmse": "rad",
    "kitti_t_err": "%",
    "kitti_r_err": "deg/100m",
}


def match_pose_files(gt: PoseFile, pred: PoseFile) -> None:
    """Check that two pose files describe the same frames, pose by pose.

    Same number of poses; when both carry timestamps (TUM), equal timestamps (to 1 µs) in the
    same order.

    Raises:
        PoseFileError: naming the shorter file at the line where its next pose is missing, or the
            estimate's line whose timestamp differs from the ground truth's.
    """
    if len(gt) != len(pred):
        short, long = (gt, pred) if len(gt) < len(pred) else (pred, gt)
        raise PoseFileError(
            short.path,
            int(short.lines[-1]) + 1,
            f"file ends after {len(short)} poses but {long.path} has {len(long)}",
        )
    if gt.timestamps is not None and pred.timestamps is not None:
        differs = np.abs(gt.timestamps - pred.timestamps) > _TIMESTAMP_TOLERANCE
        if differs.any():
            i = int(np.argmax(differs))
            raise PoseFileError(
                pred.path,
                int(pred.lines[i]),
                f"timestamp {float(pred.timestamps[i])!r} differs from the ground truth's "
                f"{float(gt.timestamps[i])!r} ({gt.path}:{int(gt.lines[i])}); pose {i + 1} of both "
                "files must be the same frame",
            )


def evaluate_trajectory(
    gt: np.ndarray, pred: np.ndarray, delta: int = 1, snippet_length: int = 5
) -> dict[str, float | int | None]:
    """ATE over snippets, RPE and KITTI drift of one estimated trajectory.

    Args:
        gt: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), in frame order.
        pred: ``(N, 4, 4)`` estimated camera-to-world poses, any world frame, same frames.
        delta: RPE frame gap.
        snippet_length: frames per ATE snippet.

    Returns:
        Flat dict: ``ate``, ``ate_std``, ``ate_rmse``, ``rpe_trans``, ``rpe_trans_std``,
        ``rpe_trans_rmse``, ``rpe_rot``, ``rpe_rot_std``, ``rpe_rot_rmse``, ``kitti_t_err``,
        ``kitti_r_err`` (units in :data:`UNITS`; None where undefined, e.g. fewer frames than a
        snippet or a path shorter than 100 m), plus the counts ``num_poses``, ``num_snippets``,
        ``num_pairs``, ``num_segments``.
    """
    # torch and the metrics (torchmetrics) are imported here, not at the top, so that --help and
    # input errors answer at once instead of after the 2–3 s these imports take.
    import torch

    from mfg_lightning.metrics import (
        kitti_drift_from_segments,
        kitti_segment_errors,
        relative_pose_error,
        snippet_ate,
    )
    from mfg_lightning.trajectories import evaluation_poses, snippets_from_poses

    Q = evaluation_poses(torch.from_numpy(np.asarray(gt, dtype=np.float64)))
    P = evaluation_poses(torch.from_numpy(np.asarray(pred, dtype=np.float64)))
    if P.shape != Q.shape or P.dim() != 3:
        raise ValueError(f"gt and pred must be (N, 4, 4) alike, got {gt.shape} and {pred.shape}")
    pred_snippets = snippets_from_poses(P, snippet_length)
    ate = snippet_ate(pred_snippets, snippets_from_poses(Q, snippet_length))
    rpe = relative_pose_error(P, Q, delta)
    t_err, r_err, _ = kitti_segment_errors(P, Q)
    drift = kitti_drift_from_segments(t_err, r_err)

    def value(x: torch.Tensor) -> float | None:
        f = float(x)
        return f if math.isfinite(f) else None

    out: dict[str, float | int | None] = {
        "num_poses": int(P.shape[0]),
        "num_snippets": int(pred_snippets.shape[0]),
        "num_pairs": max(int(P.shape[0]) - delta, 0),
        "num_segments": int(t_err.numel()),
    }
    out.update({key: value(v) for key, v in ate.items()})
    out.update({f"rpe_{key}": value(v) for key, v in rpe.items()})
    out.update({f"kitti_{key}": value(v) for key, v in drift.items()})
    return out


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mfg-eval-poses",
        description="ATE over snippets (Zhou et al. 2017), RPE (Sturm et al. 2012) and KITTI "
        "odometry drift of an estimated trajectory file against ground truth.",
    )
    parser.add_argument("--gt", required=True, help="ground-truth pose file (KITTI or TUM)")
    parser.add_argument("--pred", required=True, help="estimated pose file (KITTI or TUM)")
    parser.add_argument(
        "--format",
        choices=("auto", "kitti", "tum"),
        default="auto",
        help="format of both files; auto: by column count, per file (default: auto)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--delta", type=int, default=1, help="RPE frame gap (default: 1)")
    parser.add_argument(
        "--snippet-length", type=int, default=5, help="frames per ATE snippet (default: 5)"
    )
    return parser


def _print_table(result: dict[str, float | int | None], args: argparse.Namespace) -> None:
    from rich.console import Console
    from rich.table import Table

    def fmt(key: str) -> str:
        v = result[key]
        return "n/a" if v is None else f"{v:.5g}"

    table = Table(
        title=f"{args.pred} vs {args.gt} ({result['num_poses']} poses)",
        caption="std: population standard deviation; ATE RMSE: mean per-snippet RMSE",
    )
    for column in ("metric", "mean", "std", "RMSE", "unit"):
        table.add_column(column, justify="left" if column in ("metric", "unit") else "right")
    table.add_row(
        f"ATE, {args.snippet_length}-frame snippets ({result['num_snippets']})",
        fmt("ate"),
        fmt("ate_std"),
        fmt("ate_rmse"),
        UNITS["ate"],
    )
    for part, label in (("trans", "translation"), ("rot", "rotation")):
        table.add_row(
            f"RPE {label}, Δ = {args.delta} ({result['num_pairs']} pairs)",
            fmt(f"rpe_{part}"),
            fmt(f"rpe_{part}_std"),
            fmt(f"rpe_{part}_rmse"),
            UNITS[f"rpe_{part}"],
        )
    segments = result["num_segments"]
    table.add_row(f"KITTI t_err ({segments} segments)", fmt("kitti_t_err"), "", "", "%")
    table.add_row(f"KITTI r_err ({segments} segments)", fmt("kitti_r_err"), "", "", "deg/100m")
    Console(width=max(100, Console().width)).print(table)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 bad arguments or input files)."""
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, message already printed)
        return exc.code if isinstance(exc.code, int) else 2
    if args.delta < 1:
        parser.print_usage(sys.stderr)
        print("error: --delta must be >= 1", file=sys.stderr)
        return 2
    if args.snippet_length < 2:
        parser.print_usage(sys.stderr)
        print("error: --snippet-length must be >= 2", file=sys.stderr)
        return 2
    try:
        gt = read_poses(args.gt, args.format)
        pred = read_poses(args.pred, args.format)
        match_pose_files(gt, pred)
    except PoseFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = evaluate_trajectory(gt.poses, pred.poses, args.delta, args.snippet_length)
    if args.json:
        payload = {
            "gt": str(args.gt),
            "pred": str(args.pred),
            "gt_format": gt.format,
            "pred_format": pred.format,
            "snippet_length": args.snippet_length,
            "delta": args.delta,
            **result,
            "units": UNITS,
        }
        print(json.dumps(payload, indent=2))
    else:
        _print_table(result, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
