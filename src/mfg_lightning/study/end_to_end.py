"""Images to egomotion trained end to end against the two-stage pipeline (stage ``end_to_end``).

At Table 2's setting (its worlds, training pairs and +1 test pairs, the 2 × 2's equal budget,
:mod:`mfg_lightning.study.settle`), per seed of ``end_to_end.seeds``:

* ``end_to_end/two_stage_seed<n>``: MFG trained on the learned flow with the network frozen
  (``flow=learned``, the shipped weights; the 2 × 2's budget and precision);
* ``end_to_end/joint_seed<n>``: that model and the shipped flow network fine-tuned together on
  MFG's loss (``experiment=end_to_end`` on the same pairs' images, ``end_to_end.overrides``) for
  ``end_to_end.steps`` more steps, tested with its own network's flow;
* ``end_to_end/frozen_seed<n>``: the control of those extra steps, the same fine-tuning with the
  network frozen throughout (``model.freeze_flow_steps`` = the steps): what the end-to-end
  model gains over it is the network's training, not the steps, rate or batch.

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
from mfg_lightning.study.intervals import BLOCK_PAIRS, FLOORS, Interval, bootstrap_se, interval
from mfg_lightning.study.render import lines, table

__all__ = ["KINDS", "REGIONS", "paired_ratio", "runs", "section", "stage_end_to_end"]

#: The learned-flow models of a seed, in the order they train (the joint one and its frozen
#: control start from the two-stage one).
KINDS = ("two_stage", "joint", "frozen")
#: The regions of the flow table (the renderer's), then every pixel.
REGIONS = ("road", "structure", "moving", "far", "all")


def runs(cfg: DictConfig) -> list[tuple[str, tuple[str, int | None]]]:
    """The stage's results, ``(name, (kind, seed))``: DIS's flow quality on the test pairs (the
    flow table's reference), then the two-stage and the end-to-end model of a seed before the
    next seed, then the controls (the comparison the issue asks for comes first)."""
    seeds = [int(s) for s in cfg.end_to_end.seeds]
    two_stage, joint, frozen = KINDS
    models = [(f"end_to_end/{k}_seed{s}", (k, s)) for s in seeds for k in (two_stage, joint)]
    controls = [(f"end_to_end/{frozen}_seed{s}", (frozen, s)) for s in seeds]
    return [("end_to_end/dis_flow", ("dis_flow", None)), *models, *controls]


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
    elif kind in ("joint", "frozen"):
        start = study.cached(f"end_to_end/two_stage_seed{seed}")
        if start is None:
            return None
        if not study.checkpoint(start).is_file():
            # a fresh clone: the two-stage model is trained again first (the same config, seed
            # and recorded kernels give the same model on the same kind of machine)
            study.model(start)
        steps = int(cfg.end_to_end.steps)
        # relative to the run's own directory: the result names no path of this machine
        ckpt = f"'${{paths.output_dir}}/../../{start['checkpoint']}'"
        extra = [
            *cfg.table2.overrides, *cfg.settle.overrides, *cfg.end_to_end.overrides,
            f"model.mfg_checkpoint={ckpt}", f"seed={seed}",
            f"callbacks.convergence.budget_steps={steps}",
            *([f"model.freeze_flow_steps={steps}"] if kind == "frozen" else []),
        ]  # fmt: skip
        name = f"e2e_{kind}_seed{seed}"
        trained = study.train(name, extra, steps, cfg.end_to_end.max_time)
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
    ("control: the same extra steps, network frozen", "end_to_end/frozen"),
    ("DIS (the 2 × 2's model)", "settle/dis"),
    ("exact flow (the 2 × 2's model, its twin)", "settle/exact"),
)
METRICS = (("ATE † (m)", "ate", 4), ("RPE translation (m)", "rpe_trans", 4),
           ("RPE rotation (rad)", "rpe_rot", 5))  # fmt: skip
#: The per-pair errors of the paired ratios, and the floor below which a mean error is no
#: denominator (:data:`mfg_lightning.study.intervals.FLOORS`).
ERRORS = {"rot_err": "rotation", "trans_err": "translation"}


def _seeds(cached: Callable[[str], dict | None], prefix: str, seeds: list[int]) -> dict[int, dict]:
    """The results of ``prefix`` at ``seeds`` that are computed, by seed."""
    return {s: r for s in seeds if (r := cached(f"{prefix}_seed{s}")) is not None}


def _mean_log_ratio(a: np.ndarray, b: np.ndarray) -> Any:
    """The statistic of a paired resample: log(mean of ``a`` / mean of ``b``) over the pairs."""
    return lambda i: np.log(a[i].mean(1) / b[i].mean(1))


def paired_ratio(num: Mapping[int, dict], den: Mapping[int, dict], key: str) -> Interval | None:
    """log(``num``'s mean per-pair ``key`` error / ``den``'s) seed by seed (the models of a seed
    share their start and test pairs): t over the seeds plus the paired block bootstrap over the
    test pairs. None without a seed that has both above the error's floor.

    Raises:
        ValueError: a seed's two results hold different numbers of test pairs (not paired).
    """
    logs, ses = [], []
    for s in sorted(set(num) & set(den)):
        a = np.asarray(num[s]["mfg"]["1"][key], float)
        b = np.asarray(den[s]["mfg"]["1"][key], float)
        if len(a) != len(b):
            raise ValueError(f"end_to_end, seed {s}: {len(a)} and {len(b)} test pairs of {key}: "
                             "the two models were not tested on the same pairs")  # fmt: skip
        if not len(a) or min(a.mean(), b.mean()) < FLOORS[ERRORS[key]]:
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
    """A paired ratio as the report prints it (× the value [× its interval])."""
    if iv is None:
        return "not measured"
    v, lo, hi = math.exp(iv.value), math.exp(iv.lo), math.exp(iv.hi)
    if not iv.terms:
        return f"×{v:.3f} (no spread measured: no interval)"
    # enough digits that the printed interval shows which side of ×1 it is on
    d = 3
    while d < 7 and (
        f"{lo:.{d}f}" == f"{hi:.{d}f}" or f"{1:.{d}f}" in (f"{lo:.{d}f}", f"{hi:.{d}f}")
    ):
        d += 1
    return f"×{v:.{d}f} [×{lo:.{d}f}, ×{hi:.{d}f}]"


def _quality(r: dict) -> dict | None:
    """A result's flow quality (None where not recorded)."""
    q = r.get("flow_quality")
    return q if isinstance(q, dict) and "regions" in q else None


def _flow_rows(by: Mapping[str, dict[int, dict]], dis_quality: dict | None) -> list[list]:
    """EPE (px) and Fl (%) by region on the test pairs, all pixels and non-occluded: the shipped
    network (before), the joint seeds' networks (after, their mean), DIS's (the 2 × 2's)."""
    befores = [q for r in by["end_to_end/two_stage"].values() if (q := _quality(r))]
    after = [q for r in by["end_to_end/joint"].values() if (q := _quality(r))]
    rows = []
    for pixels, key in (("all", "regions"), ("noc", "regions_noc")):
        for label, qs in (("shipped network (before)", befores[:1]),
                          (f"fine-tuned end to end (after, seeds: {len(after)})", after),
                          ("DIS", [dis_quality] if dis_quality else [])):  # fmt: skip
            if not qs or any(key not in q for q in qs):
                continue
            cells = [fmt(float(np.mean([q[key][r][m] for q in qs])), d)
                     for r in REGIONS for m, d in (("epe", 2), ("fl", 1))]  # fmt: skip
            rows.append([label, pixels, *cells])
    return rows


def _quality_change(by: Mapping[str, dict[int, dict]], dis: dict | None) -> dict[str, Any]:
    """Per region, the EPE on the non-occluded test pixels: before, after (the joint seeds'
    mean, smallest and largest, their number) and DIS's (None: not computed), for the prose."""
    before = next((q for r in by["end_to_end/two_stage"].values() if (q := _quality(r))), None)
    after = [q for r in by["end_to_end/joint"].values() if (q := _quality(r))]
    out: dict[str, Any] = {}
    if before is None or not after or any("regions_noc" not in q for q in (before, *after)):
        return out
    for r in REGIONS:
        a = [q["regions_noc"][r]["epe"] for q in after]
        d = dis["regions_noc"][r]["epe"] if dis and "regions_noc" in dis else None
        out[r] = {"before": before["regions_noc"][r]["epe"], "after": float(np.mean(a)),
                  "lo": min(a), "hi": max(a), "n": len(a), "dis": d}  # fmt: skip
    return out


def _figure(by: Mapping[str, dict[int, dict]], seeds: list[int]) -> Any:
    """RPE rotation and translation of every model, one bar per seed (the spread the intervals
    read)."""
    from mfg_lightning.pictures.plots import bar_figure

    def series(key: str) -> dict[str, list[float | None]]:
        return {f"seed {s}": [(by[p].get(s) or {}).get("mfg", {}).get("1", {}).get("metrics",
                {}).get(key) for _, p in MODELS] for s in seeds}  # fmt: skip

    names = ["two-stage", "end to end", "control", "DIS", "exact flow"]
    panels = [("RPE rotation (rad)", series("rpe_rot")), ("RPE translation (m)",
              series("rpe_trans"))]  # fmt: skip
    return bar_figure(panels, names, "Table 2's setting: learned flow two-stage and end to end")


def section(cached: Callable[[str], dict | None], cfg: DictConfig) -> tuple[list[str], Any]:
    """The report's end-to-end section from the stage results (``cached``: a result by name;
    empty until a joint model is computed) and its figure (None without one): the models at
    the seeds that have a joint model, with intervals (t over the seeds), the joint model over
    its control and over its two-stage start seed by seed, and the flow's quality before and
    after fine-tuning."""
    joint = _seeds(cached, "end_to_end/joint", [int(s) for s in cfg.end_to_end.seeds])
    seeds = sorted(joint)
    # every row at the joint models' seeds: the intervals then compare like with like
    by = {p: _seeds(cached, p, seeds) for _, p in MODELS}
    if not seeds:
        return [], None
    dis_quality = _quality(cached("end_to_end/dis_flow") or {})
    rows = []
    for label, prefix in MODELS:
        runs_ = by[prefix]
        cells = [_cell(interval([r["mfg"]["1"]["metrics"][key] for r in runs_.values()]), d)
                 for _, key, d in METRICS]  # fmt: skip
        rows.append([label, ", ".join(map(str, sorted(runs_))) or "–", *cells])
    heads = ["model", "seeds", *(f"{h} [95 %]" for h, _, _ in METRICS)]
    over = {
        den: {k: paired_ratio(by["end_to_end/joint"], by[f"end_to_end/{den}"], k) for k in ERRORS}
        for den in ("frozen", "two_stage")
    }
    flows = _flow_rows(by, dis_quality)
    first = joint[seeds[0]]
    two_stage = by["end_to_end/two_stage"].get(seeds[0])
    per_step = {k: float(r["train_seconds"]) / max(1, int(r["steps"]))
                for k, r in (("joint", first), ("two_stage", two_stage)) if r}  # fmt: skip
    flow_heads = ["flow", "pixels", *(f"{m} {r}" for r in REGIONS for m in ("EPE", "Fl %"))]
    text = lines(
        "report/end_to_end.md.j2", table=table(heads, rows), over=over, joint=first,
        two_stage=two_stage, step_seconds=per_step, seeds=seeds, has_dis=dis_quality is not None,
        ratio_text={d: {k: _ratio_cell(v) for k, v in o.items()} for d, o in over.items()},
        flow_table=table(flow_heads, flows) if flows else None,
        quality=_quality_change(by, dis_quality),
    )  # fmt: skip
    return text, _figure(by, seeds)
