"""What ``mfg-eval-poses`` computes and writes, given its inputs read and matched
(:mod:`mfg_lightning.trajectory.pose_inputs`): the errors of every method on every sequence
(:mod:`mfg_lightning.metrics.pose_evaluation`), their tables, the JSON object, the figures and
evo's result archives. ``docs/evaluate_poses.md`` is the user's description.

Everything is computed before the first file is written, and nothing is written into an input
directory.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mfg_lightning.analysis.result_tables import pose_results_table
from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.core.tables import Column, Table, fmt
from mfg_lightning.metrics.pose_evaluation import (
    ELEMENTS,
    POSE_RELATIONS,
    UNITS,
    RpeOptions,
    SequenceErrors,
    sequence_errors,
    summarise,
)
from mfg_lightning.metrics.stats import STATISTICS
from mfg_lightning.trajectory.association import MatchOptions, PoseMatch
from mfg_lightning.trajectory.pose_inputs import Inputs
from mfg_lightning.trajectory.result_archive import result_archive_bytes

__all__ = ["EvalOptions", "PoseReport", "evaluate_inputs", "matches_table"]

#: evo's words for its pose relations and units (the titles of its results).
_RELATION_WORDS = {
    "trans_part": "translation part",
    "rot_part": "rotation part",
    "angle_rad": "rotation angle in radians",
    "angle_deg": "rotation angle in degrees",
    "full": "full transformation",
    "point_distance": "point distance",
}


@dataclass(frozen=True)
class EvalOptions:
    """How the poses are scored (the command's options; ``docs/evaluate_poses.md``).

    Attributes:
        align, n_to_align, align_origin: the alignment (:func:`~mfg_lightning.metrics.
            align_trajectory`).
        raw_rotations: rotation blocks as written (kitti-odom-eval's arithmetic).
        snippet_length: frames per ATE snippet.
        rpe: the RPE's pairs and evo's pose relation.
        match: how TUM files are matched by timestamp.
        plot_mode: the axes of the trajectory figures (evo's ``--plot_mode``).
    """

    align: str = "none"
    n_to_align: int | None = None
    align_origin: bool = False
    raw_rotations: bool = False
    snippet_length: int = 5
    rpe: RpeOptions = field(default_factory=RpeOptions)
    match: MatchOptions = field(default_factory=MatchOptions)
    plot_mode: str = "xz"

    def alignment_words(self) -> str:
        """The alignment, in words, for the tables' titles."""
        words = "not aligned" if self.align == "none" else f"{self.align} alignment"
        if self.n_to_align is not None and self.align != "none":
            words += f" on the first {self.n_to_align} poses"
        if self.align_origin:
            words += ", first poses made equal (--align_origin)"
        if self.raw_rotations:
            words += ", rotations as written (--raw-rotations)"
        return words

    def json(self) -> dict[str, Any]:
        """The options as the JSON object reports them."""
        own = asdict(self)
        keys = ("align", "n_to_align", "align_origin", "raw_rotations", "snippet_length")
        return {**{k: own[k] for k in keys}, **own["rpe"], "t_max_diff": self.match.max_diff,
                "t_offset": self.match.offset}  # fmt: skip


@dataclass(frozen=True)
class PoseReport:
    """The results of one evaluation.

    Attributes:
        errors: method → sequence → its per-element errors.
        per_sequence: method → sequence → :func:`summarise` and what was matched.
        overall: method → the pooled :func:`summarise` and the counts of poses.
    """

    errors: dict[str, dict[str, SequenceErrors]]
    per_sequence: dict[str, dict[str, dict[str, Any]]]
    overall: dict[str, dict[str, Any]]


def evaluate_inputs(inputs: Inputs, options: EvalOptions) -> PoseReport:
    """Every method's errors on every sequence, per sequence and pooled."""
    errors: dict[str, dict[str, SequenceErrors]] = {}
    for name, per in inputs.methods.items():
        errors[name] = {}
        for seq, pose_file in per.items():
            match = inputs.matches[name][seq]
            errors[name][seq] = sequence_errors(
                inputs.gt[seq].poses, pose_file.poses[match.pred_rows], options.rpe,
                options.snippet_length, options.align, options.n_to_align,
                frames=match.gt_rows, align_origin=options.align_origin,
                project=not options.raw_rotations,
            )  # fmt: skip
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
    return PoseReport(errors, per_sequence, overall)


def statistics_units(options: EvalOptions) -> dict[str, str]:
    """The unit of every element set of ``statistics`` (``sse`` is in its square)."""
    relation = POSE_RELATIONS[options.rpe.pose_relation]
    return {"ate": "m", "ate_rmse": "m", "ate_traj": "m", "ape": relation, "rpe": relation,
            "rpe_trans": "m", "rpe_rot": "rad"}  # fmt: skip


def payload(
    inputs: Inputs, report: PoseReport, options: EvalOptions, gt: str, preds: list[str]
) -> dict[str, Any]:
    """The JSON object of the run: flat for one unnamed file, else per method and sequence."""
    common = {**options.json(), "units": UNITS, "statistics_units": statistics_units(options)}
    if inputs.single:
        (name,) = inputs.methods
        (seq,) = inputs.gt
        return {
            "gt": gt,
            "pred": preds[0],
            "gt_format": inputs.gt[seq].format,
            "pred_format": inputs.methods[name][seq].format,
            **common,
            **report.per_sequence[name][seq],
        }
    return {
        "gt": gt,
        "sequences": list(inputs.gt),
        **common,
        "methods": {
            name: {
                "pred": str(inputs.sources[name]),
                "sequences": report.per_sequence[name],
                "overall": report.overall[name],
            }
            for name in inputs.methods
        },
    }


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


def tables(inputs: Inputs, report: PoseReport, options: EvalOptions) -> dict[str, Table]:
    """``table_<seq>`` per sequence, ``table_overall`` and ``table_matches``."""
    aligned = options.alignment_words()
    out = {
        f"table_{seq}": pose_results_table(
            {name: report.per_sequence[name][seq] for name in inputs.methods},
            f"Sequence {seq} ({inputs.gt[seq].poses.shape[0]} poses), {aligned}",
        )
        for seq in inputs.gt
    }
    out["table_overall"] = pose_results_table(
        report.overall, f"All sequences ({', '.join(inputs.gt)}), {aligned}; scale is per sequence"
    )
    out["table_matches"] = matches_table(inputs)
    return out


def statistics_table(result: dict[str, Any], options: EvalOptions, title: str) -> Table:
    """One method on one sequence: a row per set of errors, a column per evo statistic (of that
    row's elements: snippets, poses or pairs), then the fitted scale and the KITTI drift."""
    stats, units = result["statistics"], statistics_units(options)
    rpe = options.rpe
    relation = rpe.pose_relation
    gap = f"Δ = {rpe.delta:g} {'frames' if rpe.delta_unit == 'f' else 'm'}"
    gap += ", all pairs" if rpe.all_pairs else ""
    rows = {
        "ate": f"ATE per {options.snippet_length}-frame snippet",
        "ate_rmse": f"RMSE per {options.snippet_length}-frame snippet",
        "ate_traj": "ATE whole trajectory",
        "ape": f"APE {relation}",
        "rpe_trans": f"RPE translation, {gap}",
        "rpe_rot": f"RPE rotation, {gap}",
        "rpe": f"RPE {relation}, {gap}",
    }
    if relation == "trans_part":  # the same numbers as ATE whole trajectory and RPE translation
        del rows["ape"], rows["rpe"]
    columns = [Column("errors"), Column("n"), *(Column(s, digits=5) for s in STATISTICS),
               Column("unit")]  # fmt: skip
    table = Table(columns, title=title)
    for key, label in rows.items():
        count = result[f"num_{ELEMENTS[key][1]}"]
        table.add_row([label, count, *(stats[key][s] for s in STATISTICS), units[key]])
    blank: list[Any] = [""] * len(STATISTICS)
    if options.align != "none":
        mean = STATISTICS.index("mean")
        scale = [*blank[:mean], result["ate_traj_scale"], *blank[mean + 1 :]]
        table.add_row([f"fitted scale ({options.align})", 1, *scale, "1"])
    for key, label in (("drift_t_err", "KITTI t_err"), ("drift_r_err", "KITTI r_err")):
        mean = STATISTICS.index("mean")
        value = [*blank[:mean], result[key], *blank[mean + 1 :]]
        table.add_row([label, result["num_segments"], *value, UNITS[key]])
    return table


def single_title(match: PoseMatch, options: EvalOptions, gt: str, pred: str) -> str:
    """The title of the one-file table: what was compared and how it was matched."""
    used = f"{match.num_matched} of {match.num_pred} poses matched to {match.num_gt}"
    return f"{pred} vs {gt} ({used} {match.describe(options.match)}); {options.alignment_words()}"


def print_single(result: dict[str, Any], title: str, options: EvalOptions) -> None:
    """Print :func:`statistics_table` with rich, at its natural width (no cell is wrapped)."""
    from rich.console import Console
    from rich.table import Table as RichTable

    table = statistics_table(result, options, title)
    rich = RichTable(
        title=title,
        caption="statistics over each row's n elements (snippets, poses, pairs; scale and KITTI "
        "drift: mean only); std: population; sse: sum of squares, in the unit squared; ATE "
        "whole trajectory and RPE translation are evo's APE and RPE with -r trans_part",
    )
    for i, column in enumerate(table.columns):
        rich.add_column(
            column.name, justify="left" if i in (0, len(table.columns) - 1) else "right"
        )
    for row in table.rows:
        rich.add_row(*(v if isinstance(v, str) else fmt(v, 5) for v in row))
    Console(width=max(200, Console().width)).print(rich)


def archive_title(metric: str, options: EvalOptions) -> str:
    """The title evo gives a result of ``metric`` (``APE`` or ``RPE``) with these options."""
    relation = options.rpe.pose_relation
    unit = {"1": "unit-less"}.get(POSE_RELATIONS[relation], POSE_RELATIONS[relation])
    title = f"{metric} w.r.t. {_RELATION_WORDS[relation]} ({unit})"
    if metric == "RPE":
        rpe = options.rpe
        title += f"\nfor delta = {rpe.delta} ({'frames' if rpe.delta_unit == 'f' else 'm'})"
        title += " using all pairs" if rpe.all_pairs else " using consecutive pairs"
    title += {
        "se3": "\n(with SE(3) Umeyama alignment)",
        "sim3": "\n(with Sim(3) Umeyama alignment)",
        "sim3_scale": "\n(scale corrected)",
        "none": "" if options.align_origin else "\n(not aligned)",
    }.get(options.align, f"\n(kitti-odom-eval {options.align} alignment)")
    if options.align != "none" and options.n_to_align is not None:
        title += f" (aligned poses: {options.n_to_align})"
    if options.align_origin:
        title += "\n(with origin alignment)"
    return title


def archives(
    inputs: Inputs, report: PoseReport, options: EvalOptions, path: Path
) -> dict[Path, bytes]:
    """evo's result archives (:mod:`mfg_lightning.trajectory.result_archive`), APE and RPE of
    every method on every sequence: ``<stem>_ape.zip`` and ``<stem>_rpe.zip`` beside ``path``
    for one unnamed file, else ``<stem>_<method>_<seq>_{ape,rpe}.zip``."""
    relation = options.rpe.pose_relation
    unit = {"1": "unit-less"}.get(POSE_RELATIONS[relation], POSE_RELATIONS[relation])
    out = {}
    stem = path.name.removesuffix(".zip")
    for name, per in report.errors.items():
        for seq, e in per.items():
            pose_file, gt = inputs.methods[name][seq], inputs.gt[seq]
            match = inputs.matches[name][seq]
            times = None if pose_file.timestamps is None else pose_file.timestamps[match.pred_rows]
            stats = report.per_sequence[name][seq]["statistics"]
            for metric, errors, rows in (("APE", e.ape, None), ("RPE", e.rpe, e.pairs[:, 1])):
                arrays: dict[str, np.ndarray] = {"error_array": errors.numpy()}
                if times is not None:
                    t = times if rows is None else times[rows.numpy()]
                    arrays["timestamps"] = t
                    arrays["seconds_from_start"] = t - times[0]
                info = {"title": archive_title(metric, options), "ref_name": str(gt.path),
                        "est_name": str(pose_file.path) if inputs.single else f"{name}/{seq}",
                        "label": f"{metric} ({unit})"}  # fmt: skip
                tail = (
                    f"_{metric.lower()}.zip"
                    if inputs.single
                    else f"_{name}_{seq}_{metric.lower()}.zip"
                )
                out[path.with_name(stem + tail)] = result_archive_bytes(
                    info, stats[metric.lower()], arrays
                )
    return out


def figures(inputs: Inputs, report: PoseReport, options: EvalOptions) -> dict[str, dict]:
    """Every figure: ``{prefix: {kind: Figure}}`` per sequence and ``overall``."""
    from mfg_lightning.metrics import kitti_drift_by_length
    from mfg_lightning.pictures import plots

    align = "origin" if options.align == "none" and options.align_origin else options.align
    errors = report.errors
    out: dict[str, dict] = {}
    cols = ["xyz".index(a) for a in options.plot_mode]
    for seq in inputs.gt:
        curves = {
            name: plots.curves_from_alignment(
                e.aligned, frames=e.frames, reference=e.reference,
                segments=(e.drift_t, e.drift_r, e.drift_length),
            )
            for name, e in ((name, errors[name][seq]) for name in errors)
        }  # fmt: skip
        out[seq] = plots.sequence_figures(seq, curves, align)
        if options.plot_mode != "xz":  # evo's --plot_mode: drawn again on the axes asked for
            first = next(iter(curves.values()))
            aligned = "not aligned" if align == "none" else f"{align}-aligned"
            out[seq]["trajectory"] = plots.trajectory_figure(
                first.gt_xyz[:, cols], {name: c.pred_xyz[:, cols] for name, c in curves.items()},
                f"sequence {seq}: {options.plot_mode} view, {aligned}", options.plot_mode,
            )  # fmt: skip
    pooled = {}
    for name, per in errors.items():
        segs = [torch.cat([getattr(e, k) for e in per.values()])
                for k in ("drift_t", "drift_r", "drift_length")]  # fmt: skip
        by_length = kitti_drift_by_length(*segs)
        pooled[name] = {k: (float(v["t_err"]), float(v["r_err"])) for k, v in by_length.items()}
    aligned = "not aligned" if align == "none" else f"{align}-aligned"
    out["overall"] = {"drift": plots.drift_by_length_figure(
        pooled, f"all sequences ({', '.join(inputs.gt)}): KITTI drift per segment length, {aligned}"
    )}  # fmt: skip
    return out


def write_out(
    out: Path, tables_: dict[str, Table], result: dict[str, Any], figures_: dict[str, dict]
) -> None:
    """Write tables, ``results.json`` and figures into ``out``."""
    from mfg_lightning.pictures import plots

    out.mkdir(parents=True, exist_ok=True)
    for stem, table in tables_.items():
        table.write(out / stem)
    atomic_write_text(out / "results.json", json.dumps(result, indent=2) + "\n")
    for prefix, figs in figures_.items():
        plots.save_figures(figs, out, prefix)
