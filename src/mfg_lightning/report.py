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
``../shared/docs/protocols.md``), ``rpe_trans`` (m) and ``rpe_rot`` (rad), ``trans_err`` (m) and
``rot_err`` (rad) per frame, ``active_fraction`` (fraction of hidden units with a non-zero
activation per test input, measured *after* top-k, so at most ``top_k``), ``train_seconds``.

A job without ``metrics.json``, with an unreadable one, or with a Python traceback in a log file
of its directory is reported as ``failed`` with the reason; the other jobs are still tabulated.
Exit codes: 0 report written; 1 report written but no job finished; 2 not a multirun directory
(missing, empty, a single run, or no job directories).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import re
import statistics
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from mfg_lightning.atomic import atomic_write_bytes, atomic_write_text

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: the main metrics: report column → key in ``metrics.json["metrics"]``
MAIN_METRICS: dict[str, str] = {
    "ate": "test/ate",
    "ate_std": "test/ate_std",
    "ate_rmse": "test/ate_rmse",
    "rpe_trans": "test/rpe_trans",
    "rpe_rot": "test/rpe_rot",
    "trans_err": "test/trans_err",
    "rot_err": "test/rot_err",
    "active_fraction": "test/active_fraction",
}
#: config values every row carries (read from the job's config): column → dotted config key
CONFIG_COLUMNS: dict[str, str] = {
    "w_s": "model.loss.w_s",
    "top_k": "model.top_k",
    "lr": "model.optimizer.lr",
    "seed": "seed",
}
#: the config keys of the two axes of the sparsity study
W_S_KEY = "model.loss.w_s"
TOP_K_KEY = "model.top_k"
PLOT_FILES = ("error_vs_top_k.png", "error_vs_w_s.png", "active_fraction_vs_w_s.png")

# A log line that names an exception ("ValueError: …", "Error executing job …").
_ERROR_LINE = re.compile(r"\b(\w*Error|\w*Exception)\b")


class NotAMultirunError(ValueError):
    """The directory is missing, empty, a single run, or holds no job directories."""


@dataclass
class JobRecord:
    """One job of a multirun.

    Attributes:
        name: the job directory relative to the multirun directory (``"0"``, ``"1"``, …).
        path: the job directory.
        num: Hydra's ``hydra.job.num`` (None when ``.hydra/hydra.yaml`` is missing).
        overrides: the job's command-line overrides, ``key → value`` as written (strings).
        config: the job's config (resolved ``config.yaml`` if present, else ``.hydra/config.yaml``).
        metrics: ``metrics.json["metrics"]`` (floats, None where the value was not finite).
        extra: the other fields of ``metrics.json`` (``train_seconds``, ``global_step``, …).
        status: ``"ok"`` or ``"failed"``.
        reason: why the job failed, or a warning about a finished job (non-finite metrics).
    """

    name: str
    path: Path
    num: int | None = None
    overrides: dict[str, str] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, float | None] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    status: str = "ok"
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def config_value(self, key: str) -> Any:
        """A dotted key of the job's config (None if absent)."""
        node: Any = self.config
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                return None
            node = node[part]
        return node

    def metric(self, column: str) -> float | None:
        """A main metric by report column name (see :data:`MAIN_METRICS`), or a raw key."""
        return _finite(self.metrics.get(MAIN_METRICS.get(column, column)))

    def top_k_percent(self) -> float | None:
        """Hidden units kept at evaluation in % (``model.top_k`` null means all: 100)."""
        k = self.config_value(TOP_K_KEY)
        if k is None:
            return 100.0 if self.config else None
        return _finite(k) * 100.0 if _finite(k) is not None else None


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


# --------------------------------------------------------------------------------------------
# Collecting the jobs
# --------------------------------------------------------------------------------------------


def _finite(value: Any) -> float | None:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _natural_key(name: str) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def find_job_dirs(multirun_dir: Path, exclude: Iterable[Path] = ()) -> list[Path]:
    """Every directory below ``multirun_dir`` that holds a ``.hydra/`` (a job), not descending
    into jobs, hidden directories (``.submitit/``) or ``exclude`` (the report's own output)."""
    excluded = {p.resolve() for p in exclude}
    jobs = []
    for root, dirs, _ in os.walk(multirun_dir):
        here = Path(root)
        if here.resolve() in excluded:
            dirs[:] = []
            continue
        if here != multirun_dir and ".hydra" in dirs:
            jobs.append(here)
            dirs[:] = []
            continue
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
    return jobs


def _read_yaml(path: Path) -> Any:
    with path.open() as fh:
        return yaml.safe_load(fh)


def parse_override(text: str) -> tuple[str, str]:
    """``"+model.loss.w_s=10"`` → ``("model.loss.w_s", "10")``; ``~key`` → ``("key", "~")``."""
    text = text.strip()
    if text.startswith("~"):
        key, _, _ = text[1:].partition("=")
        return key, "~"
    key, _, value = text.lstrip("+").partition("=")
    return key, value


def _error_in_logs(job_dir: Path, tracebacks_only: bool = False) -> str | None:
    """Why a job failed, from the log files of its directory (``*.log``, ``*.err``).

    The last line naming an exception of a Python traceback or of Hydra's "Error executing job";
    unless ``tracebacks_only``, also the message of the last ``[ERROR]`` record of a Hydra job
    log (``[time][logger][ERROR] - message``). None when the logs say nothing.
    """
    found = None
    for log in sorted(job_dir.glob("*.log")) + sorted(job_dir.glob("*.err")):
        try:
            text = log.read_text(errors="replace")
        except OSError:
            continue
        lines = text.splitlines()
        errors = []
        if not tracebacks_only:
            errors += [ln.split("] - ", 1)[-1].strip() for ln in lines if "[ERROR]" in ln]
        if "Traceback (most recent call last)" in text or "Error executing job" in text:
            named = [ln.strip() for ln in lines if _ERROR_LINE.search(ln)]
            errors.append(named[-1] if named else "traceback")
        if errors:
            found = f"{log.name}: {errors[-1]}"
    return found


def read_job(job_dir: Path, multirun_dir: Path) -> JobRecord:
    """Read one job directory; never raises for a broken job (it is marked failed instead)."""
    job = JobRecord(name=job_dir.relative_to(multirun_dir).as_posix(), path=job_dir)
    hydra_dir = job_dir / ".hydra"
    problems: list[str] = []
    try:
        overrides = _read_yaml(hydra_dir / "overrides.yaml") or []
        job.overrides = dict(parse_override(str(o)) for o in overrides)
    except (OSError, yaml.YAMLError) as err:
        problems.append(f"unreadable .hydra/overrides.yaml ({err})")
    try:
        job.num = int(_read_yaml(hydra_dir / "hydra.yaml")["hydra"]["job"]["num"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        job.num = None
    for cfg_path in (job_dir / "config.yaml", hydra_dir / "config.yaml"):
        if cfg_path.is_file():
            try:
                job.config = _read_yaml(cfg_path) or {}
                break
            except (OSError, yaml.YAMLError) as err:
                problems.append(f"unreadable {cfg_path.relative_to(job_dir)} ({err})")

    metrics_path = job_dir / "metrics.json"
    finished = metrics_path.is_file()
    # metrics.json is written last: a finished job failed only if it crashed with a traceback
    # afterwards, not because something logged an error on the way
    error = _error_in_logs(job_dir, tracebacks_only=finished)
    if not finished:
        job.status = "failed"
        job.reason = error or "no metrics.json: the job crashed, was killed or is still running"
        if error is None and (multirun_dir / ".submitit").is_dir():
            job.reason += f" (SLURM logs: {multirun_dir / '.submitit'})"
    else:
        try:
            payload = json.loads(metrics_path.read_text())
            if not isinstance(payload, dict) or not isinstance(payload.get("metrics"), dict):
                raise ValueError("no 'metrics' mapping")
            job.metrics = {str(k): _finite(v) for k, v in payload["metrics"].items()}
            job.extra = {k: v for k, v in payload.items() if k != "metrics"}
        except (OSError, ValueError) as err:
            job.status, job.reason = "failed", f"unreadable metrics.json ({err})"
        if job.ok and error is not None:
            job.status, job.reason = "failed", error
        if job.ok:
            missing = [c for c in ("trans_err", "rot_err") if job.metric(c) is None]
            if missing:
                job.reason = "non-finite or missing: " + ", ".join(MAIN_METRICS[c] for c in missing)
    if problems:
        job.reason = "; ".join(filter(None, [job.reason, *problems]))
    return job


def collect_jobs(
    multirun_dir: str | os.PathLike[str], exclude: Iterable[Path] = ()
) -> list[JobRecord]:
    """Every job of a multirun directory, in Hydra's job order.

    Raises:
        NotAMultirunError: the directory is missing or empty, is a single run directory, or
            holds no job directories.
    """
    root = Path(multirun_dir)
    if not root.is_dir():
        raise NotAMultirunError(f"{root} is not a directory")
    if not any(root.iterdir()):
        raise NotAMultirunError(
            f"{root} is empty: no jobs to report (Hydra creates a job directory when a job starts)"
        )
    if (root / ".hydra").is_dir():
        raise NotAMultirunError(
            f"{root} is a single run directory (it has .hydra/ itself), not a multirun: pass the "
            "multirun directory (hydra.sweep.dir) holding multirun.yaml and one directory per job"
        )
    dirs = find_job_dirs(root, exclude=exclude)
    if not dirs:
        hint = (
            "multirun.yaml is there, so no job has started yet"
            if (root / "multirun.yaml").is_file()
            else "a Hydra multirun directory holds multirun.yaml and one directory per job"
        )
        raise NotAMultirunError(f"{root} holds no job directories (with .hydra/): {hint}")
    jobs = [read_job(d, root) for d in dirs]
    jobs.sort(
        key=lambda j: (j.num is None, j.num if j.num is not None else 0, _natural_key(j.name))
    )
    return jobs


def swept_keys(jobs: Sequence[JobRecord]) -> list[str]:
    """Override keys whose value differs between jobs, in the order the overrides list them.

    A multirun of one job, or one whose jobs share all their overrides, returns every override key.
    """
    order: list[str] = []
    for job in jobs:
        order += [k for k in job.overrides if k not in order]
    varying = [k for k in order if len({j.overrides.get(k) for j in jobs}) > 1]
    return varying or order


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def _fmt(value: float | None, digits: int = 4) -> str:
    return "–" if value is None else f"{value:.{digits}g}"


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def table_rows(
    jobs: Sequence[JobRecord], swept: Sequence[str]
) -> tuple[list[str], list[list[Any]]]:
    """The CSV header and rows: fixed columns, then every metric key found in any job."""
    metric_keys = sorted({k for j in jobs for k in j.metrics})
    header = [
        "job",
        "status",
        "reason",
        *swept,
        *CONFIG_COLUMNS,
        *MAIN_METRICS,
        "train_seconds",
        "global_step",
        *metric_keys,
    ]
    rows = []
    for j in jobs:
        config = [j.config_value(key) for key in CONFIG_COLUMNS.values()]
        rows.append(
            [
                j.name,
                j.status,
                j.reason,
                *[j.overrides.get(k, "") for k in swept],
                *["" if v is None else v for v in config],
                *["" if j.metric(c) is None else j.metric(c) for c in MAIN_METRICS],
                "" if _finite(j.extra.get("train_seconds")) is None else j.extra["train_seconds"],
                j.extra.get("global_step", ""),
                *["" if j.metrics.get(k) is None else j.metrics[k] for k in metric_keys],
            ]
        )
    return header, rows


def _csv_text(header: Sequence[Any], rows: Iterable[Sequence[Any]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()


def _md_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """The lines of a Markdown table (cells escaped)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_md_cell(str(c)) for c in row) + " |" for row in rows]
    return lines


def to_csv(jobs: Sequence[JobRecord], swept: Sequence[str]) -> str:
    return _csv_text(*table_rows(jobs, swept))


def to_markdown(
    jobs: Sequence[JobRecord],
    swept: Sequence[str],
    title: str = "",
    notes: Sequence[str] = (),
) -> str:
    """A Markdown table: a row per job with the swept values and the main metrics.

    ATE and RPE columns appear only when some job has them; failed jobs are listed below the
    table with their reasons.
    """
    has = {c: any(j.metric(c) is not None for j in jobs) for c in MAIN_METRICS}
    header = ["job", "status", *[f"`{k}`" for k in swept]]
    if has["ate"]:
        header.append("ATE (m)")
    if has["rpe_trans"]:
        header.append("RPE trans (m)")
    if has["rpe_rot"]:
        header.append("RPE rot (rad)")
    header += ["trans err (m)", "rot err (rad)", "active units (%)", "train time (s)"]
    lines = [f"# {title}", ""] if title else []
    common = _common_overrides(jobs, swept)
    if common:
        lines += ["Common overrides: " + " ".join(f"`{o}`" for o in common), ""]
    rows = []
    for j in jobs:
        cells = [j.name, "ok" if j.ok else "**failed**", *[j.overrides.get(k, "") for k in swept]]
        if has["ate"]:
            ate, std = j.metric("ate"), j.metric("ate_std")
            cells.append("–" if ate is None else f"{ate:.4f} ± {_fmt(std, 3)}")
        if has["rpe_trans"]:
            cells.append(_fmt(j.metric("rpe_trans")))
        if has["rpe_rot"]:
            cells.append(_fmt(j.metric("rpe_rot")))
        active = j.metric("active_fraction")
        seconds = _finite(j.extra.get("train_seconds"))
        cells += [
            _fmt(j.metric("trans_err")),
            _fmt(j.metric("rot_err")),
            "–" if active is None else f"{100 * active:.1f}",
            "–" if seconds is None else f"{seconds:.1f}",
        ]
        rows.append(cells)
    lines += _md_table(header, rows)
    failed = [j for j in jobs if not j.ok]
    if failed:
        lines += ["", f"Failed jobs ({len(failed)} of {len(jobs)}):", ""]
        lines += [f"- `{j.name}`: {_md_cell(j.reason)}" for j in failed]
    warned = [j for j in jobs if j.ok and j.reason]
    if warned:
        lines += ["", "Warnings:", ""] + [f"- `{j.name}`: {_md_cell(j.reason)}" for j in warned]
    if notes:
        lines += ["", *notes]
    return "\n".join(lines).rstrip() + "\n"


def _common_overrides(jobs: Sequence[JobRecord], swept: Sequence[str]) -> list[str]:
    if not jobs:
        return []
    first = jobs[0].overrides
    return [
        f"{k}={v}"
        for k, v in first.items()
        if k not in swept and all(j.overrides.get(k) == v for j in jobs)
    ]


def _optuna_note(multirun_dir: Path) -> list[str]:
    """The best trial of an Optuna sweep (``optimization_results.yaml``), as Markdown lines."""
    path = multirun_dir / "optimization_results.yaml"
    if not path.is_file():
        return []
    try:
        res = _read_yaml(path) or {}
    except (OSError, yaml.YAMLError):
        return []
    params = res.get("best_params") or {}
    value = res.get("best_value")
    if not params:
        return []
    text = ", ".join(f"`{k}={v}`" for k, v in params.items())
    return [f"Optuna best: {text} → {value}"]


# --------------------------------------------------------------------------------------------
# Across seeds
# --------------------------------------------------------------------------------------------

#: the override that names a job's seed
SEED_KEY = "seed"
#: the columns of the seed table in ``report.md``: report column, header, scale, digits
_SEED_COLUMNS = (
    ("ate", "ATE (m)", 1.0, 4),
    ("rpe_trans", "RPE trans (m)", 1.0, 4),
    ("rpe_rot", "RPE rot (rad)", 1.0, 5),
    ("trans_err", "trans err (m)", 1.0, 4),
    ("rot_err", "rot err (rad)", 1.0, 5),
    ("active_fraction", "active units (%)", 100.0, 2),
)


@dataclass
class SeedGroup:
    """Jobs of a multirun whose overrides are the same except ``seed``.

    Attributes:
        overrides: the overrides the jobs share, ``key → value`` (``seed`` left out).
        jobs: every job of the group, finished or not, in Hydra's order.
    """

    overrides: dict[str, str]
    jobs: list[JobRecord]

    @property
    def finished(self) -> list[JobRecord]:
        return [j for j in self.jobs if j.ok]

    @property
    def seeds(self) -> list[str]:
        """The seeds of the finished jobs, as their overrides write them."""
        return [j.overrides.get(SEED_KEY, "") for j in self.finished]

    def stats(self, key: str) -> tuple[float | None, float | None, int]:
        """``(mean, std, n)`` of a metric (report column or raw ``metrics.json`` key) over the
        finished seeds that have it: the sample standard deviation (ddof = 1), None below two
        values, and ``n`` the number of values."""
        if key == "train_seconds":
            found = [_finite(j.extra.get(key)) for j in self.finished]
        else:
            found = [j.metric(key) for j in self.finished]
        values = [v for v in found if v is not None]
        mean = statistics.fmean(values) if values else None
        std = statistics.stdev(values) if len(values) >= 2 else None
        return mean, std, len(values)


def seed_groups(jobs: Sequence[JobRecord], swept: Sequence[str]) -> list[SeedGroup]:
    """Group the jobs that differ only in ``seed``, in the order of their first job.

    Empty when ``seed`` is not swept (all jobs share one seed, or none is given).
    """
    if SEED_KEY not in swept or not any(SEED_KEY in j.overrides for j in jobs):
        return []
    groups: dict[tuple[tuple[str, str], ...], SeedGroup] = {}
    for j in jobs:
        shared = {k: v for k, v in j.overrides.items() if k != SEED_KEY}
        key = tuple(sorted(shared.items()))
        groups.setdefault(key, SeedGroup(shared, [])).jobs.append(j)
    return list(groups.values())


def _pm_text(mean: float | None, std: float | None, scale: float = 1.0, digits: int = 4) -> str:
    if mean is None:
        return "–"
    spread = "–" if std is None else f"{scale * std:.{digits}f}"
    return f"{scale * mean:.{digits}f} ± {spread}"


def seeds_markdown(groups: Sequence[SeedGroup], swept: Sequence[str]) -> list[str]:
    """The Markdown section of the seed table (no lines without groups)."""
    if not groups:
        return []
    keys = [k for k in swept if k != SEED_KEY]
    columns = [c for c in _SEED_COLUMNS if any(g.stats(c[0])[2] for g in groups)]
    header = [*[f"`{k}`" for k in keys], "n", "seeds", *[h for _, h, _, _ in columns]]
    rows = []
    for g in groups:
        cells = [g.overrides.get(k, "") for k in keys]
        cells += [f"{len(g.finished)} of {len(g.jobs)}", " ".join(g.seeds) or "–"]
        cells += [_pm_text(*g.stats(c)[:2], scale, digits) for c, _, scale, digits in columns]
        rows.append(cells)
    return [
        "## Across seeds",
        "",
        "Mean ± standard deviation (ddof = 1) over the finished seeds of each group of jobs that "
        "differ only in `seed`; n counts the finished seeds.",
        "",
        *_md_table(header, rows),
    ]


def seeds_csv(groups: Sequence[SeedGroup], swept: Sequence[str]) -> str:
    """``seeds.csv``: per group, the shared swept values, n, the seeds, then the mean and the
    std over seeds of the main metrics, ``train_seconds`` and every ``metrics.json`` key."""
    keys = [k for k in swept if k != SEED_KEY]
    raw = sorted({k for g in groups for j in g.finished for k in j.metrics})
    metrics = [*MAIN_METRICS, "train_seconds", *raw]
    header = [*keys, "n", "jobs", "seeds"]
    header += [f"{m} {stat}" for m in metrics for stat in ("mean", "std")]
    rows = []
    for g in groups:
        row: list[Any] = [g.overrides.get(k, "") for k in keys]
        row += [len(g.finished), len(g.jobs), " ".join(g.seeds)]
        for m in metrics:
            mean, std, _ = g.stats(m)
            row += ["" if mean is None else mean, "" if std is None else std]
        rows.append(row)
    return _csv_text(header, rows)


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------


def _group_label(job: JobRecord, keys: Sequence[str]) -> str:
    return ", ".join(f"{k.rsplit('.', 1)[-1]}={job.overrides.get(k, '')}" for k in keys) or "all"


def _error_panels(jobs: Sequence[JobRecord]) -> list[tuple[str, str | None, str]]:
    """(metric column, std column, axis label) of every error present in some finished job."""
    panels: list[tuple[str, str | None, str]] = []
    if any(j.metric("ate") is not None for j in jobs):
        panels.append(("ate", "ate_std", "ATE over 5-frame snippets (m)"))
    panels += [
        ("trans_err", None, "translation error per frame (m)"),
        ("rot_err", None, "rotation error per frame (rad)"),
    ]
    return panels


def _w_s_of(job: JobRecord) -> float | None:
    return _finite(job.config_value(W_S_KEY))


def _plot(
    jobs: Sequence[JobRecord],
    swept: Sequence[str],
    x_of: Any,
    x_key: str,
    x_label: str,
    panels: Sequence[tuple[str, str | None, str]],
    x_scale: str,
    title: str,
) -> Figure:
    """One figure of panels (metric against x), one line per value of the other swept keys."""
    from matplotlib.figure import Figure

    group_keys = [k for k in swept if k != x_key]
    groups: dict[str, list[JobRecord]] = {}
    for j in jobs:
        groups.setdefault(_group_label(j, group_keys), []).append(j)
    from matplotlib.ticker import NullFormatter

    xs_all = sorted({x for x in (x_of(j) for j in jobs) if x is not None})
    width = max(5.0, 4.2 * len(panels))
    fig = Figure(figsize=(width, 3.6), dpi=110)
    axes = fig.subplots(1, len(panels), squeeze=False)
    for ax, (column, std_column, label) in zip(axes[0], panels, strict=True):
        for name, members in groups.items():
            pts = sorted(
                (x_of(j), j.metric(column), j.metric(std_column) if std_column else None)
                for j in members
                if x_of(j) is not None and j.metric(column) is not None
            )
            if not pts:
                continue
            xs, ys, es = zip(*pts, strict=True)
            yerr = [e or 0.0 for e in es] if std_column and any(e is not None for e in es) else None
            ax.errorbar(xs, ys, yerr=yerr, marker="o", capsize=3, label=name)
        if x_scale == "symlog":
            # w_s = 0 (no sparsity loss) must stay on a log-like axis: linear below the
            # smallest positive value
            positive = [x for x in xs_all if x > 0]
            ax.set_xscale("symlog", linthresh=min(positive) if positive else 1.0)
        else:
            ax.set_xscale(x_scale)
        # ticks at the swept values, labelled plainly (no 5×10¹)
        ax.set_xticks(xs_all, [f"{x:g}" for x in xs_all], fontsize="small")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.ticklabel_format(axis="y", useOffset=False, style="plain")
        ax.set_xlabel(x_label)
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    if len(labels) > 1:
        axes[0][-1].legend(handles, labels, fontsize="small")
    fig.suptitle(title, fontsize="medium")
    fig.tight_layout()
    return fig


def figure_png(fig: Figure) -> bytes:
    """A matplotlib figure as PNG bytes (Agg canvas; no display, no pyplot state)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def draw_plots(
    jobs: Sequence[JobRecord], swept: Sequence[str]
) -> tuple[dict[str, Figure], dict[str, str]]:
    """The three plots of the sparsity study (file name → figure), and why any was not drawn.

    Only finished jobs are drawn. A plot needs at least two distinct values of its x variable.
    """
    done = [j for j in jobs if j.ok]
    images: dict[str, Figure] = {}
    skipped: dict[str, str] = {}
    top_ks = {j.top_k_percent() for j in done} - {None}
    w_ss = {_w_s_of(j) for j in done} - {None}
    panels = _error_panels(done)
    if len(top_ks) >= 2:
        images["error_vs_top_k.png"] = _plot(
            done,
            swept,
            JobRecord.top_k_percent,
            TOP_K_KEY,
            "hidden units kept at evaluation, k (%)",
            panels,
            "log",
            "error against top-k (paper §5.3, supplementary Figure 4)",
        )
    else:
        skipped["error_vs_top_k.png"] = f"top-k takes {len(top_ks)} value(s) among finished jobs"
    if len(w_ss) >= 2:
        x_label = "sparsity coefficient w_s"
        images["error_vs_w_s.png"] = _plot(
            done, swept, _w_s_of, W_S_KEY, x_label, panels, "symlog", "error against w_s"
        )
        active = [("active_fraction", None, "active hidden units per test input (fraction)")]
        images["active_fraction_vs_w_s.png"] = _plot(
            done,
            swept,
            _w_s_of,
            W_S_KEY,
            x_label,
            active,
            "symlog",
            "population sparsity against w_s (measured after top-k)",
        )
    else:
        reason = f"w_s takes {len(w_ss)} value(s) among finished jobs"
        skipped["error_vs_w_s.png"] = skipped["active_fraction_vs_w_s.png"] = reason
    return images, skipped


# --------------------------------------------------------------------------------------------
# The report
# --------------------------------------------------------------------------------------------


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
    images, skipped = draw_plots(jobs, swept)
    notes = _optuna_note(root)
    notes += [f"Plot not drawn: `{name}` ({why})." for name, why in skipped.items()]
    notes += [f"![{name}]({name})" for name in images]
    n_ok = sum(j.ok for j in jobs)
    title = f"Sweep report: {root.resolve().name} ({n_ok} of {len(jobs)} jobs finished)"
    groups = seed_groups(jobs, swept)
    seed_lines = seeds_markdown(groups, swept)
    notes = [*seed_lines, *([""] if seed_lines else []), *notes]
    markdown = to_markdown(jobs, swept, title=title, notes=notes)
    csv_path, md_path = out / "report.csv", out / "report.md"
    pngs = {name: figure_png(fig) for name, fig in images.items()}
    seeds_text = seeds_csv(groups, swept) if groups else None
    atomic_write_text(csv_path, to_csv(jobs, swept))
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
    except NotAMultirunError as err:
        print(f"report: {err}", file=sys.stderr)
        return 2
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
