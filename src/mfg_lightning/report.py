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

The report is written by :mod:`mfg_lightning.analysis.sweep_report`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from mfg_lightning.analysis.sweep_report import write_report
from mfg_lightning.core.errors import report_user_error


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
