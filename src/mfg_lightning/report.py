"""Tabulate a Hydra multirun: ``python -m mfg_lightning.report <multirun dir> [--out DIR]``.

A multirun directory (``hydra.sweep.dir``, e.g. ``outputs/train/multiruns/<date>/``) holds
``multirun.yaml`` and one directory per job (``0/``, ``1/``, … or whatever ``hydra.sweep.subdir``
names them), each with ``.hydra/overrides.yaml`` (the job's overrides, among them the swept
values), the resolved ``config.yaml`` (or Hydra's own ``.hydra/config.yaml``) and, once the job
finished, the ``metrics.json`` written by :mod:`mfg_lightning.train`.

The report, written into ``--out`` (default ``<multirun dir>/report/``), each file atomically:

* ``report.csv``: one row per job: job, status, reason, the swept values, ``w_s``, ``top_k``,
  ``lr``, ``seed`` (from the job's config), the main metrics (below), then every metric of
  ``metrics.json`` under its own key (``test/…``, ``val/…``);
* ``report.md``: the same rows as a Markdown table of the swept values and the main metrics, with
  the reasons of failed jobs and, for an Optuna sweep, the best parameters;
* ``error_vs_top_k.png``, ``error_vs_w_s.png``, ``active_fraction_vs_w_s.png``: each drawn when its
  x variable takes at least two values among the finished jobs, one line per value of the other
  swept parameters.
* when ``seed`` is swept (``hparams_search=seeds``, or ``seed=0,1,2`` beside other sweeps):
  ``seeds.csv`` and a section of ``report.md`` with one row per group of jobs that differ only in
  ``seed``: the number of finished seeds ``n`` and, for every metric, the mean and the sample
  standard deviation (ddof = 1) over those seeds. This ± is the run-to-run spread; the ± of a
  single job's ATE is over its snippets.

Main metrics (units as logged by the module): ``ate`` ± ``ate_std`` (m, ATE over 5-frame snippets,
``docs/protocols.md``), ``rpe_trans`` (m) and ``rpe_rot`` (rad), ``trans_err`` (m) and
``rot_err`` (rad) per frame, ``active_fraction`` (fraction of hidden units with a non-zero
activation per test input, measured *after* top-k, so at most ``top_k``), ``train_seconds``.

A job without ``metrics.json``, with an unreadable one, or with a Python traceback in a log file
of its directory is reported as ``failed`` with the reason; the other jobs are still tabulated.
Exit codes: 0 report written; 1 report written but no job finished; 2 not a multirun directory
(missing, empty, a single run, or no job directories: one ``error: …`` line).

The jobs are read by :mod:`mfg_lightning.analysis.sweeps`, the tables built by
:mod:`mfg_lightning.analysis.result_tables` and the figures drawn by
:mod:`mfg_lightning.pictures.plots`.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mfg_lightning.analysis.result_tables import (
    seeds_csv_table,
    seeds_table,
    sweep_csv_table,
    sweep_table,
)
from mfg_lightning.analysis.sweep_figures import sweep_figures
from mfg_lightning.analysis.sweeps import (
    JobRecord,
    SeedGroup,
    collect_jobs,
    common_overrides,
    optuna_note,
    seed_groups,
    swept_keys,
)
from mfg_lightning.core.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.core.errors import report_user_error
from mfg_lightning.core.tables import markdown_text
from mfg_lightning.pictures.plots import figure_png

__all__ = ["Report", "main", "report_markdown", "write_report"]


@dataclass
class Report:
    """What :func:`write_report` produced."""

    multirun_dir: Path
    out_dir: Path
    jobs: list[JobRecord]
    swept: list[str]
    csv_path: Path
    markdown_path: Path
    markdown: str
    plots: dict[str, Path]
    skipped_plots: dict[str, str]
    #: groups of jobs that differ only in ``seed`` (empty when no seed is swept)
    seed_groups: list[SeedGroup] = field(default_factory=list)

    @property
    def n_failed(self) -> int:
        return sum(not j.ok for j in self.jobs)


def report_markdown(
    jobs: Sequence[JobRecord],
    swept: Sequence[str],
    title: str = "",
    groups: Sequence[SeedGroup] = (),
    notes: Sequence[str] = (),
) -> str:
    """``report.md``: the title, the common overrides, a row per job (swept values and main
    metrics), the failed jobs with their reasons, warnings, the seed table and the notes."""
    lines = [f"# {title}", ""] if title else []
    common = common_overrides(jobs, swept)
    if common:
        lines += ["Common overrides: " + " ".join(f"`{o}`" for o in common), ""]
    lines.append(sweep_table(jobs, swept).markdown().rstrip())
    failed = [j for j in jobs if not j.ok]
    if failed:
        lines += ["", f"Failed jobs ({len(failed)} of {len(jobs)}):", ""]
        lines += [f"- `{j.name}`: {markdown_text(j.reason)}" for j in failed]
    warned = [j for j in jobs if j.ok and j.reason]
    if warned:
        lines += ["", "Warnings:", ""] + [
            f"- `{j.name}`: {markdown_text(j.reason)}" for j in warned
        ]
    if groups:
        lines += ["", "## Across seeds", "",
                  "Mean ± standard deviation (ddof = 1) over the finished seeds of each group of "
                  "jobs that differ only in `seed`; n counts the finished seeds.", "",
                  seeds_table(groups, swept).markdown().rstrip()]  # fmt: skip
    if notes:
        lines += ["", *notes]
    return "\n".join(lines).rstrip() + "\n"


def write_report(
    multirun_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str] | None = None
) -> Report:
    """Collect the jobs of ``multirun_dir`` and write the CSV, Markdown and PNGs into ``out_dir``
    (default ``<multirun dir>/report``). Everything is computed before the first file is written.

    Raises:
        NotAMultirunError: see :func:`collect_jobs`.
    """
    root = Path(multirun_dir)
    out = Path(out_dir) if out_dir is not None else root / "report"
    jobs = collect_jobs(root, exclude=[out])
    swept = swept_keys(jobs)
    images, skipped = sweep_figures(jobs, swept)
    notes = optuna_note(root)
    notes += [f"Plot not drawn: `{name}` ({why})." for name, why in skipped.items()]
    notes += [f"![{name}]({name})" for name in images]
    n_ok = sum(j.ok for j in jobs)
    title = f"Sweep report: {root.resolve().name} ({n_ok} of {len(jobs)} jobs finished)"
    groups = seed_groups(jobs, swept)
    markdown = report_markdown(jobs, swept, title=title, groups=groups, notes=notes)
    csv_path, md_path = out / "report.csv", out / "report.md"
    pngs = {name: figure_png(fig) for name, fig in images.items()}
    seeds_text = seeds_csv_table(groups, swept).csv() if groups else None
    atomic_write_text(csv_path, sweep_csv_table(jobs, swept).csv())
    atomic_write_text(md_path, markdown)
    if seeds_text is not None:
        atomic_write_text(out / "seeds.csv", seeds_text)
    plots = {name: atomic_write_bytes(out / name, data) for name, data in pngs.items()}
    return Report(root, out, jobs, swept, csv_path, md_path, markdown, plots, skipped, groups)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mfg_lightning.report",
        description="Tabulate a Hydra multirun of mfg_lightning.train: a CSV and a Markdown table "
        "with a row per job (swept values, ATE, RPE, per-frame errors, active units, training "
        "time) and plots of error against top-k and w_s.",
    )
    parser.add_argument("multirun_dir", type=Path, help="the multirun directory (hydra.sweep.dir)")
    parser.add_argument(
        "--out", type=Path, default=None, help="output directory (default: <multirun dir>/report)"
    )
    args = parser.parse_args(argv)
    try:
        report = write_report(args.multirun_dir, args.out)
    except Exception as err:  # a user error: one line, exit 2; a bug: its traceback
        return report_user_error(err)
    print(report.markdown)
    print(f"report: wrote {report.csv_path}, {report.markdown_path}", end="")
    print(f" and {len(report.plots)} plot(s) in {report.out_dir}")
    if report.seed_groups:
        print(f"report: {len(report.seed_groups)} group(s) across seeds in seeds.csv")
    if report.n_failed:
        print(
            f"report: {report.n_failed} of {len(report.jobs)} jobs failed (reasons in the table)",
            file=sys.stderr,
        )
    if report.n_failed == len(report.jobs):
        print("report: no job finished", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
