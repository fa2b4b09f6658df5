"""Evaluate estimated trajectory files against ground truth: ATE, RPE and KITTI drift, for one
method or many, with the alignments of evo and kitti-odom-eval.

Usage::

    mfg-eval-poses --gt poses/09.txt --pred 09_pred.txt [--format auto|kitti|tum] [--json]
                   [--delta 1] [--snippet-length 5] [--align none|se3|sim3|scale]
                   [--n-to-align N] [--out DIR]
    mfg-eval-poses --gt poses/ --pred a=method_a/ --pred b=method_b/ [--seqs 09 10]
                   --align sim3 --out results/
    python -m mfg_lightning.evaluate_poses ...

Inputs. ``--gt`` is a pose file or a directory of ``<seq>.txt`` files (KITTI's ``poses/``).
``--pred`` is repeated once per method, ``name=<file|dir>`` (or just ``<file|dir>``, named after
it): a directory holds ``<seq>.txt`` per sequence, a file is one sequence. Every file is KITTI
(12 numbers per line) or TUM (``timestamp tx ty tz qx qy qz qw``), camera-to-world
(:mod:`mfg_lightning.trajectory.pose_io`). The sequences evaluated are those of the ground truth, or
``--seqs``; a method without one of them is an error, unless ``--seqs`` leaves it out.

Reported per sequence and overall (``../shared/docs/protocols.md``):

* ATE over snippets (Zhou et al. 2017; Table 1): all overlapping snippets of ``--snippet-length``
  frames, ground truth and estimate each re-expressed relative to the snippet's first frame,
  translation and scale aligned; mean ± population std of ``sqrt(Σ‖·‖²)/L``, and the mean
  conventional RMSE (each snippet aligns itself: ``--align`` does not change it);
* whole-trajectory ATE (``ate_traj``; ``evo_ape``, kitti-odom-eval): the RMSE of the per-pose
  position errors after ``--align`` (fitted on the first ``--n-to-align`` poses), with their mean
  and std and the fitted scale (:mod:`mfg_lightning.metrics.ate_traj`);
* RPE (Sturm et al. 2012; Table 2) with a gap of ``--delta`` frames: translation (pose units) and
  rotation (radians), mean, std and RMSE;
* KITTI odometry drift (Geiger et al. 2012): ``t_err`` in %, ``r_err`` in deg/100 m; undefined
  (null) for paths shorter than 100 m.

RPE and drift are computed on the aligned estimate. The default ``--align none`` uses the poses
as they are (evo's and the devkit's default), so a monocular estimate must then be in metres for
them to mean anything. "Overall" pools the snippets, poses, pairs and segments of all sequences
(each sequence aligned on its own), as the devkit pools its segments.

Matching poses: the i-th pose of one file is compared with the i-th pose of the other; the files
must have the same number of poses. When both are TUM files their timestamps must also agree pose
by pose (to 1 µs); no association by nearest timestamp and no interpolation is done, so evaluate
estimates written for exactly the ground truth's frames.

Output. With one ``--pred <file>`` (no name) against a ``--gt`` file: a table, or with ``--json``
one flat JSON object, as before. Otherwise one Markdown table per sequence and one overall (rows:
methods), or with ``--json`` one object ``{"methods": {name: {"sequences": {seq: {...}},
"overall": {...}}}}``; NaN is written as null. ``--out DIR`` also writes there
``table_<seq>.{md,csv,tex}``, ``table_overall.{md,csv,tex}``, ``results.json``, and the figures
``trajectory_<seq>.png`` (x–z, every method over the ground truth), ``drift_<seq>.png`` (drift
per segment length), ``error_<seq>.png`` (position error along the trajectory) and
``drift_overall.png``. Everything is computed before the first file is written, and nothing is
ever written into an input directory.

Errors. Any problem with the input (a missing sequence, files of different lengths, a line that is
not a pose, a non-finite number) prints one line ``error: <file>:<line>: <reason>`` to stderr and
exits with status 2 before anything is written to stdout.
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
from mfg_lightning.trajectory.pose_io import PoseFile, PoseFileError, read_poses

if TYPE_CHECKING:
    from torch import Tensor

    from mfg_lightning.core.tables import Table
    from mfg_lightning.metrics import Alignment

__all__ = [
    "SequenceErrors",
    "evaluate_trajectory",
    "main",
    "match_pose_files",
    "sequence_errors",
    "summarise",
]

# TUM files are written with microsecond timestamps (or coarser).
_TIMESTAMP_TOLERANCE = 1e-6
# The modes of mfg_lightning.metrics.alignment.ALIGN_MODES (tests check they agree), listed here so
# that --help and argument errors answer before torch is imported.
_ALIGN_CHOICES = ("none", "se3", "sim3", "scale")

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


# ------------------------------------------------------------------------------------------------
# Metrics of one sequence, and pooled over sequences
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SequenceErrors:
    """The per-element errors of one method on one sequence, and its alignment.

    Attributes:
        pred_snippets, gt_snippets: ``(S, L, 4, 4)`` the ATE snippets.
        rpe_trans, rpe_rot: ``(N − Δ,)`` RPE per pair (m, rad), after alignment.
        drift_t, drift_r, drift_length: ``(G,)`` KITTI segment errors (per metre; rad per metre)
            and lengths (m), after alignment.
        traj: ``(N,)`` per-pose position errors after alignment (m).
        aligned: the alignment (aligned trajectories and fitted transform).
    """

    pred_snippets: Tensor
    gt_snippets: Tensor
    rpe_trans: Tensor
    rpe_rot: Tensor
    drift_t: Tensor
    drift_r: Tensor
    drift_length: Tensor
    traj: Tensor
    aligned: Alignment

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
) -> SequenceErrors:
    """Every per-element error of one estimated trajectory (see the module docstring).

    Args:
        gt: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), in frame order.
        pred: ``(N, 4, 4)`` estimated camera-to-world poses, any world frame, same frames.
        delta: RPE frame gap.
        snippet_length: frames per ATE snippet.
        align, n_to_align: alignment for the whole-trajectory ATE, RPE and drift.
    """
    # torch and the metrics (torchmetrics) are imported here, not at the top, so that --help and
    # input errors answer at once instead of after the 2–3 s these imports take.
    import torch

    from mfg_lightning.metrics import (
        align_trajectory,
        ate_traj_errors,
        kitti_segment_errors,
        relative_pose_errors,
    )
    from mfg_lightning.trajectory.trajectories import evaluation_poses, snippets_from_poses

    Q = evaluation_poses(torch.from_numpy(np.asarray(gt, dtype=np.float64)))
    P = evaluation_poses(torch.from_numpy(np.asarray(pred, dtype=np.float64)))
    if P.shape != Q.shape or P.dim() != 3:
        raise ValueError(f"gt and pred must be (N, 4, 4) alike, got {gt.shape} and {pred.shape}")
    aligned = align_trajectory(P, Q, align, n_to_align)
    rpe_trans, rpe_rot = relative_pose_errors(aligned.pred, aligned.target, delta)
    drift_t, drift_r, drift_length = kitti_segment_errors(aligned.pred, aligned.target)
    return SequenceErrors(
        pred_snippets=snippets_from_poses(P, snippet_length),
        gt_snippets=snippets_from_poses(Q, snippet_length),
        rpe_trans=rpe_trans,
        rpe_rot=rpe_rot,
        drift_t=drift_t,
        drift_r=drift_r,
        drift_length=drift_length,
        traj=ate_traj_errors(aligned),
        aligned=aligned,
    )


def _value(x: Any) -> float | None:
    f = float(x)
    return f if math.isfinite(f) else None


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

    from mfg_lightning.metrics import kitti_drift_from_segments, snippet_ate, summary

    def cat(name: str) -> torch.Tensor:
        return torch.cat([getattr(e, name) for e in errors])

    ate = snippet_ate(cat("pred_snippets"), cat("gt_snippets"))
    traj = summary(cat("traj"))
    trans, rot = summary(cat("rpe_trans")), summary(cat("rpe_rot"))
    drift = kitti_drift_from_segments(cat("drift_t"), cat("drift_r"))
    out: dict[str, float | int | None] = {
        "num_poses": sum(e.num_poses for e in errors),
        "num_snippets": sum(int(e.pred_snippets.shape[0]) for e in errors),
        "num_pairs": sum(int(e.rpe_trans.numel()) for e in errors),
        "num_segments": sum(int(e.drift_t.numel()) for e in errors),
    }
    out.update({key: _value(v) for key, v in ate.items()})
    out["ate_traj"] = _value(traj["rmse"])
    out["ate_traj_mean"] = _value(traj["mean"])
    out["ate_traj_std"] = _value(traj["std"])
    out["ate_traj_scale"] = _value(errors[0].aligned.scale) if len(errors) == 1 else None
    for part, stats in (("trans", trans), ("rot", rot)):
        out[f"rpe_{part}"] = _value(stats["mean"])
        out[f"rpe_{part}_std"] = _value(stats["std"])
        out[f"rpe_{part}_rmse"] = _value(stats["rmse"])
    out.update({f"drift_{key}": _value(v) for key, v in drift.items()})
    return out


def evaluate_trajectory(
    gt: np.ndarray, pred: np.ndarray, **options: Any
) -> dict[str, float | int | None]:
    """ATE over snippets, whole-trajectory ATE, RPE and KITTI drift of one estimated trajectory.

    Args:
        gt: ``(N, 4, 4)`` ground-truth camera-to-world poses (metres), in frame order.
        pred: ``(N, 4, 4)`` estimated camera-to-world poses, any world frame, same frames.
        options: ``delta``, ``snippet_length``, ``align``, ``n_to_align`` as
            :func:`sequence_errors` takes them.

    Returns:
        The flat dict of :func:`summarise`.
    """
    return summarise([sequence_errors(gt, pred, **options)])


# ------------------------------------------------------------------------------------------------
# Inputs: methods, sequences, files
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Inputs:
    """The pose files to evaluate, read and checked.

    Attributes:
        gt: sequence → ground-truth file, in evaluation order.
        methods: method name → sequence → its pose file (the same sequences as ``gt``).
        sources: method name → the ``--pred`` path it came from.
        single: one unnamed ``--pred <file>`` against a ``--gt <file>`` (the flat output).
        directories: the input directories (never written into).
    """

    gt: dict[str, PoseFile]
    methods: dict[str, dict[str, PoseFile]]
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
    gt: str | Path, preds: Sequence[str], seqs: Sequence[str] | None = None, fmt: str = "auto"
) -> Inputs:
    """Read and check every pose file of an evaluation (see the module docstring).

    Raises:
        PoseFileError: a file that cannot be read as a pose file, a missing sequence of a method
            (naming the file it looked for), files of different lengths or timestamps.
        InputError: arguments that do not fit together (repeated names, a file for many
            sequences).
    """
    gt = Path(gt)
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
    methods: dict[str, dict[str, PoseFile]] = {}
    for name, per_seq in files.items():
        methods[name] = {}
        for seq, path in per_seq.items():
            pose_file = read_poses(path, fmt)
            match_pose_files(gt_files[seq], pose_file)
            methods[name][seq] = pose_file
    single = (
        len(named) == 1 and named[0][0] is None and not gt.is_dir() and not named[0][1].is_dir()
    )
    directories = [p for p in [gt, *sources.values()] if p.is_dir()]
    return Inputs(gt_files, methods, sources, single, directories)


# ------------------------------------------------------------------------------------------------
# Output
# ------------------------------------------------------------------------------------------------


def _print_table(result: dict[str, float | int | None], args: argparse.Namespace) -> None:
    from rich.console import Console
    from rich.table import Table

    from mfg_lightning.core.tables import fmt

    def cell(key: str, digits: int = 5) -> str:
        return fmt(result[key], digits) if result[key] is not None else "n/a"

    table = Table(
        title=f"{args.pred[0]} vs {args.gt} ({result['num_poses']} poses)",
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
        "trajectory files against ground truth, for one method or many.",
    )
    parser.add_argument(
        "--gt", required=True, help="ground-truth pose file, or a directory of <seq>.txt files"
    )
    parser.add_argument(
        "--pred",
        required=True,
        action="append",
        metavar="[NAME=]PATH",
        help="estimated poses of one method: a file, or a directory of <seq>.txt files; "
        "repeat for more methods (default name: the file or directory name)",
    )
    parser.add_argument(
        "--seqs", nargs="+", metavar="SEQ", help="sequences to evaluate (default: all of --gt)"
    )
    parser.add_argument(
        "--format",
        choices=("auto", "kitti", "tum"),
        default="auto",
        help="format of every file; auto: by column count, per file (default: auto)",
    )
    parser.add_argument(
        "--align",
        choices=_ALIGN_CHOICES,
        default="none",
        help="alignment before the whole-trajectory ATE, RPE and drift: none (as the poses are), "
        "se3 / sim3 (Umeyama; evo -a / -as), scale (kitti-odom-eval) (default: none)",
    )
    parser.add_argument(
        "--n-to-align",
        type=int,
        default=None,
        metavar="N",
        help="fit the alignment on the first N poses of each sequence (default: all)",
    )
    parser.add_argument("--out", type=Path, help="write tables and figures into this directory")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--delta", type=int, default=1, help="RPE frame gap (default: 1)")
    parser.add_argument(
        "--snippet-length", type=int, default=5, help="frames per ATE snippet (default: 5)"
    )
    return parser


def _usage_error(parser: argparse.ArgumentParser, message: str) -> int:
    parser.print_usage(sys.stderr)
    print(f"error: {message}", file=sys.stderr)
    return 2


def _run(args: argparse.Namespace) -> int:
    seqs = [s for arg in args.seqs for s in arg.split(",") if s] if args.seqs else None
    inputs = read_inputs(args.gt, args.pred, seqs, args.format)
    if args.out is not None:
        _check_out(args.out, inputs)
    options = (args.delta, args.snippet_length, args.align, args.n_to_align)
    errors = {
        name: {seq: sequence_errors(inputs.gt[seq].poses, f.poses, *options)
               for seq, f in per.items()}
        for name, per in inputs.methods.items()
    }  # fmt: skip
    per_sequence = {
        name: {seq: summarise([e]) for seq, e in per.items()} for name, per in errors.items()
    }
    overall = {name: summarise(list(per.values())) for name, per in errors.items()}
    options_json = {
        "align": args.align,
        "n_to_align": args.n_to_align,
        "snippet_length": args.snippet_length,
        "delta": args.delta,
    }
    if inputs.single:
        (name,) = inputs.methods
        (seq,) = inputs.gt
        payload: dict[str, Any] = {
            "gt": str(args.gt),
            "pred": str(args.pred[0]),
            "gt_format": inputs.gt[seq].format,
            "pred_format": inputs.methods[name][seq].format,
            **options_json,
            **per_sequence[name][seq],
            "units": UNITS,
        }
    else:
        payload = {
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
    aligned = "not aligned" if args.align == "none" else f"{args.align} alignment"
    if args.n_to_align is not None and args.align != "none":
        aligned += f" on the first {args.n_to_align} poses"
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
    if args.out is not None:
        _write_out(args.out, inputs, errors, tables, payload, args.align)
    if args.json:
        print(json.dumps(payload, indent=2))
    elif inputs.single:
        _print_table(payload, args)
    else:
        print("\n".join(t.markdown() for t in tables.values()), end="")
    return 0


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
        curves = {name: plots.curves_from_alignment(errors[name][seq].aligned) for name in errors}
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
    if args.n_to_align is not None and args.n_to_align < 1:
        return _usage_error(parser, "--n-to-align must be >= 1")
    try:
        return _run(args)
    except Exception as exc:
        # PoseFileError and InputError answer before torch and the metrics are imported;
        # everything is classified as every entry point does (mfg_lightning.core.errors).
        return report_user_error(exc)


if __name__ == "__main__":
    sys.exit(main())
