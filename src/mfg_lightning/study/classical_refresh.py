"""The classical methods' rows of a cached stage result, computed again without its models.

The classical baselines (:func:`mfg_lightning.analysis.scoring.classical_methods`) train
nothing, so a fix of theirs (:data:`mfg_lightning.motion.baselines.VERSION`; version 2 is the
essential matrix's cheirality test) needs only their test data: rendered again from the
stage's config, scored, and merged into the cached result. The stage's MFG rows, its models
and their numbers stay as they are; the result records the baselines' new version, the commit
and the seconds of the refresh (``classical_refresh``), so the report no longer marks it stale
(:func:`mfg_lightning.study.report.stale_essential`).

``python -m mfg_lightning.reproduce poses_dir=<poses/> 'stages=[]'
'refresh_classical=[methods,twin,table2,table2_exact]'``: a stage whose result already has
the current version is left alone.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.study import stages as S
from mfg_lightning.study.measures import coverage_bins

__all__ = ["REFRESHABLE", "refresh_classical"]


def _merged(old: list[dict], new: list[dict]) -> list[dict]:
    """``old``'s rows in their order, each classical one replaced by ``new``'s row of its
    name; a new row that ``old`` lacks goes at the end."""
    by_name = {r["name"]: r for r in new}
    rows = [by_name.pop(r["name"], r) for r in old]
    return rows + list(by_name.values())


def _methods(study: S.Study, result: dict, extra: list[str]) -> None:
    """A ``methods`` table (the central test of the main setting, ``extra`` its overrides):
    the classical rows and their coverage bins."""
    from mfg_lightning.analysis.scoring import classical_methods, score_methods, scored_rows

    central = study.test_datamodule(extra)
    ds = central.dataset("test")
    if len(ds) != result["test_pairs"]:
        raise ValueError(
            f"the test split has {len(ds)} pairs, the cached methods table "
            f"{result['test_pairs']}: the config is not the one the stage ran with"
        )
    rows = score_methods(classical_methods(ds.height, ds.width), study.loader(central, "test"))
    result["rows"] = _merged(result["rows"], scored_rows(rows))
    result["bins"] = {**result["bins"], **coverage_bins(rows, ds.samples, result["edges"])}


def _table2(study: S.Study, result: dict, exact: bool) -> None:
    """Table 2's test split (the study's flow, or the exact flow): the classical rows."""
    from mfg_lightning.analysis.scoring import classical_methods, score_methods, scored_rows

    cfg = study.cfg
    name = "table2_exact" if exact else "table2"
    extra = [*cfg.table2.overrides, *(cfg.table2.exact if exact else [])]
    dm = study.datamodule(study.train_config(name, extra), splits=("test",))
    ds = dm.dataset("test")
    if len(ds) != result["test_pairs"]:
        raise ValueError(
            f"Table 2's test split has {len(ds)} pairs, the cached {name} result "
            f"{result['test_pairs']}: the config is not the one the stage ran with"
        )
    test = list(study.loader(dm, "test", forward_only=True))
    rows = score_methods(classical_methods(ds.height, ds.width), test)
    result["classical"] = _merged(result["classical"], scored_rows(rows))


def _refreshers(study: S.Study) -> dict[str, Callable[[dict], None]]:
    main = list(study.cfg.main)
    return {
        "methods": lambda r: _methods(study, r, main),
        "twin": lambda r: _methods(study, r["methods"], [*main, *study.cfg.twin.overrides]),
        "table2": lambda r: _table2(study, r, exact=False),
        "table2_exact": lambda r: _table2(study, r, exact=True),
    }


#: The stages whose results hold classical rows computed in the stage itself.
REFRESHABLE = ("methods", "twin", "table2", "table2_exact")


def refresh_classical(study: S.Study, name: str) -> bool:
    """Compute the classical rows of the cached result ``name`` (one of :data:`REFRESHABLE`)
    again and write it back; False (nothing done) when it is not cached or already has the
    baselines' current version."""
    if name not in REFRESHABLE:
        raise ValueError(f"refresh_classical: {name!r} is not one of {', '.join(REFRESHABLE)}")
    result: dict[str, Any] | None = study.cached(name)
    if result is None or result.get("baselines_version", 1) >= S.BASELINES_VERSION:
        return False
    start = time.perf_counter()
    print(f"refreshing the classical rows of {name}", flush=True)
    _refreshers(study)[name](result)
    result["classical_refresh"] = {
        "from_version": result.get("baselines_version", 1),
        "seconds": time.perf_counter() - start,
        "commit": S.checkout_commit(),
    }
    result["baselines_version"] = S.BASELINES_VERSION
    atomic_write_text(study.path(name), json.dumps(result, indent=1) + "\n")
    print(f"refreshed: {name} ({result['classical_refresh']['seconds']:.0f} s)", flush=True)
    return True
