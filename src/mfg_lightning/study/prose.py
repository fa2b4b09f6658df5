"""The report's reading of the results: the findings of each paragraph computed from the stage
results (:mod:`mfg_lightning.study.findings`), and the paragraph rendered from its template
(``templates/reading/<name>.md.j2``). Every number comes from a cached stage (or from
``changes.json``, the record of changes made after a test number was seen), so rerunning a stage
rewrites the text with it; every conclusion word is computed from the number it describes.

Each ``para_*`` function returns one paragraph (Markdown, no line breaks) or None when its stages
have not run. :func:`reading` assembles them in the report's order.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from mfg_lightning.core.tables import fmt
from mfg_lightning.study import findings as F
from mfg_lightning.study.causes import classical_metrics, irls_rotation, size_points
from mfg_lightning.study.claims import PAPER_CENTRAL_OVER_FRAME
from mfg_lightning.study.config_findings import para_recipe, para_rule
from mfg_lightning.study.findings import Cached
from mfg_lightning.study.intervals import t_quantile
from mfg_lightning.study.noise import ratio, spread_of
from mfg_lightning.study.render import paragraph
from mfg_lightning.study.sentences import PRINTED_TABLE2_ROT, SEQS, Judged, Settled, View, growth
from mfg_lightning.study.sentences import test_at as at
from mfg_lightning.study.settle_report import para_settle

__all__ = ["reading"]


def _render(name: str, **findings: Any) -> str:
    return paragraph(f"reading/{name}.md.j2", **findings)


def para_run(cached: Cached, views: Mapping[int, View]) -> str | None:
    """What was trained and on what: the pairs, the main model's run and each seed's."""
    data, main = cached("data"), cached("main")
    if data is None or main is None:
        return None
    s0 = min(views, default=0)  # the main model's seed
    seeds = [(s, views[s]["trained"]) for s in sorted(views) if s != s0]
    return _render("run", data=data, main=main, s0=s0, seeds=seeds)


def para_noise(views: Mapping[int, View]) -> str | None:
    """How large the seed spread is, on the headline numbers."""
    if not views:
        return None
    val = spread_of(views, lambda v: v["table1"]["val"]["1"].get("ate"))
    t09 = spread_of(views, lambda v: at(v, 1.0, "09/ate"))
    rot = spread_of(views, lambda v: at(v, 1.0, "rpe_rot"))
    t = t_quantile(val.n - 1) if val.n >= 2 else None
    return _render("noise", val=val, t09=t09, rot=rot, t=t)


def star_bounds(rows: list[dict]) -> dict[str, tuple[float, float]]:
    """The classical methods' lowest and highest ATE * / ATE † per test sequence."""
    out = {}
    for s in SEQS:
        rs = [ratio(m.get(f"{s}/ate_central"), m.get(f"{s}/ate")) for m in
              classical_metrics(rows).values()]  # fmt: skip
        if rs := [r for r in rs if r is not None]:
            out[s] = (min(rs), max(rs))
    return out


def _offset_ratio(flow: dict, far: int) -> float | None:
    """The test pairs' pixel-pooled EPE at offsets ±``far`` over that at ±1."""

    def pooled(offsets: tuple[int, ...]) -> float | None:
        qs = [flow["test"][str(o)]["regions"]["all"] for o in offsets if str(o) in flow["test"]]
        px = sum(q["pixels"] for q in qs)
        return sum(q["epe"] * q["pixels"] for q in qs) / px if px else None

    return ratio(pooled((-far, far)), pooled((-1, 1)))


def central(cached: Cached, views: Mapping[int, View]) -> F.Central | None:
    """ATE * / ATE † (:class:`~mfg_lightning.study.findings.Central`)."""
    mt = cached("methods")
    if mt is None or not views:
        return None
    ours = {s: spread_of(views, lambda v, s=s: ratio(at(v, 1.0, f"{s}/ate_central"),
                                                     at(v, 1.0, f"{s}/ate"))).mean
            for s in SEQS}  # fmt: skip
    f = F.Central(ours, dict(PAPER_CENTRAL_OVER_FRAME), star_bounds(mt["rows"]))
    if (flow := cached("flow_error")) is not None:
        test = sorted(flow["test"].items(), key=lambda kv: int(kv[0]))
        f.epe = [(int(o), e["regions"]["all"]["epe"], e["regions"]["all"]["fl"]) for o, e in test]
        f.far_ratio = _offset_ratio(flow, 2)
    return f


def para_central(cached: Cached, views: Mapping[int, View]) -> str | None:
    """ATE * / ATE †: MFG's against the classical methods' on the same flow."""
    f = central(cached, views)
    return None if f is None else _render("central", f=f)


def para_twin(cached: Cached, views: Mapping[int, View]) -> str | None:
    """ATE * / ATE † separated: the exact-flow twin on exact and on DIS flow, the classical
    methods on both flows."""
    twin = cached("twin")
    if twin is None:
        return None

    def star(m: Mapping[str, Any]) -> str:
        return " / ".join(
            f"×{fmt(ratio(m.get(f'{s}/ate_central'), m.get(f'{s}/ate')), 2)}" for s in SEQS
        )

    mt = cached("methods")
    ranges = {"exact": F.star_ranges(star_bounds(twin["methods"]["rows"])),
              "dis": F.star_ranges(star_bounds(mt["rows"])) if mt is not None else []}  # fmt: skip
    return _render("twin", exact=twin["table1"]["test"]["1"], dis=twin["dis_test"], star=star,
                   paper=PAPER_CENTRAL_OVER_FRAME, ranges=ranges)  # fmt: skip


def size_curve(size: Mapping[str, dict]) -> F.SizeCurve | None:
    """The size curve (:class:`~mfg_lightning.study.findings.SizeCurve`), None before a point."""
    points = size_points(size)
    if not points:
        return None
    irls = irls_rotation(cl["classical"]) if (cl := size.get("classical")) is not None else None
    spreads = [
        (int(runs[0]["train_pairs"]),
         spread_of(dict(enumerate(runs)), lambda r: r["test"].get("rpe_rot")))
        for runs in points.values()
    ]  # fmt: skip
    return F.SizeCurve(spreads, irls)


def para_size(size: Mapping[str, dict]) -> str | None:
    """MFG's rotation against the training set's size, beside the robust continuous method."""
    f = size_curve(size)
    return None if f is None else _render("size", f=f)


def flow_gain(exact: dict, dis: dict) -> F.FlowGain:
    """What the exact flow changes for each side (:class:`~mfg_lightning.study.findings.
    FlowGain`)."""
    rot = [r["mfg"]["1"].get("rpe_rot") for r in (exact, dis)]
    return F.FlowGain(*rot, irls_rotation(exact["classical"]), irls_rotation(dis["classical"]))


def table2_contrast(cached: Cached, views: Mapping[int, View]) -> F.Table2Contrast | None:
    """The full split against the classical methods, beside the small set's ratio over IRLS."""
    mt, t2 = cached("methods"), cached("table2")
    if mt is None or not views:
        return None
    full = spread_of(views, lambda v: at(v, 1.0, "rpe_rot"))
    classical = {n: m.get("rpe_rot") for n, m in classical_metrics(mt["rows"]).items()}
    best = min((v for v in classical.values() if v is not None), default=None)
    small = None if t2 is None else ratio(t2["mfg"]["1"].get("rpe_rot"),
                                          irls_rotation(t2["classical"]))  # fmt: skip
    return F.Table2Contrast(full, irls_rotation(mt["rows"]), best, small)


def para_table2(cached: Cached, views: Mapping[int, View]) -> str | None:
    """Rotation against the classical methods: the first Table-2-sized runs (one seed each, the
    rule) on exact flow (the paper's protocol) and on DIS, and the full split."""
    t2, exact = cached("table2"), cached("table2_exact")
    if t2 is None and exact is None:
        return None
    runs = [{"flow": f, "steps": r["steps"], "mfg": r["mfg"]["1"].get("rpe_rot"),
             "irls": irls_rotation(r["classical"])}
            for r, f in ((exact, "exact"), (t2, "DIS")) if r is not None]  # fmt: skip
    c = table2_contrast(cached, views)
    return _render(
        "table2", runs=runs, pairs=(exact or t2)["train_pairs"], printed=PRINTED_TABLE2_ROT,
        g=flow_gain(exact, t2) if exact is not None and t2 is not None else None, c=c,
        main_pairs=cached("data")["main"]["train_pairs"] if c is not None else None,
    )  # fmt: skip


def robustness(cached: Cached, views: Mapping[int, View]) -> F.Robustness | None:
    """Errors against moving-object coverage (:class:`~mfg_lightning.study.findings.
    Robustness`)."""
    mt = cached("methods")
    if mt is None or not views:
        return None
    bins = mt["bins"]
    return F.Robustness(
        mt["edges"], mt["counts"],
        spread_of(views, lambda v: growth(v, "rot_bins")).mean,
        spread_of(views, lambda v: growth(v, "trans_bins")).mean,
        {n: b["growth"] for n, b in bins.items() if not n.startswith("MFG") and "oracle" not in n},
        [b["growth"] for n, b in bins.items() if n.startswith("essential")],
    )  # fmt: skip


def para_robustness(cached: Cached, views: Mapping[int, View]) -> str | None:
    """Errors against moving-object coverage: MFG's growth beside the classical methods'."""
    f = robustness(cached, views)
    return None if f is None else _render("robustness", f=f)


def _first_seed(views: Mapping[int, View], key: str) -> Any:
    """The first seed's (the main model's) result ``key``, None when not measured."""
    return views[min(views)].get(key) if views else None


def para_basis(views: Mapping[int, View], residual: float) -> str | None:
    """The rotational decoder's silent units."""
    bs = _first_seed(views, "basis")
    if bs is None:
        return None
    d = bs["per_decoder"]["omega"]
    fired = [r for r, f in zip(d["residual"], d["firing_rate"], strict=True) if f > 0]
    silent = [r for r, f in zip(d["residual"], d["firing_rate"], strict=True) if f <= 0]
    median = sorted(silent)[len(silent) // 2] if silent else None
    return _render("basis", seed=min(views), bs=bs, d=d, fired=fired, silent=silent,
                   median=median, fits=sum(r <= residual for r in fired))  # fmt: skip


def para_object_motion(
    views: Mapping[int, View], theta_d: float, twin: dict | None = None
) -> str | None:
    """The two sides' treatment in the object-mask comparison: the exact-flow ``twin``'s masks
    when it has run (the paper's protocol), else the main model's."""
    use_twin = bool(twin and twin.get("object_motion"))
    om = twin["object_motion"] if use_twin else _first_seed(views, "object_motion")  # type: ignore[index]
    if om is None:
        return None
    om = om["exact"]
    return _render("object_motion", om=om, choice=om.get("filters_choice"), theta_d=theta_d,
                   twin=use_twin)  # fmt: skip


def para_changes(cached: Cached) -> str | None:
    """The changes made after a test number was seen (``changes.json``)."""
    ch = cached("changes")
    return _render("changes", changes=ch.get("changes", [])) if ch else None


def para_verdicts(judged: list[Judged]) -> str | None:
    """One sentence counting the verdicts."""
    return _render("verdicts", by=F.verdict_count(judged)) if judged else None


def reading(
    cached: Cached,
    views: Mapping[int, View],
    judged: list[Judged],
    residual: float,
    theta_d: float,
    scale_text: str,
    size: Mapping[str, dict] | None = None,
    settled: Settled | None = None,
    data: Sequence[str] = (),
) -> list[str]:
    """The generated reading, as Markdown lines (a blank line between paragraphs); ``size``:
    the size curve's results by name (:func:`mfg_lightning.study.causes.size_section`);
    ``settled``: the 2 × 2's results (:mod:`mfg_lightning.study.settle_report`); ``data``: the
    study's data overrides (the training sequences a run without its own has)."""
    paras = [
        para_run(cached, views),
        para_noise(views),
        para_verdicts(judged),
        para_central(cached, views),
        para_twin(cached, views),
        para_table2(cached, views),
        para_settle(settled, data) if settled is not None else None,
        para_size(size or {}),
        para_robustness(cached, views),
        para_basis(views, residual),
        para_object_motion(views, theta_d, cached("twin")),
        scale_text or None,
        para_rule(cached),
        para_recipe(cached),
        para_changes(cached),
    ]
    return [line for p in paras if p for line in (p, "")]
