"""Images to egomotion trained end to end against the two-stage pipeline (stage ``end_to_end``).

At Table 2's setting (its worlds, training pairs and +1 test pairs, the 2 × 2's equal budget,
:mod:`mfg_lightning.study.settle`), per seed of ``end_to_end.seeds``:

* ``end_to_end/two_stage_seed<n>``: MFG trained on the learned flow with the network frozen
  (``flow=learned``, the shipped weights; the 2 × 2's budget and precision);
* ``end_to_end/joint_seed<n>``: that model and the shipped flow network fine-tuned together on
  MFG's loss (``experiment=end_to_end`` on the same pairs' images, ``end_to_end.overrides``) for
  ``end_to_end.steps`` more steps, tested with its own network's flow.

Both are scored as the 2 × 2's models (per-pair errors, :func:`settle.mfg_pairs`) on the same
test pairs, whose DIS and exact-flow models (``settle/<flow>_seed<n>``) are the references;
each also records its flow's quality against the exact flow by region (all pixels and the
non-occluded ones) on those pairs: the shipped network's before fine-tuning, its own after.
:func:`section` writes the report's section from these results.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from omegaconf import DictConfig

from mfg_lightning.core.tables import fmt
from mfg_lightning.study import settle as T
from mfg_lightning.study import stages as S
from mfg_lightning.study.intervals import BLOCK_PAIRS, Interval, bootstrap_se, interval
from mfg_lightning.study.render import lines, table

__all__ = ["KINDS", "REGIONS", "runs", "section", "stage_end_to_end"]

#: The two learned-flow models of a seed, in the order they train (the joint one starts from
#: the two-stage one).
KINDS = ("two_stage", "joint")
#: The regions of the flow table (the renderer's), then every pixel.
REGIONS = ("road", "structure", "moving", "far", "all")


def runs(cfg: DictConfig) -> list[tuple[str, tuple[str, int | None]]]:
    """The stage's results, ``(name, (kind, seed))``: DIS's flow quality on the test pairs (the
    flow table's reference), then both models of a seed before the next seed."""
    models = [(f"end_to_end/{k}_seed{s}", (k, int(s))) for s in cfg.end_to_end.seeds for k in KINDS]
    return [("end_to_end/dis_flow", ("dis_flow", None)), *models]


def _flow_quality(dm: Any) -> dict[str, Any] | None:
    """The test split's flow quality at +1 (``regions``: all pixels whose exact flow is known;
    ``regions_noc``: the non-occluded ones), as the dataset pools it."""
    test = dm.dataset("test")
    # None for a study whose flow is the exact one (the tiny study's): no estimate to score
    return test.quality_by_offset()["1"] if hasattr(test, "quality_by_offset") else None


def stage_end_to_end(study: S.Study, kind: str, seed: int | None) -> dict | None:
    """``end_to_end/<kind>_seed<n>`` (module docstring), or ``end_to_end/dis_flow`` (DIS's flow
    quality on the same test pairs, from the 2 × 2's cache); None (not cached) for a joint model
    whose two-stage start is not computed yet."""
    cfg = study.cfg
    if kind == "dis_flow":
        dm, test = T.test_loader(study, "dis")
        return {"test_pairs": len(test.dataset), "flow_quality": _flow_quality(dm)}
    if kind == "two_stage":
        extra = [*T.table2_extra(cfg, "learned"), f"seed={seed}"]
        trained, more = T.train_settled(study, f"e2e_two_stage_seed{seed}", extra), ()
    elif kind == "joint":
        start = study.cached(f"end_to_end/two_stage_seed{seed}")
        if start is None:
            return None
        if not study.checkpoint(start).is_file():
            study.model(start)  # a fresh clone: the two-stage model is trained again first
        steps = int(cfg.end_to_end.steps)
        # relative to the run's own directory: the result names no path of this machine
        ckpt = f"'${{paths.output_dir}}/../../{start['checkpoint']}'"
        extra = [
            *cfg.table2.overrides, *cfg.settle.overrides, *cfg.end_to_end.overrides,
            f"model.mfg_checkpoint={ckpt}", f"seed={seed}",
            f"callbacks.convergence.budget_steps={steps}",
        ]  # fmt: skip
        trained = study.train(f"e2e_joint_seed{seed}", extra, steps, cfg.end_to_end.max_time)
        more = (f"flow.weights={study.checkpoint(trained)}",)
    else:
        raise ValueError(f"end_to_end: unknown model {kind!r}; known: {', '.join(KINDS)}")
    out = T.evaluated(study, trained, "learned", seed, full=False, more=more)
    dm, _ = T.test_loader(study, "learned", more)
    return {**out, "kind": kind, "flow_quality": _flow_quality(dm)}


# --------------------------------------------------------------------------------------------
# The report's section
# --------------------------------------------------------------------------------------------

#: The rows of the comparison: label, the stage results' prefix.
MODELS = (
    ("two-stage (learned flow, network frozen)", "end_to_end/two_stage"),
    ("end to end (network and MFG fine-tuned)", "end_to_end/joint"),
    ("DIS (the 2 × 2's model)", "settle/dis"),
    ("exact flow (the 2 × 2's model, its twin)", "settle/exact"),
)
METRICS = (("ATE † (m)", "ate", 4), ("RPE translation (m)", "rpe_trans", 4),
           ("RPE rotation (rad)", "rpe_rot", 5))  # fmt: skip


def _seeds(cached: Callable[[str], dict | None], prefix: str, seeds: list[int]) -> dict[int, dict]:
    return {s: r for s in seeds if (r := cached(f"{prefix}_seed{s}")) is not None}


def _mean_log_ratio(a: np.ndarray, b: np.ndarray) -> Any:
    """The statistic of a paired resample: log(mean of ``a`` / mean of ``b``) over the pairs."""
    return lambda i: np.log(a[i].mean(1) / b[i].mean(1))


def joint_over_two_stage(runs_: Mapping[str, dict[int, dict]], key: str) -> Interval | None:
    """log(end to end's mean per-pair ``key`` error / the two-stage model's) seed by seed (the
    joint model of a seed starts from that seed's two-stage model): t over the seeds plus the
    paired block bootstrap over the test pairs. None without a seed that has both."""
    two, joint = runs_["end_to_end/two_stage"], runs_["end_to_end/joint"]
    logs, ses = [], []
    for s in sorted(set(two) & set(joint)):
        a = np.asarray(joint[s]["mfg"]["1"][key], float)
        b = np.asarray(two[s]["mfg"]["1"][key], float)
        if len(a) != len(b) or not len(a) or b.mean() <= 0:
            continue
        logs.append(math.log(a.mean() / b.mean()))
        ses.append(bootstrap_se(_mean_log_ratio(a, b), len(a), block=BLOCK_PAIRS))
    return interval(logs, ses)


def _cell(iv: Interval | None, digits: int) -> str:
    """A mean and its interval; one seed alone has none (no spread to measure)."""
    if iv is None:
        return "–"
    if not iv.terms:
        return f"{fmt(iv.value, digits)} (one seed: no interval)"
    return f"{fmt(iv.value, digits)} [{fmt(iv.lo, digits)}, {fmt(iv.hi, digits)}]"


def _ratio_cell(iv: Interval | None) -> str:
    if iv is None:
        return "–"
    return f"×{math.exp(iv.value):.3f} [×{math.exp(iv.lo):.3f}, ×{math.exp(iv.hi):.3f}]"


def _flow_rows(runs_: Mapping[str, dict[int, dict]], dis_quality: dict | None) -> list[list]:
    """EPE (px) and Fl (%) by region on the test pairs, all pixels and non-occluded: the shipped
    network (before), each joint seed's (after, their mean), DIS's (the study's cache)."""
    rows = []
    before = next(iter(runs_["end_to_end/two_stage"].values()), {}).get("flow_quality")
    after = [r["flow_quality"] for r in runs_["end_to_end/joint"].values()]
    for pixels, key in (("all", "regions"), ("noc", "regions_noc")):
        for label, qs in (("shipped network (before)", [before] if before else []),
                          (f"fine-tuned end to end (after, seeds: {len(after)})", after),
                          ("DIS", [dis_quality] if dis_quality else [])):  # fmt: skip
            if not qs or any(key not in q for q in qs):
                continue
            cells = []
            for r in REGIONS:
                for m, d in (("epe", 2), ("fl", 1)):
                    cells.append(fmt(float(np.mean([q[key][r][m] for q in qs])), d))
            rows.append([label, pixels, *cells])
    return rows


def _figure(by: Mapping[str, dict[int, dict]], seeds: list[int]) -> Any:
    """RPE rotation and translation of every model, one bar per seed (the spread the intervals
    read)."""
    from mfg_lightning.pictures.plots import bar_figure

    def series(key: str) -> dict[str, list[float | None]]:
        return {f"seed {s}": [(by[p].get(s) or {}).get("mfg", {}).get("1", {}).get("metrics",
                {}).get(key) for _, p in MODELS] for s in seeds}  # fmt: skip

    names = ["two-stage", "end to end", "DIS", "exact flow"]
    panels = [("RPE rotation (rad)", series("rpe_rot")), ("RPE translation (m)",
              series("rpe_trans"))]  # fmt: skip
    return bar_figure(panels, names, "Table 2's setting: learned flow two-stage and end to end")


def section(cached: Callable[[str], dict | None], cfg: DictConfig) -> tuple[list[str], Any]:
    """The report's end-to-end section from the stage results (``cached``: a result by name;
    empty until a joint model is computed) and its figure (None without one): the four models
    at every seed with intervals (t over the seeds), the joint model over the two-stage one
    seed by seed, and the flow's quality before and after fine-tuning."""
    seeds = [int(s) for s in cfg.end_to_end.seeds]
    by = {p: _seeds(cached, p, seeds) for _, p in MODELS}
    dis_quality = (cached("end_to_end/dis_flow") or {}).get("flow_quality")
    if not by["end_to_end/joint"]:
        return [], None
    rows = []
    for label, prefix in MODELS:
        runs_ = by[prefix]
        cells = []
        for _, key, d in METRICS:
            iv = interval([r["mfg"]["1"]["metrics"][key] for r in runs_.values()])
            cells.append(_cell(iv, d))
        rows.append([label, ", ".join(map(str, sorted(runs_))) or "–", *cells])
    heads = ["model", "seeds", *(f"{h} [95 %]" for h, _, _ in METRICS)]
    ratios = {k: joint_over_two_stage(by, k) for k in ("rot_err", "trans_err")}
    flow_heads = ["flow", "pixels", *(f"{m} {r}" for r in REGIONS for m in ("EPE", "Fl %"))]
    flows = _flow_rows(by, dis_quality)
    joint = next(iter(by["end_to_end/joint"].values()))
    two_stage = by["end_to_end/two_stage"][joint["seed"]]
    per_step = {k: float(r["train_seconds"]) / max(1, int(r["steps"]))
                for k, r in (("joint", joint), ("two_stage", two_stage))}  # fmt: skip
    text = lines(
        "report/end_to_end.md.j2", table=table(heads, rows), ratios=ratios,
        ratio_text={k: _ratio_cell(v) for k, v in ratios.items()}, joint=joint,
        two_stage=two_stage, step_seconds=per_step,
        flow_table=table(flow_heads, flows) if flows else None, by=by, cfg=cfg.end_to_end,
        quality=_quality_change(by, dis_quality),
    )  # fmt: skip
    return text, _figure(by, seeds)


def _quality_change(by: Mapping[str, dict[int, dict]], dis: dict | None) -> dict[str, Any]:
    """Per region, the EPE on the non-occluded test pixels: before, after (the joint seeds'
    mean and range) and DIS's, for the prose."""
    before = next(iter(by["end_to_end/two_stage"].values()), {}).get("flow_quality") or {}
    after = [r["flow_quality"] for r in by["end_to_end/joint"].values()]
    out = {}
    for r in REGIONS:
        try:
            b = before["regions_noc"][r]["epe"]
            a = [q["regions_noc"][r]["epe"] for q in after]
        except KeyError:
            continue
        d = dis["regions_noc"][r]["epe"] if dis and "regions_noc" in dis else None
        out[r] = {"before": b, "after": float(np.mean(a)), "lo": min(a), "hi": max(a), "dis": d}
    return out
