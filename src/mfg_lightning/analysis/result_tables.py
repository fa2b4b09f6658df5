"""The result tables (:class:`~mfg_lightning.core.tables.Table`): of an evaluation, from its logged
``test/*`` metrics (:mod:`mfg_lightning.evaluate`), and of a multirun, from its jobs
(:mod:`mfg_lightning.analysis.sweeps`, written by :mod:`mfg_lightning.report`).

Metric names as the module logs them: ``test/<metric>`` over all test sequences and
``test/<seq>/<metric>`` per sequence; ``<metric>_std`` beside a mean is its standard deviation.
Units: ATE and RPE translation in metres, RPE rotation in radians, drift in % and deg / 100 m.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from mfg_lightning.analysis.sweeps import CONFIG_COLUMNS, MAIN_METRICS, SEED_KEY
from mfg_lightning.core.tables import Column, Table, finite_or_none, pm

if TYPE_CHECKING:
    from mfg_lightning.analysis.sweeps import JobRecord, SeedGroup

__all__ = [
    "object_motion_table",
    "pose_results_table",
    "scoped",
    "seeds_csv_table",
    "seeds_table",
    "sequence_table",
    "sweep_csv_table",
    "sweep_table",
    "top_k_table",
]

#: The object-motion scores per method: (metric key, column).
_OBJECT_COLUMNS = (
    ("iou", Column("IoU", digits=3)),
    ("precision", Column("precision", digits=3)),
    ("recall", Column("recall", digits=3)),
    ("epe", Column("EPE", "px", digits=3)),
    ("near/iou", Column("near IoU", digits=3)),
    ("far/iou", Column("far IoU", digits=3)),
    ("near/recall", Column("near recall", digits=3)),
    ("far/recall", Column("far recall", digits=3)),
)


def scoped(metrics: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """The metrics under ``prefix`` with the prefix removed (``test/09/ate`` → ``ate``)."""
    return {k[len(prefix) :]: v for k, v in metrics.items() if k.startswith(prefix)}


def _pm(metrics: Mapping[str, Any], key: str) -> str:
    """``mean ± std`` of ``key`` and ``key_std``."""
    return pm(metrics.get(key), metrics.get(f"{key}_std"))


def sequence_table(metrics: Mapping[str, float | None], sequences: list[str]) -> Table:
    """One row per test sequence, then ``all``: ATE (mean ± std and RMSE), RPE, drift."""
    table = Table([
        Column("sequence"), Column("ATE", "m"), Column("ATE RMSE", "m"),
        Column("RPE trans", "m"), Column("RPE rot", "rad", digits=5),
        Column("drift t", "%", digits=2), Column("drift r", "deg/100m", digits=2),
    ])  # fmt: skip
    for name, prefix in [(s, f"test/{s}/") for s in sequences] + [("all", "test/")]:
        m = scoped(metrics, prefix)
        table.add_row([name, _pm(m, "ate"), m.get("ate_rmse"), m.get("rpe_trans"),
                       m.get("rpe_rot"), m.get("drift_t_err"), m.get("drift_r_err")])  # fmt: skip
    return table


def top_k_table(results: Mapping[float, Mapping[str, float | None]], sequences: list[str]) -> Table:
    """The paper's Table 1 layout: one row per k (%), ATE mean ± std per sequence, then RPE."""
    table = Table([
        Column("k (%)"), *[Column(f"ATE {s}") for s in sequences], Column("ATE all"),
        Column("RPE trans", "m"), Column("RPE rot", "rad", digits=5),
    ])  # fmt: skip
    for k, m in sorted(results.items(), reverse=True):
        overall = scoped(m, "test/")
        per = [_pm(scoped(m, f"test/{s}/"), "ate") for s in sequences]
        table.add_row([f"{100 * k:g}", *per, _pm(overall, "ate"), overall.get("rpe_trans"),
                       overall.get("rpe_rot")])  # fmt: skip
    return table


def pose_results_table(
    results: Mapping[str, Mapping[str, float | int | None]], title: str
) -> Table:
    """``mfg-eval-poses``: one row per method of the flat metrics of
    :func:`mfg_lightning.metrics.pose_evaluation.summarise` (whole-trajectory ATE with its fitted
    scale, snippet ATE, RPE, KITTI drift). Each heading names its statistic (RMSE, mean, std)
    and its elements (``traj``: over poses; ``snippet``: over snippets; RPE: over pairs; the
    drift over KITTI's segments), so no two columns use one word for two things."""
    table = Table([
        Column("method"), Column("ATE traj RMSE", "m"), Column("ATE traj mean", "m"),
        Column("ATE traj std", "m"), Column("scale"), Column("ATE snippet mean", "m"),
        Column("ATE snippet std", "m"), Column("RPE trans mean", "m"),
        Column("RPE rot mean", "rad", 5), Column("t_err", "%", 2), Column("r_err", "deg/100m", 2),
    ], title=title)  # fmt: skip
    keys = ("ate_traj", "ate_traj_mean", "ate_traj_std", "ate_traj_scale", "ate", "ate_std",
            "rpe_trans", "rpe_rot", "drift_t_err", "drift_r_err")  # fmt: skip
    for name, m in results.items():
        table.add_row([name, *(m[k] for k in keys)])
    return table


def object_motion_table(metrics: Mapping[str, float | None]) -> Table:
    """The object masks and fields of the paper's section 4 and the plain-threshold baseline."""
    table = Table([Column("method"), *(c for _, c in _OBJECT_COLUMNS)])
    for name, key in (("MFG + filters (paper §4)", "object"),
                      ("‖r‖ threshold baseline", "object_baseline")):  # fmt: skip
        table.add_row([name, *(metrics.get(f"test/{key}/{m}") for m, _ in _OBJECT_COLUMNS)])
    return table


# --------------------------------------------------------------------------------------------
# The tables of a multirun (mfg_lightning.report)
# --------------------------------------------------------------------------------------------

#: The seed table's metrics in ``report.md``: (report column, column, scale).
_SEED_COLUMNS = (
    ("ate", Column("ATE", "m"), 1.0),
    ("rpe_trans", Column("RPE trans", "m"), 1.0),
    ("rpe_rot", Column("RPE rot", "rad", digits=5), 1.0),
    ("trans_err", Column("trans err", "m"), 1.0),
    ("rot_err", Column("rot err", "rad", digits=5), 1.0),
    ("active_fraction", Column("active units", "%", digits=2), 100.0),
)


def _scaled(value: float | None, scale: float) -> float | None:
    return None if value is None else scale * value


def sweep_csv_table(jobs: Sequence[JobRecord], swept: Sequence[str]) -> Table:
    """``report.csv``: a row per job: job, status, reason, the swept values, the config values
    of :data:`~mfg_lightning.analysis.sweeps.CONFIG_COLUMNS`, the main metrics, ``train_seconds``,
    ``global_step``, then every metric key found in any job (empty where a job has none)."""
    metric_keys = sorted({k for j in jobs for k in j.metrics})
    names = ["job", "status", "reason", *swept, *CONFIG_COLUMNS, *MAIN_METRICS, "train_seconds",
             "global_step", *metric_keys]  # fmt: skip
    table = Table([Column(n) for n in names])
    for j in jobs:
        table.add_row([
            j.name, j.status, j.reason, *[j.overrides.get(k, "") for k in swept],
            *[j.config_value(key) for key in CONFIG_COLUMNS.values()],
            *[j.metric(c) for c in MAIN_METRICS], finite_or_none(j.extra.get("train_seconds")),
            j.extra.get("global_step"), *[j.metrics.get(k) for k in metric_keys],
        ])  # fmt: skip
    return table


def sweep_table(jobs: Sequence[JobRecord], swept: Sequence[str]) -> Table:
    """``report.md``'s table: a row per job with the swept values and the main metrics; the ATE
    and RPE columns only when some job has them."""
    has = {c: any(j.metric(c) is not None for j in jobs) for c in MAIN_METRICS}
    optional = [
        ("ate", Column("ATE", "m")),
        ("rpe_trans", Column("RPE trans", "m")),
        ("rpe_rot", Column("RPE rot", "rad", digits=5)),
    ]
    shown = [(c, col) for c, col in optional if has[c]]
    table = Table([
        Column("job"), Column("status"), *[Column(f"`{k}`") for k in swept], *(c for _, c in shown),
        Column("trans err", "m"), Column("rot err", "rad", digits=5),
        Column("active units", "%", digits=1), Column("train time", "s", digits=1),
    ])  # fmt: skip
    for j in jobs:
        cells: list[Any] = [j.name, "ok" if j.ok else "**failed**"]
        cells += [j.overrides.get(k, "") for k in swept]
        cells += [pm(j.metric("ate"), j.metric("ate_std")) if c == "ate" else j.metric(c)
                  for c, _ in shown]  # fmt: skip
        cells += [j.metric("trans_err"), j.metric("rot_err"),
                  _scaled(j.metric("active_fraction"), 100.0),
                  finite_or_none(j.extra.get("train_seconds"))]  # fmt: skip
        table.add_row(cells)
    return table


def seeds_table(groups: Sequence[SeedGroup], swept: Sequence[str]) -> Table:
    """``report.md``'s seed table: per group of jobs that differ only in ``seed``, the shared
    swept values, the finished seeds and mean ± std (ddof = 1) over them of each metric."""
    keys = [k for k in swept if k != SEED_KEY]
    columns = [c for c in _SEED_COLUMNS if any(g.stats(c[0])[2] for g in groups)]
    table = Table([*[Column(f"`{k}`") for k in keys], Column("n"), Column("seeds"),
                   *(col for _, col, _ in columns)])  # fmt: skip
    for g in groups:
        cells: list[Any] = [g.overrides.get(k, "") for k in keys]
        cells += [f"{len(g.finished)} of {len(g.jobs)}", " ".join(g.seeds) or "–"]
        for c, col, scale in columns:
            mean, std, _ = g.stats(c)
            cells.append(pm(_scaled(mean, scale), _scaled(std, scale), col.digits))
        table.add_row(cells)
    return table


def seeds_csv_table(groups: Sequence[SeedGroup], swept: Sequence[str]) -> Table:
    """``seeds.csv``: per group, the shared swept values, n, the seeds, then the mean and the
    std over seeds of the main metrics, ``train_seconds`` and every ``metrics.json`` key."""
    keys = [k for k in swept if k != SEED_KEY]
    raw = sorted({k for g in groups for j in g.finished for k in j.metrics})
    metrics = [*MAIN_METRICS, "train_seconds", *raw]
    names = [*keys, "n", "jobs", "seeds", *[f"{m} {s}" for m in metrics for s in ("mean", "std")]]
    table = Table([Column(n) for n in names])
    for g in groups:
        row: list[Any] = [g.overrides.get(k, "") for k in keys]
        row += [len(g.finished), len(g.jobs), " ".join(g.seeds)]
        for m in metrics:
            row += list(g.stats(m)[:2])
        table.add_row(row)
    return table
