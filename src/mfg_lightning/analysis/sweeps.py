"""The jobs of a Hydra multirun, read back: their overrides, configs, metrics and failures.

A multirun directory (``hydra.sweep.dir``, e.g. ``outputs/train/multiruns/<date>/``) holds
``multirun.yaml`` and one directory per job (``0/``, ``1/``, … or whatever ``hydra.sweep.subdir``
names them), each with ``.hydra/overrides.yaml`` (the job's overrides, among them the swept
values), the resolved ``config.yaml`` (or Hydra's own ``.hydra/config.yaml``) and, once the job
finished, the ``metrics.json`` written by :mod:`mfg_lightning.train`.

A job without ``metrics.json``, with an unreadable one, or with a Python traceback in a log file
of its directory is ``failed`` with the reason. Jobs that differ only in ``seed`` form a
:class:`SeedGroup` (mean and sample standard deviation over the seeds). Read by
:mod:`mfg_lightning.report`, whose tables are in :mod:`mfg_lightning.analysis.result_tables` and
figures in
:mod:`mfg_lightning.pictures.plots`. Imports the standard library and PyYAML only.
"""

from __future__ import annotations

import json
import os
import re
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mfg_lightning.core.tables import finite_or_none

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
        return finite_or_none(self.metrics.get(MAIN_METRICS.get(column, column)))

    def top_k_percent(self) -> float | None:
        """Hidden units kept at evaluation in % (``model.top_k`` null means all: 100)."""
        k = self.config_value(TOP_K_KEY)
        if k is None:
            return 100.0 if self.config else None
        return finite_or_none(k) * 100.0 if finite_or_none(k) is not None else None


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
            job.metrics = {str(k): finite_or_none(v) for k, v in payload["metrics"].items()}
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


def common_overrides(jobs: Sequence[JobRecord], swept: Sequence[str]) -> list[str]:
    """The overrides every job shares, ``key=value``, but the swept keys."""
    if not jobs:
        return []
    first = jobs[0].overrides
    return [
        f"{k}={v}"
        for k, v in first.items()
        if k not in swept and all(j.overrides.get(k) == v for j in jobs)
    ]


def optuna_note(multirun_dir: Path) -> list[str]:
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


# Across seeds

#: the override that names a job's seed
SEED_KEY = "seed"


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
            found = [finite_or_none(j.extra.get(key)) for j in self.finished]
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
