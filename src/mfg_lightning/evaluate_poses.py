"""Evaluate estimated trajectory files against ground truth: ``mfg-eval-poses --gt … --pred …``.

ATE over snippets, whole-trajectory ATE (evo's APE), RPE and KITTI drift, for one method or many,
with the pose matching, the alignments and the flags of evo and kitti-odom-eval
(``docs/evaluate_poses.md`` lists every flag and its equivalents; ``--help`` too)::

    mfg-eval-poses --gt poses/09.txt --pred 09_pred.txt [-as] [--json]
    mfg-eval-poses --gt poses/ --pred a=method_a/ --pred b=method_b/ --seqs 9 10 --out results/
    mfg-eval-poses --gt gt.tum --pred est.tum -r angle_deg --delta 10 --save_results est.zip

The inputs are read and matched by :mod:`mfg_lightning.trajectory.pose_inputs`, scored by
:mod:`mfg_lightning.metrics.pose_evaluation` and reported by
:mod:`mfg_lightning.analysis.pose_report`. Any problem with the input prints one line
``error: <file>:<line>: <reason>`` (or ``error: <reason>``) and exits with status 2 before
anything is written.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

from mfg_lightning.core.errors import report_user_error
from mfg_lightning.trajectory.association import (
    DEFAULT_MAX_TIME_DIFF,
    KITTI_FRAME_RATE,
    MatchOptions,
)
from mfg_lightning.trajectory.pairs import RpeOptions
from mfg_lightning.trajectory.pose_inputs import check_out, read_inputs

__all__ = ["main"]

# mfg_lightning.metrics.alignment.ALIGN_MODES, and kitti-odom-eval's names of them (tests check
# they agree), listed here so that --help and argument errors answer before torch is imported.
_ALIGN_CHOICES = ("none", "se3", "sim3", "scale", "scale_7dof", "sim3_scale")
_KITTI_ALIGN = {"6dof": "se3", "7dof": "sim3"}
# The modes fitted with Umeyama's method, which needs 3 poses.
_UMEYAMA = ("se3", "sim3", "scale_7dof", "sim3_scale")
_RELATIONS = ("trans_part", "rot_part", "angle_rad", "angle_deg", "full", "point_distance")
_PLOT_MODES = ("xz", "xy", "yx", "yz", "zx", "zy", "xyz")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mfg-eval-poses",
        description="ATE over snippets (Zhou et al. 2017), whole-trajectory ATE (evo's APE), RPE "
        "and KITTI odometry drift of estimated trajectory files against ground truth, for one "
        "method or many, with evo's and kitti-odom-eval's flags. KITTI files are matched to the "
        "ground truth by frame index, TUM files by timestamp. docs/evaluate_poses.md has it all.",
    )
    add = parser.add_argument
    add("--gt", required=True, help="ground-truth pose file, or a directory of <seq>.txt files")
    add("--pred", required=True, action="append", metavar="[NAME=]PATH",
        help="estimated poses of one method: a file, or a directory of <seq>.txt files; "
        "repeat for more methods (default name: the file or directory name)")  # fmt: skip
    add("--seqs", nargs="+", metavar="SEQ",
        help="sequences to evaluate, e.g. 09 10 or 9 10 (default: all of --gt)")  # fmt: skip
    add("--format", choices=("auto", "kitti", "tum"), default="auto",
        help="format of every file; auto: by column count, per file (default: auto)")  # fmt: skip
    align = parser.add_argument_group("alignment (evo's flags, kitti-odom-eval's names)")
    align.add_argument("--align", choices=(*_ALIGN_CHOICES, *_KITTI_ALIGN), default=None,
        help="before the whole-trajectory ATE, APE, RPE and drift: none (default), se3 / sim3 "
        "(Umeyama; evo -a / -as; kitti-odom-eval 6dof / 7dof, also accepted), scale, "
        "scale_7dof (kitti-odom-eval), sim3_scale (evo -s alone)")  # fmt: skip
    align.add_argument("-a", dest="evo_align", action="store_true",
        help="evo: SE(3) Umeyama alignment (with -s: Sim(3))")  # fmt: skip
    align.add_argument("-s", "--correct_scale", action="store_true",
        help="evo: correct the scale (Umeyama); alone: the scale only (sim3_scale)")  # fmt: skip
    align.add_argument("--n-to-align", "--n_to_align", type=int, default=None, metavar="N",
        help="fit the alignment on the first N matched poses of each sequence (default: all; "
        "evo's -1 means all)")  # fmt: skip
    align.add_argument("--align-origin", "--align_origin", action="store_true",
        help="first put the estimate's first pose on the ground truth's (evo --align_origin; "
        "kitti-odom-eval's default)")  # fmt: skip
    align.add_argument("--raw-rotations", action="store_true",
        help="rotation blocks as written, general matrix inverses (kitti-odom-eval's "
        "arithmetic) instead of projecting them onto SO(3) (evo's)")  # fmt: skip
    rpe = parser.add_argument_group("APE and RPE (evo's flags)")
    rpe.add_argument("-r", "--pose_relation", choices=_RELATIONS, default="trans_part",
        help="evo's pose relation of the APE and RPE statistics (default: trans_part)")  # fmt: skip
    rpe.add_argument("-d", "--delta", type=float, default=1,
        help="RPE gap, in --delta_unit (default: 1)")  # fmt: skip
    rpe.add_argument("-u", "--delta_unit", choices=("f", "m"), default="f",
        help="f: frames (matched poses), m: metres of path (default: f)")  # fmt: skip
    rpe.add_argument("--all_pairs", action="store_true",
        help="RPE over every pair Δ apart (overlapping) instead of consecutive pairs")  # fmt: skip
    rpe.add_argument("-t", "--delta_tol", type=float, default=0.1,
        help="with --all_pairs and -u m: relative tolerance on Δ (default: 0.1)")  # fmt: skip
    rpe.add_argument("--pairs_from_reference", action="store_true",
        help="with -u m: measure the path on the ground truth, not the estimate")  # fmt: skip
    match = parser.add_argument_group("matching TUM files by timestamp (evo's flags)")
    match.add_argument("--t-max-diff", "--t_max_diff", type=float, default=DEFAULT_MAX_TIME_DIFF,
        metavar="S", help="largest time difference of a match in seconds "
        f"(default: {DEFAULT_MAX_TIME_DIFF:g})")  # fmt: skip
    match.add_argument("--t-offset", "--t_offset", type=float, default=0.0, metavar="S",
        help="seconds added to the estimate's timestamps (default: 0)")  # fmt: skip
    match.add_argument("--gt-times", type=Path, metavar="PATH",
        help="a KITTI ground truth's times.txt (one sequence), or a directory of <seq>.txt or "
        "<seq>/times.txt (default: <root>/sequences/<seq>/times.txt beside "
        "<root>/poses/)")  # fmt: skip
    match.add_argument("--gt-rate", type=float, default=KITTI_FRAME_RATE, metavar="HZ",
        help="the clock of a KITTI ground truth without times: frame / HZ "
        "(default: 10)")  # fmt: skip
    out = parser.add_argument_group("output")
    out.add_argument("--out", type=Path, help="write tables and figures into this directory")
    out.add_argument("--json", action="store_true", help="print one JSON object")
    out.add_argument("--save_results", type=Path, metavar="ZIP",
        help="evo's result archives, for evo_res: <stem>_ape.zip and <stem>_rpe.zip (many "
        "files: <stem>_<method>_<seq>_ape.zip ...)")  # fmt: skip
    out.add_argument("--plot_mode", choices=_PLOT_MODES, default="xz",
        help="axes of the trajectory figures of --out (default: xz, KITTI's ground "
        "plane)")  # fmt: skip
    out.add_argument("--snippet-length", type=int, default=5,
        help="frames per ATE snippet (default: 5)")  # fmt: skip
    return parser


def _align_mode(args: argparse.Namespace) -> str:
    """One alignment mode from ``--align`` and evo's ``-a`` / ``-s``."""
    evo = ("sim3" if args.correct_scale else "se3") if args.evo_align else (
        "sim3_scale" if args.correct_scale else None)  # fmt: skip
    chosen = _KITTI_ALIGN.get(args.align, args.align)
    if chosen is not None and evo is not None and chosen != evo:
        raise ValueError(f"--align {args.align} and evo's -a/-s ({evo}) disagree; give one")
    mode = chosen or evo or "none"
    if args.align_origin and mode in ("se3", "sim3"):
        raise ValueError("--align_origin goes with --align none, scale or sim3_scale, as in evo "
                         "(an Umeyama alignment fits the first pose anyway)")  # fmt: skip
    return mode


def _options(args: argparse.Namespace) -> tuple[str, int | None, RpeOptions, MatchOptions]:
    """The alignment, ``n_to_align``, RPE and matching options, checked (``ValueError``) before
    torch is imported."""
    mode = _align_mode(args)
    n = None if args.n_to_align in (None, -1) else args.n_to_align
    if args.snippet_length < 2:
        raise ValueError("--snippet-length must be >= 2")
    if n is not None and n < (3 if mode in _UMEYAMA else 1):
        least = "3 (Umeyama's fit)" if mode in _UMEYAMA else "1"
        raise ValueError(f"--n_to_align must be >= {least} with --align {mode}")
    if not (args.t_max_diff >= 0 and math.isfinite(args.t_max_diff)):
        raise ValueError("--t_max_diff must be a finite number of seconds >= 0")
    if not math.isfinite(args.t_offset):
        raise ValueError("--t_offset must be a finite number of seconds")
    if not (args.gt_rate > 0 and math.isfinite(args.gt_rate)):
        raise ValueError("--gt-rate must be a finite frame rate > 0 (Hz)")
    rpe = RpeOptions(args.delta, args.delta_unit, args.all_pairs, args.delta_tol,
                     args.pairs_from_reference, args.pose_relation)  # fmt: skip
    fit = 3 if mode in _UMEYAMA else 1
    match = MatchOptions(args.t_max_diff, args.t_offset, args.gt_times, args.gt_rate,
                         max(2, rpe.frames + 1, fit))  # fmt: skip
    return mode, n, rpe, match


def _run(args: argparse.Namespace) -> int:
    mode, n, rpe, match = _options(args)
    seqs = [s for arg in args.seqs for s in arg.split(",") if s] if args.seqs else None
    inputs = read_inputs(args.gt, args.pred, seqs, args.format, match)
    for path, flag in ((args.out, "--out"), (args.save_results, "--save_results")):
        if path is not None:
            check_out(path, inputs, flag)
    # torch and the metrics are imported only now: --help and input errors answer at once
    # instead of after the seconds these imports take.
    from mfg_lightning.analysis import pose_report as report
    from mfg_lightning.core.atomic import atomic_write_bytes

    options = report.EvalOptions(mode, n, args.align_origin, args.raw_rotations,
                                 args.snippet_length, rpe, match, args.plot_mode)  # fmt: skip
    results = report.evaluate_inputs(inputs, options)
    payload = report.payload(inputs, results, options, str(args.gt), [str(p) for p in args.pred])
    tables = report.tables(inputs, results, options)
    archives = report.archives(inputs, results, options, args.save_results) if (
        args.save_results) else {}  # fmt: skip
    if args.out is not None:
        report.write_out(args.out, tables, payload, report.figures(inputs, results, options))
    for path, data in archives.items():
        atomic_write_bytes(path, data)
    if args.json:
        print(json.dumps(payload, indent=2))
    elif inputs.single:
        (name,) = inputs.matches
        match_ = next(iter(inputs.matches[name].values()))
        title = report.single_title(match_, options, str(args.gt), str(args.pred[0]))
        report.print_single(payload, title, options)
    else:
        print("\n".join(t.markdown() for t in tables.values()), end="")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 bad arguments or input files)."""
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, message already printed)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        return _run(args)
    except Exception as exc:
        # Input errors (PoseFileError, InputError, bad option values) are one line, as every
        # entry point's (mfg_lightning.core.errors); a bug keeps its traceback.
        return report_user_error(exc)


if __name__ == "__main__":
    sys.exit(main())
