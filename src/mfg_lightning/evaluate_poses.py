"""Evaluate estimated trajectory files against ground truth: ATE, RPE and KITTI drift, for one
method or many, with the pose matching and the alignments of evo and kitti-odom-eval.

Usage (``--help`` lists every option)::

    mfg-eval-poses --gt poses/09.txt --pred 09_pred.txt [--align sim3] [--json]
    mfg-eval-poses --gt poses/ --pred a=method_a/ --pred b=method_b/ [--seqs 09 10] --out results/
    python -m mfg_lightning.evaluate_poses ...

Inputs. ``--gt`` is a pose file or a directory of ``<seq>.txt`` files (KITTI's ``poses/``).
``--pred`` is repeated once per method, ``name=<file|dir>`` (or just ``<file|dir>``, named after
it): a directory holds ``<seq>.txt`` per sequence, a file is one sequence. Every file is KITTI
(12 numbers a line, or 13 with the frame index first) or TUM (``timestamp tx ty tz qx qy qz qw``),
camera-to-world (:mod:`mfg_lightning.trajectory.pose_io`); each method may use its own. The
sequences evaluated are those of the ground truth, or ``--seqs``; a method without one of them is
an error, unless ``--seqs`` leaves it out.

Matching poses (:mod:`mfg_lightning.trajectory.association`). A KITTI estimate is matched by
frame index (kitti-odom-eval): a 12-number file's k-th pose is frame k, a 13-number file names its
frames, so it may start late, end early and have holes. A TUM estimate is matched by timestamp as
``evo`` associates it: nearest in time within ``--t-max-diff`` seconds (default 0.01) after adding
``--t-offset`` to its timestamps; the ground truth's timestamps are its own (TUM), its
``times.txt`` (``--gt-times FILE|DIR``, else KITTI's ``<root>/sequences/<seq>/times.txt`` beside
``<root>/poses/``), or else ``frame / --gt-rate`` (10 Hz). Every metric is then computed on the
matched poses; what was matched is reported per sequence (``poses_used`` of ``poses_given``). A file
with fewer matched poses than the metrics need (2, Δ + 1, and 3 for an Umeyama fit) is an error.

Reported per sequence and overall (``../shared/docs/protocols.md``):

* ATE over snippets (Zhou et al. 2017; Table 1): all overlapping snippets of ``--snippet-length``
  consecutive ground-truth frames that are all matched, ground truth and estimate each
  re-expressed relative to the snippet's first frame, translation and scale aligned; mean ±
  population std of ``sqrt(Σ‖·‖²)/L``, and the mean conventional RMSE (each snippet aligns
  itself: ``--align`` does not change it);
* whole-trajectory ATE (``ate_traj``; ``evo_ape``, kitti-odom-eval): the RMSE of the per-pose
  position errors after ``--align`` (fitted on the first ``--n-to-align`` matched poses), with
  their mean and std and the fitted scale (:mod:`mfg_lightning.metrics.ate_traj`);
* RPE (Sturm et al. 2012; Table 2) over pairs of matched poses ``--delta`` apart (``evo_rpe
  --delta Δ --delta_unit f`` on the associated poses; kitti-odom-eval's ``compute_RPE`` for
  Δ = 1): translation (pose units) and rotation (radians), mean, std and RMSE;
* KITTI odometry drift (Geiger et al. 2012): ``t_err`` in %, ``r_err`` in deg/100 m, over the
  segments of the ground truth's path whose first and last frames are matched (kitti-odom-eval's
  rule); undefined (null) without one (a path shorter than 100 m).

RPE and drift are computed on the aligned estimate. The default ``--align none`` uses the poses
as they are (evo's default), so a monocular estimate must then be in metres for them to mean
anything; ``--align-origin`` first puts the estimate's first pose on the ground truth's (evo's
``--align_origin``; kitti-odom-eval expresses both relative to their first frame, so its results
without ``--align`` are ``--align none --align-origin``; its ``6dof`` and ``7dof`` are ``se3`` and
``sim3``). ``--raw-rotations`` keeps the files' rotation blocks as written and inverts with general
matrix inverses, kitti-odom-eval's arithmetic; by default they are projected onto SO(3) first (as
evo's angles are), which moves the mean rotational RPE of 6-digit KITTI files by ~1 % and every
other number by less than 1e-5. "Overall" pools the snippets, poses, pairs and segments of all
sequences (each sequence aligned on its own), as the devkit pools its segments.

Output. With one ``--pred <file>`` (no name) against a ``--gt`` file: a table, or with ``--json``
one flat JSON object, as before. Otherwise one Markdown table per sequence, one overall (rows:
methods) and one of the poses matched, or with ``--json`` one object ``{"methods": {name:
{"sequences": {seq: {...}}, "overall": {...}}}}``; NaN is written as null. ``--out DIR`` also
writes there ``table_<seq>.{md,csv,tex}``, ``table_overall.{md,csv,tex}``,
``table_matches.{md,csv,tex}``, ``results.json``, and the figures ``trajectory_<seq>.png`` (x–z,
every method over the ground truth), ``drift_<seq>.png`` (drift per segment length),
``error_<seq>.png`` (position error along the trajectory) and ``drift_overall.png``. Everything is
computed before the first file is written, and nothing is ever written into an input directory.

Errors. Any problem with the input (a missing sequence, a frame the ground truth does not have,
too few matched poses, a line that is not a pose, a non-finite number) prints one line
``error: <file>:<line>: <reason>`` to stderr and exits with status 2 before anything is written to
stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mfg_lightning.analysis.result_tables import pose_results_table
from mfg_lightning.core.errors import report_user_error
from mfg_lightning.core.tables import Column, Table, finite_or_none
from mfg_lightning.trajectory.association import (
    DEFAULT_MAX_TIME_DIFF,
    KITTI_FRAME_RATE,
    MatchOptions,
    PoseMatch,
    SequenceMatcher,
)
from mfg_lightning.trajectory.pose_io import PoseFile, PoseFileError, read_poses

if TYPE_CHECKING:
    from torch import Tensor

    from mfg_lightning.metrics import Alignment

__all__ = [
    "SequenceErrors",
    "evaluate_trajectory",
    "main",
    "matches_table",
    "sequence_errors",
    "summarise",
]

# The modes of mfg_lightning.metrics.alignment.ALIGN_MODES (tests check they agree), listed here so
# that --help and argument errors answer before torch is imported.
_ALIGN_CHOICES = ("none", "se3", "sim3", "scale", "scale_7dof")
# The modes fitted with Umeyama's method, which needs 3 poses.
_UMEYAMA = ("se3", "sim3", "scale_7dof")

UNITS: dict[str, str] = {
    "ate": "m",
    "ate_std": "m",
    "ate_rmse": "m",
    "ate_traj": "m",
    "ate_traj_mean": "m",
    "ate_traj_std": "m",
    "ate_traj_scale": "1",
    "rpe_trans": "m",
    "rpe_trans_std": "m",
    "rpe_trans_rmse": "m",
    "rpe_rot": "rad",
    "rpe_rot_std": "rad",
    "rpe_rot_rmse": "rad",
    "drift_t_err": "%",
    "drift_r_err": "deg/100m",
}


class InputError(ValueError):
    """A problem with the command's arguments that is not inside one file (one line)."""


# ------------------------------------------------------------------------------------------------
# Metrics of one sequence, and pooled over sequences
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SequenceErrors:
    """The per-element errors of one method on one sequence, and its alignment.

    Attributes:
        snippet_ate, snippet_ate_rmse: ``(S,)`` the ATE of every snippet of matched consecutive
            frames (:func:`mfg_lightning.metrics.snippet_ate_errors`, m).
        rpe_trans, rpe_rot: ``(M − Δ,)`` RPE per pair of matched poses (m, rad), after alignment.
        drift_t, drift_r, drift_length: ``(G,)`` KITTI segment errors (per metre; rad per metre)
            and lengths (m), after alignment.
        traj: ``(M,)`` per-pose position errors after alignment (m).
        aligned: the alignment (aligned matched trajectories and fitted transform).
        frames: ``(M,)`` the ground-truth row of every matched pose.
        reference: ``(N, 4, 4)`` the whole ground truth (float64).
    """

    snippet_ate: Tensor
    snippet_ate_rmse: Tensor
    rpe_trans: Tensor
    rpe_rot: Tensor
    drift_t: Tensor
    drift_r: Tensor
    drift_length: Tensor
    traj: Tensor
    aligned: Alignment
    frames: Tensor
    reference: Tensor

    @property
    def num_poses(self) -> int:
        return int(self.traj.numel())


def sequence_errors(
    gt: np.ndarray,
    pred: np.ndarray,
    delta: int = 1,
    snippet_length: int = 5,
    align: str = "none",
    n_to_align: int | None = None,
    *,
    frames: np.ndarray | None = None,
    align_origin: bool = False,
    project: bool = True,
) -> SequenceErrors:
    """Every per-element error of one estimated trajectory (see the module docstring).

    Args:
        gt: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), every frame in order.
        pred: ``(M, 4, 4)`` estimated camera-to-world poses of the matched frames, any world
            frame, in order.
        delta: RPE gap in matched poses.
        snippet_length: frames per ATE snippet.
        align, n_to_align: alignment for the whole-trajectory ATE, RPE and drift.
        frames: ``(M,)`` the ground-truth row of each estimated pose (non-decreasing); None:
            ``M == N`` and pose k is frame k.
        align_origin: put the estimate's first pose on the ground truth's first (evo's
            ``--align_origin``) before aligning.
        project: rotation blocks onto SO(3) first (default); ``False``: as written, with general
            inverses (kitti-odom-eval's arithmetic) for the ATE, RPE and drift.
    """
    # torch and the metrics (torchmetrics) are imported here, not at the top, so that --help and
    # input errors answer at once instead of after the 2–3 s these imports take.
    import torch

    from mfg_lightning.metrics import (
        align_trajectory,
        ate_traj_errors,
        kitti_segment_errors,
        relative_pose_errors,
        snippet_ate_errors,
    )
    from mfg_lightning.trajectory.trajectories import (
        consecutive_windows,
        evaluation_poses,
        snippets_from_poses,
    )

    gt_t = torch.from_numpy(np.asarray(gt, dtype=np.float64))
    pred_t = torch.from_numpy(np.asarray(pred, dtype=np.float64))
    if frames is None:
        if pred_t.shape != gt_t.shape:
            raise ValueError(
                f"gt and pred must be (N, 4, 4) alike, got {gt.shape} and {pred.shape}"
            )
        rows = torch.arange(gt_t.shape[0])
    else:
        rows = torch.from_numpy(np.asarray(frames, dtype=np.int64))
    if pred_t.dim() != 3 or tuple(pred_t.shape[1:]) != (4, 4) or rows.shape != pred_t.shape[:1]:
        raise ValueError(f"pred must be (M, 4, 4) with M frames, got {tuple(pred_t.shape)}")
    Q_all = evaluation_poses(gt_t, project)
    aligned = align_trajectory(
        pred_t, Q_all[rows], align, n_to_align, align_origin=align_origin, project=project
    )
    rpe_trans, rpe_rot = relative_pose_errors(aligned.pred, aligned.target, delta, project)
    drift_t, drift_r, drift_length = kitti_segment_errors(
        aligned.pred, aligned.target, frames=rows, reference=Q_all, project=project
    )
    # The snippet ATE is not kitti-odom-eval's: its snippets always use projected rotations.
    windows = consecutive_windows(rows, snippet_length)
    P = evaluation_poses(pred_t)
    Q = Q_all[rows] if project else evaluation_poses(gt_t)[rows]
    ate, ate_rmse = snippet_ate_errors(
        snippets_from_poses(P, snippet_length)[windows],
        snippets_from_poses(Q, snippet_length)[windows],
    )
    return SequenceErrors(
        snippet_ate=ate,
        snippet_ate_rmse=ate_rmse,
        rpe_trans=rpe_trans,
        rpe_rot=rpe_rot,
        drift_t=drift_t,
        drift_r=drift_r,
        drift_length=drift_length,
        traj=ate_traj_errors(aligned),
        aligned=aligned,
        frames=rows,
        reference=Q_all,
    )


def summarise(errors: Sequence[SequenceErrors]) -> dict[str, float | int | None]:
    """The metrics of one sequence, or pooled over several (elements of all sequences together).

    Returns:
        Flat dict: ``ate``, ``ate_std``, ``ate_rmse``, ``ate_traj``, ``ate_traj_mean``,
        ``ate_traj_std``, ``ate_traj_scale`` (of one sequence; None pooled), ``rpe_trans``,
        ``rpe_trans_std``, ``rpe_trans_rmse``, ``rpe_rot``, ``rpe_rot_std``, ``rpe_rot_rmse``,
        ``drift_t_err``, ``drift_r_err`` (units in :data:`UNITS`; None where undefined, e.g.
        fewer frames than a snippet or a path shorter than 100 m), plus the counts
        ``num_poses``, ``num_snippets``, ``num_pairs``, ``num_segments``.
    """
    import torch

    from mfg_lightning.metrics import kitti_drift_from_segments, snippet_ate_from_errors, summary

    def cat(name: str) -> torch.Tensor:
        return torch.cat([getattr(e, name) for e in errors])

    ate = snippet_ate_from_errors(cat("snippet_ate"), cat("snippet_ate_rmse"))
    traj = summary(cat("traj"))
    trans, rot = summary(cat("rpe_trans")), summary(cat("rpe_rot"))
    drift = kitti_drift_from_segments(cat("drift_t"), cat("drift_r"))
    out: dict[str, float | int | None] = {
        "num_poses": sum(e.num_poses for e in errors),
        "num_snippets": sum(int(e.snippet_ate.numel()) for e in errors),
        "num_pairs": sum(int(e.rpe_trans.numel()) for e in errors),
        "num_segments": sum(int(e.drift_t.numel()) for e in errors),
    }
    out.update({key: finite_or_none(v) for key, v in ate.items()})
    out["ate_traj"] = finite_or_none(traj["rmse"])
    out["ate_traj_mean"] = finite_or_none(traj["mean"])
    out["ate_traj_std"] = finite_or_none(traj["std"])
    out["ate_traj_scale"] = finite_or_none(errors[0].aligned.scale) if len(errors) == 1 else None
    for part, stats in (("trans", trans), ("rot", rot)):
        out[f"rpe_{part}"] = finite_or_none(stats["mean"])
        out[f"rpe_{part}_std"] = finite_or_none(stats["std"])
        out[f"rpe_{part}_rmse"] = finite_or_none(stats["rmse"])
    out.update({f"drift_{key}": finite_or_none(v) for key, v in drift.items()})
    return out


def evaluate_trajectory(
    gt: np.ndarray, pred: np.ndarray, **options: Any
) -> dict[str, float | int | None]:
    """ATE over snippets, whole-trajectory ATE, RPE and KITTI drift of one estimated trajectory.

    Args:
        gt: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), every frame in order.
        pred: ``(M, 4, 4)`` estimated camera-to-world poses, any world frame, of the frames
            ``options["frames"]`` (default: the same N frames).
        options: ``delta``, ``snippet_length``, ``align``, ``n_to_align``, ``frames``,
            ``align_origin``, ``project`` as :func:`sequence_errors` takes them.

    Returns:
        The flat dict of :func:`summarise`.
    """
    return summarise([sequence_errors(gt, pred, **options)])


# ------------------------------------------------------------------------------------------------
# Inputs: methods, sequences, files, matches
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Inputs:
    """The pose files to evaluate, read, matched and checked.

    Attributes:
        gt: sequence → ground-truth file, in evaluation order.
        methods: method name → sequence → its pose file (the same sequences as ``gt``).
        matches: method name → sequence → its poses matched to the ground truth's.
        sources: method name → the ``--pred`` path it came from.
        single: one unnamed ``--pred <file>`` against a ``--gt <file>`` (the flat output).
        directories: the input directories (never written into).
    """

    gt: dict[str, PoseFile]
    methods: dict[str, dict[str, PoseFile]]
    matches: dict[str, dict[str, PoseMatch]]
    sources: dict[str, Path]
    single: bool
    directories: list[Path]


def parse_method(spec: str) -> tuple[str | None, Path]:
    """``name=<path>`` → ``(name, path)``; a bare ``<path>`` → ``(None, path)``.

    A ``name`` is what precedes the first ``=``, when that is non-empty and holds no path
    separator (so a path that contains ``=`` can still be given as ``./a=b.txt``).
    """
    name, sep, rest = spec.partition("=")
    if sep and name and "/" not in name and "\\" not in name and rest:
        return name, Path(rest)
    return None, Path(spec)


def _sequence_names(gt: Path, seqs: Sequence[str] | None) -> dict[str, Path]:
    """Sequence → ground-truth file: the ``<seq>.txt`` of a directory, or the one file."""
    if gt.is_dir():
        if seqs:
            return {s: gt / f"{s}.txt" for s in seqs}
        found = {p.stem: p for p in sorted(gt.glob("*.txt")) if p.is_file()}
        if not found:
            raise InputError(f"{gt}: the ground-truth directory holds no <seq>.txt pose files")
        return found
    if seqs and list(seqs) != [gt.stem]:
        raise InputError(
            f"--seqs {' '.join(seqs)}: --gt {gt} is one file (sequence {gt.stem}); give a "
            "directory of <seq>.txt files to choose sequences"
        )
    return {gt.stem: gt}


def _method_files(name: str, path: Path, sequences: dict[str, Path], gt: Path) -> dict[str, Path]:
    """Sequence → the method's file, for every evaluated sequence."""
    if path.is_dir():
        files = {}
        for seq, gt_file in sequences.items():
            candidate = path / f"{seq}.txt"
            if not candidate.is_file():
                raise PoseFileError(
                    candidate,
                    1,
                    f"method {name!r} has no poses for sequence {seq} (ground truth {gt_file}); "
                    "leave the sequence out with --seqs",
                )
            files[seq] = candidate
        return files
    if len(sequences) != 1:
        raise InputError(
            f"--pred {name}={path}: a file holds one sequence but {len(sequences)} are evaluated "
            f"({', '.join(sequences)} of {gt}); give a directory of <seq>.txt files"
        )
    return {next(iter(sequences)): path}


def read_inputs(
    gt: str | Path,
    preds: Sequence[str],
    seqs: Sequence[str] | None = None,
    fmt: str = "auto",
    options: MatchOptions | None = None,
) -> Inputs:
    """Read, match and check every pose file of an evaluation (see the module docstring).

    Raises:
        PoseFileError: a file that cannot be read as a pose file, a missing sequence of a method
            (naming the file it looked for), a frame the ground truth does not have, too few
            matched poses.
        InputError: arguments that do not fit together (repeated names, a file for many
            sequences).
        ValueError: ``--gt-times`` without the times of a sequence.
    """
    gt = Path(gt)
    options = options or MatchOptions()
    sequences = _sequence_names(gt, seqs)
    named = [parse_method(spec) for spec in preds]
    sources: dict[str, Path] = {}
    for name, path in named:
        name = name or (path.stem if path.suffix else path.name) or str(path)
        if name in sources:
            raise InputError(f"--pred: two methods are named {name!r}; name them with name=<path>")
        sources[name] = path
    gt_files = {seq: read_poses(path, fmt) for seq, path in sequences.items()}
    files = {name: _method_files(name, path, sequences, gt) for name, path in sources.items()}
    single_seq = len(sequences) == 1
    matchers = {s: SequenceMatcher(s, f, options, single_seq) for s, f in gt_files.items()}
    methods: dict[str, dict[str, PoseFile]] = {}
    matches: dict[str, dict[str, PoseMatch]] = {}
    for name, per_seq in files.items():
        methods[name], matches[name] = {}, {}
        for seq, path in per_seq.items():
            methods[name][seq] = read_poses(path, fmt)
            matches[name][seq] = matchers[seq](methods[name][seq])
    single = (
        len(named) == 1 and named[0][0] is None and not gt.is_dir() and not named[0][1].is_dir()
    )
    directories = [p for p in [gt, *sources.values()] if p.is_dir()]
    return Inputs(gt_files, methods, matches, sources, single, directories)


# ------------------------------------------------------------------------------------------------
# Output
# ------------------------------------------------------------------------------------------------


def matches_table(inputs: Inputs) -> Table:
    """One row per method and sequence: how its poses were matched, how many were used."""
    table = Table(
        [Column("method"), Column("sequence"), Column("matched by"), Column("poses used"),
         Column("poses given"), Column("ground-truth poses"), Column("max |Δt|", "s", 4)],
        title="Poses matched to the ground truth",
    )  # fmt: skip
    for name, per in inputs.matches.items():
        for seq, m in per.items():
            table.add_row([name, seq, m.by, m.num_matched, m.num_pred, m.num_gt, m.max_time_diff])
    return table


def _alignment_words(args: argparse.Namespace) -> str:
    """The alignment of the tables' titles, in words."""
    words = "not aligned" if args.align == "none" else f"{args.align} alignment"
    if args.n_to_align is not None and args.align != "none":
        words += f" on the first {args.n_to_align} poses"
    if args.align_origin:
        words += ", first poses made equal (--align-origin)"
    if args.raw_rotations:
        words += ", rotations as written (--raw-rotations)"
    return words


def _print_table(
    result: dict[str, float | int | None], args: argparse.Namespace, match: PoseMatch
) -> None:
    from rich.console import Console
    from rich.table import Table as RichTable

    from mfg_lightning.core.tables import fmt

    def cell(key: str, digits: int = 5) -> str:
        return fmt(result[key], digits) if result[key] is not None else "n/a"

    used = f"{match.num_matched} of {match.num_pred} poses matched to {match.num_gt}"
    table = RichTable(
        title=f"{args.pred[0]} vs {args.gt} ({used} {match.describe(_match_options(args))})",
        caption="std: population standard deviation; ATE RMSE: mean per-snippet RMSE",
    )
    for column in ("metric", "mean", "std", "RMSE", "unit"):
        table.add_column(column, justify="left" if column in ("metric", "unit") else "right")
    table.add_row(
        f"ATE, {args.snippet_length}-frame snippets ({result['num_snippets']})",
        cell("ate"),
        cell("ate_std"),
        cell("ate_rmse"),
        UNITS["ate"],
    )
    aligned = "not aligned" if args.align == "none" else f"{args.align}-aligned"
    table.add_row(
        f"ATE, whole trajectory, {aligned} ({result['num_poses']} poses)",
        cell("ate_traj_mean"),
        cell("ate_traj_std"),
        cell("ate_traj"),
        UNITS["ate_traj"],
    )
    if args.align != "none":
        table.add_row(f"fitted scale ({args.align})", cell("ate_traj_scale"), "", "", "")
    for part, label in (("trans", "translation"), ("rot", "rotation")):
        table.add_row(
            f"RPE {label}, Δ = {args.delta} ({result['num_pairs']} pairs)",
            cell(f"rpe_{part}"),
            cell(f"rpe_{part}_std"),
            cell(f"rpe_{part}_rmse"),
            UNITS[f"rpe_{part}"],
        )
    segments = result["num_segments"]
    table.add_row(f"KITTI t_err ({segments} segments)", cell("drift_t_err"), "", "", "%")
    table.add_row(f"KITTI r_err ({segments} segments)", cell("drift_r_err"), "", "", "deg/100m")
    Console(width=max(100, Console().width)).print(table)


def _check_out(out: Path, inputs: Inputs) -> None:
    resolved = out.resolve()
    for directory in inputs.directories:
        d = directory.resolve()
        if resolved == d or d in resolved.parents:
            raise InputError(f"--out {out}: inside the input directory {directory}; "
                             "results are never written among the data")  # fmt: skip
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a directory")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mfg-eval-poses",
        description="ATE over snippets (Zhou et al. 2017), whole-trajectory ATE after alignment "
        "(evo, kitti-odom-eval), RPE (Sturm et al. 2012) and KITTI odometry drift of estimated "
        "trajectory files against ground truth, for one method or many. KITTI files are matched "
        "to the ground truth by frame index, TUM files by timestamp.",
    )
    add = parser.add_argument
    add("--gt", required=True, help="ground-truth pose file, or a directory of <seq>.txt files")
    add("--pred", required=True, action="append", metavar="[NAME=]PATH",
        help="estimated poses of one method: a file, or a directory of <seq>.txt files; "
        "repeat for more methods (default name: the file or directory name)")  # fmt: skip
    add("--seqs", nargs="+", metavar="SEQ", help="sequences to evaluate (default: all of --gt)")
    add("--format", choices=("auto", "kitti", "tum"), default="auto",
        help="format of every file; auto: by column count, per file (default: auto)")  # fmt: skip
    add("--align", choices=_ALIGN_CHOICES, default="none",
        help="alignment before the whole-trajectory ATE, RPE and drift: none (as the poses are), "
        "se3 / sim3 (Umeyama; evo -a / -as; kitti-odom-eval 6dof / 7dof), scale, scale_7dof "
        "(kitti-odom-eval) (default: none)")  # fmt: skip
    add("--n-to-align", type=int, default=None, metavar="N",
        help="fit the alignment on the first N matched poses of each sequence "
        "(default: all)")  # fmt: skip
    add("--align-origin", action="store_true",
        help="first put the estimate's first pose on the ground truth's (evo --align_origin; "
        "kitti-odom-eval's default)")  # fmt: skip
    add("--raw-rotations", action="store_true",
        help="rotation blocks as written, general matrix inverses (kitti-odom-eval's "
        "arithmetic) instead of projecting them onto SO(3) (evo's)")  # fmt: skip
    add("--t-max-diff", type=float, default=DEFAULT_MAX_TIME_DIFF, metavar="S",
        help="TUM files: largest time difference of a match in seconds (evo --t_max_diff; "
        f"default: {DEFAULT_MAX_TIME_DIFF:g})")  # fmt: skip
    add("--t-offset", type=float, default=0.0, metavar="S",
        help="TUM files: seconds added to the estimate's timestamps (evo --t_offset; "
        "default: 0)")  # fmt: skip
    add("--gt-times", type=Path, metavar="PATH",
        help="a KITTI ground truth's times.txt (one sequence), or a directory of <seq>.txt or "
        "<seq>/times.txt (default: <root>/sequences/<seq>/times.txt beside "
        "<root>/poses/)")  # fmt: skip
    add("--gt-rate", type=float, default=KITTI_FRAME_RATE, metavar="HZ",
        help="the clock of a KITTI ground truth without times: frame / HZ "
        "(default: 10)")  # fmt: skip
    add("--out", type=Path, help="write tables and figures into this directory")
    add("--json", action="store_true", help="print one JSON object")
    add("--delta", type=int, default=1, help="RPE gap in matched poses (default: 1)")
    add("--snippet-length", type=int, default=5, help="frames per ATE snippet (default: 5)")
    return parser


def _usage_error(parser: argparse.ArgumentParser, message: str) -> int:
    parser.print_usage(sys.stderr)
    print(f"error: {message}", file=sys.stderr)
    return 2


def _match_options(args: argparse.Namespace) -> MatchOptions:
    fit = 3 if args.align in _UMEYAMA else 1
    return MatchOptions(args.t_max_diff, args.t_offset, args.gt_times, args.gt_rate,
                        max(2, args.delta + 1, fit))  # fmt: skip


def _payload(
    args: argparse.Namespace,
    inputs: Inputs,
    per_sequence: dict[str, dict[str, dict[str, Any]]],
    overall: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """The JSON object of the run (module docstring)."""
    options_json = {
        "align": args.align,
        "n_to_align": args.n_to_align,
        "align_origin": args.align_origin,
        "raw_rotations": args.raw_rotations,
        "snippet_length": args.snippet_length,
        "delta": args.delta,
        "t_max_diff": args.t_max_diff,
        "t_offset": args.t_offset,
    }
    if inputs.single:
        (name,) = inputs.methods
        (seq,) = inputs.gt
        return {
            "gt": str(args.gt),
            "pred": str(args.pred[0]),
            "gt_format": inputs.gt[seq].format,
            "pred_format": inputs.methods[name][seq].format,
            **options_json,
            **per_sequence[name][seq],
            "units": UNITS,
        }
    return {
        "gt": str(args.gt),
        "sequences": list(inputs.gt),
        **options_json,
        "methods": {
            name: {
                "pred": str(inputs.sources[name]),
                "sequences": per_sequence[name],
                "overall": overall[name],
            }
            for name in inputs.methods
        },
        "units": UNITS,
    }


def _errors(inputs: Inputs, args: argparse.Namespace) -> dict[str, dict[str, SequenceErrors]]:
    """Method → sequence → the errors of its matched poses."""
    options = (args.delta, args.snippet_length, args.align, args.n_to_align)
    errors: dict[str, dict[str, SequenceErrors]] = {}
    for name, per in inputs.methods.items():
        errors[name] = {}
        for seq, pose_file in per.items():
            match = inputs.matches[name][seq]
            errors[name][seq] = sequence_errors(
                inputs.gt[seq].poses, pose_file.poses[match.pred_rows], *options,
                frames=match.gt_rows, align_origin=args.align_origin,
                project=not args.raw_rotations,
            )  # fmt: skip
    return errors


def _run(args: argparse.Namespace) -> int:
    seqs = [s for arg in args.seqs for s in arg.split(",") if s] if args.seqs else None
    inputs = read_inputs(args.gt, args.pred, seqs, args.format, _match_options(args))
    if args.out is not None:
        _check_out(args.out, inputs)
    errors = _errors(inputs, args)
    per_sequence = {
        name: {seq: {**summarise([e]), **inputs.matches[name][seq].summary()}
               for seq, e in per.items()}
        for name, per in errors.items()
    }  # fmt: skip
    overall = {}
    for name, per in errors.items():
        m = inputs.matches[name].values()
        overall[name] = {**summarise(list(per.values())),
                         "poses_given": sum(x.num_pred for x in m),
                         "gt_poses": sum(x.num_gt for x in m)}  # fmt: skip
    payload = _payload(args, inputs, per_sequence, overall)
    aligned = _alignment_words(args)
    tables = {
        f"table_{seq}": pose_results_table(
            {name: per_sequence[name][seq] for name in inputs.methods},
            f"Sequence {seq} ({inputs.gt[seq].poses.shape[0]} poses), {aligned}",
        )
        for seq in inputs.gt
    }
    tables["table_overall"] = pose_results_table(
        overall, f"All sequences ({', '.join(inputs.gt)}), {aligned}; scale is per sequence"
    )
    tables["table_matches"] = matches_table(inputs)
    if args.out is not None:
        _write_out(args.out, inputs, errors, tables, payload, _figure_alignment(args))
    if args.json:
        print(json.dumps(payload, indent=2))
    elif inputs.single:
        (name,) = inputs.matches
        _print_table(payload, args, next(iter(inputs.matches[name].values())))
    else:
        print("\n".join(t.markdown() for t in tables.values()), end="")
    return 0


def _figure_alignment(args: argparse.Namespace) -> str:
    """The alignment the figures' titles name (``origin`` for ``none`` with --align-origin)."""
    return "origin" if args.align == "none" and args.align_origin else args.align


def _write_out(
    out: Path,
    inputs: Inputs,
    errors: dict[str, dict[str, SequenceErrors]],
    tables: dict[str, Table],
    payload: dict[str, Any],
    align: str,
) -> None:
    """Draw every figure, then write tables, ``results.json`` and figures into ``out``."""
    import torch

    from mfg_lightning.core.atomic import atomic_write_text
    from mfg_lightning.metrics import kitti_drift_by_length
    from mfg_lightning.pictures import plots

    figures = {}
    for seq in inputs.gt:
        curves = {
            name: plots.curves_from_alignment(
                e.aligned, frames=e.frames, reference=e.reference,
                segments=(e.drift_t, e.drift_r, e.drift_length),
            )
            for name, e in ((name, errors[name][seq]) for name in errors)
        }  # fmt: skip
        figures[seq] = plots.sequence_figures(seq, curves, align)
    pooled = {}
    for name, per in errors.items():
        segs = [torch.cat([getattr(e, k) for e in per.values()])
                for k in ("drift_t", "drift_r", "drift_length")]  # fmt: skip
        by_length = kitti_drift_by_length(*segs)
        pooled[name] = {k: (float(v["t_err"]), float(v["r_err"])) for k, v in by_length.items()}
    aligned = "not aligned" if align == "none" else f"{align}-aligned"
    overall_drift = plots.drift_by_length_figure(
        pooled, f"all sequences ({', '.join(inputs.gt)}): KITTI drift per segment length, {aligned}"
    )
    out.mkdir(parents=True, exist_ok=True)
    for stem, table in tables.items():
        table.write(out / stem)
    atomic_write_text(out / "results.json", json.dumps(payload, indent=2) + "\n")
    for seq, figs in figures.items():
        plots.save_figures(figs, out, seq)
    plots.save_figures({"drift": overall_drift}, out, "overall")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 bad arguments or input files)."""
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, message already printed)
        return exc.code if isinstance(exc.code, int) else 2
    if args.delta < 1:
        return _usage_error(parser, "--delta must be >= 1")
    if args.snippet_length < 2:
        return _usage_error(parser, "--snippet-length must be >= 2")
    if args.n_to_align is not None and args.n_to_align < (3 if args.align in _UMEYAMA else 1):
        least = "3 (Umeyama's fit)" if args.align in _UMEYAMA else "1"
        return _usage_error(parser, f"--n-to-align must be >= {least} with --align {args.align}")
    if not (args.t_max_diff >= 0 and math.isfinite(args.t_max_diff)):
        return _usage_error(parser, "--t-max-diff must be a finite number of seconds >= 0")
    if not math.isfinite(args.t_offset):
        return _usage_error(parser, "--t-offset must be a finite number of seconds")
    if not (args.gt_rate > 0 and math.isfinite(args.gt_rate)):
        return _usage_error(parser, "--gt-rate must be a finite frame rate > 0 (Hz)")
    try:
        return _run(args)
    except Exception as exc:
        # PoseFileError and InputError answer before torch and the metrics are imported;
        # everything is classified as every entry point does (mfg_lightning.core.errors).
        return report_user_error(exc)


if __name__ == "__main__":
    sys.exit(main())
