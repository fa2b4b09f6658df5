"""The tables of an evaluation, built from its logged ``test/*`` metrics (:mod:`~.tables`).

Metric names as the module logs them: ``test/<metric>`` over all test sequences and
``test/<seq>/<metric>`` per sequence; ``<metric>_std`` beside a mean is its standard deviation.
Units: ATE and RPE translation in metres, RPE rotation in radians, drift in % and deg / 100 m.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mfg_lightning.tables import Column, Table, pm

__all__ = ["object_motion_table", "scoped", "sequence_table", "top_k_table"]

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


def object_motion_table(metrics: Mapping[str, float | None]) -> Table:
    """The object masks and fields of the paper's section 4 and the plain-threshold baseline."""
    table = Table([Column("method"), *(c for _, c in _OBJECT_COLUMNS)])
    for name, key in (("MFG + filters (paper §4)", "object"),
                      ("‖r‖ threshold baseline", "object_baseline")):  # fmt: skip
        table.add_row([name, *(metrics.get(f"test/{key}/{m}") for m, _ in _OBJECT_COLUMNS)])
    return table
