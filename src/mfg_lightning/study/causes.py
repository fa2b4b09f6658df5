"""The causes separated, beside the verdicts: the flow against the method (the main model's
exact-flow twin, stage ``twin``), the paper's protocol against ours (Table 2 on exact flow,
stage ``table2_exact``, against DIS, stage ``table2``) and the training set's size (stages
``size/*``). Each section is a table and, where a picture says more, a figure; nothing here
is a verdict (:mod:`mfg_lightning.study.sentences` judges)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from mfg_lightning.core.tables import fmt
from mfg_lightning.study.claims import PAPER_CENTRAL_OVER_FRAME
from mfg_lightning.study.findings import LearnedFlow
from mfg_lightning.study.noise import ratio, spread_of
from mfg_lightning.study.render import lines, table
from mfg_lightning.study.sentences import IRLS, PRINTED_TABLE2_ROT, SEQS

Lines = list[str]
Metrics = Mapping[str, float]


def classical_metrics(rows: list[dict]) -> dict[str, Metrics]:
    """The classical methods' metrics by name (the oracle is a check, not a method)."""
    return {
        r["name"]: r["metrics"]
        for r in rows
        if "oracle" not in r["name"] and not r["name"].startswith("MFG")
    }


def irls_rotation(rows: list[dict]) -> float | None:
    """The robust continuous method's (IRLS's) RPE rotation (rad) among the classical ``rows``."""
    return next((m.get("rpe_rot") for n, m in classical_metrics(rows).items() if IRLS in n), None)


#: Short names for the figure's axis.
SHORT = {"essential matrix + RANSAC": "RANSAC", "essential matrix + MAGSAC++": "MAGSAC++",
         "continuous least squares": "least squares", "continuous LS + IRLS": "IRLS",
         "MFG, main model": "MFG main (DIS-trained)",
         "MFG, exact-flow twin": "MFG twin (exact-trained)"}  # fmt: skip


def _short(label: str) -> str:
    return next((v for k, v in SHORT.items() if label.startswith(k)), label)


def _main_seeds(views: Mapping[int, Any]) -> tuple[dict, str, Callable[[str], float | None]]:
    """The main model's seeds (the views with ``table1``), their row's label and their mean of a
    test metric (all units)."""
    main = {s: v for s, v in views.items() if v.get("table1")}

    def seeds_mean(key: str) -> float | None:
        return spread_of(main, lambda v: v["table1"]["test"]["1"].get(key)).mean

    return main, f"MFG, main model ({len(main)} seed{'s' * (len(main) > 1)})", seeds_mean


def _twin_rows(views: Mapping[int, Any], twin: dict, methods: dict | None) -> list[tuple]:
    """(label, flow trained on, flow tested on, metrics or per-key mean over seeds)."""
    main, label, seeds_mean = _main_seeds(views)
    rows = [(label, "DIS", "DIS", seeds_mean)] if main else []
    exact = twin["table1"]["test"]["1"]
    rows.append(("MFG, exact-flow twin", "exact", "exact", exact.get))
    rows.append(("MFG, exact-flow twin", "exact", "DIS", twin["dis_test"].get))
    dis_rows = classical_metrics(methods["rows"]) if methods else {}
    for name, m in classical_metrics(twin["methods"]["rows"]).items():
        if name in dis_rows:
            rows.append((name, "–", "DIS", dis_rows[name].get))
        rows.append((name, "–", "exact", m.get))
    return rows


def twin_section(
    views: Mapping[int, Any], twin: dict | None, methods: dict | None
) -> tuple[Lines, Any]:
    """The exact-flow twin against the main model, and every classical method on exact and on
    DIS flow: ATE † and ATE * per test sequence and their ratio, RPE rotation; a figure of the
    ratios. Nothing before the stage has run."""
    from mfg_lightning.pictures.plots import bar_figure

    if twin is None:
        return [], None
    rows = _twin_rows(views, twin, methods)
    table_rows = []
    for label, trained, tested, get in rows:
        cells = [label, trained, tested]
        for s in SEQS:
            dagger, star = get(f"{s}/ate"), get(f"{s}/ate_central")
            cells += [fmt(dagger, 4), fmt(star, 4), fmt(ratio(star, dagger), 2)]
        table_rows.append([*cells, fmt(get("rpe_rot"), 5)])
    heads = ["method", "trained on", "tested on"]
    for s in SEQS:
        heads += [f"ATE † {s} (m)", f"ATE * {s} (m)", f"* / † {s}"]
    # one bar group per method, one colour per test flow: the flow's part is the step between
    # a method's two bars, the method's its exact bar
    names = list(dict.fromkeys(_short(lab) for lab, _, _, _ in rows))
    panels = []
    for s in SEQS:
        series = {f"{f} test flow": [None] * len(names) for f in ("exact", "DIS")}
        for lab, _, tested, get in rows:
            value = ratio(get(f"{s}/ate_central"), get(f"{s}/ate"))
            series[f"{tested} test flow"][names.index(_short(lab))] = value
        panels.append((f"ATE * / ATE † ({s})", series))
    title = "ATE * / ATE †: the method (exact flow) and the flow (DIS)"
    refs = [("the paper's MFG", PAPER_CENTRAL_OVER_FRAME[s]) for s in SEQS]
    fig = bar_figure(panels, names, title, references=refs)
    table_md = table([*heads, "RPE rotation (rad)"], table_rows)
    return lines("report/twin.md.j2", twin=twin, methods=methods, table=table_md), fig


def _test_epe(flow_error: dict | None, offset: str = "1", region: str = "all") -> float | None:
    """The EPE (px) at ``offset`` over ``region``'s pixels of a ``flow_error``-shaped result's
    test pairs."""
    try:
        return flow_error["test"][offset]["regions"][region]["epe"]  # type: ignore[index]
    except (KeyError, TypeError):
        return None


def learned_section(
    views: Mapping[int, Any],
    twin: dict | None,
    learned: dict | None,
    study_flow: dict | None,
    flow_name: str = "DIS",
) -> Lines:
    """The main setting on the learned flow (stage ``learned``) beside the main model on the
    study's flow (``flow_name``, with its error ``study_flow``: stage ``flow_error``) and the
    exact-flow twin, on the same central test pairs: ATE † and ATE * per test sequence, RPE
    rotation, and the test flow's EPE at +1 and +2. Nothing before the stage has run."""
    if learned is None:
        return []
    main, label, seeds_mean = _main_seeds(views)
    rows = [(label, flow_name, flow_name, seeds_mean, study_flow)] if main else []
    if twin is not None:
        exact = {region: {"epe": 0.0} for region in ("all", "road", "far")}
        fe = {"test": {o: {"regions": exact} for o in ("1", "2")}}
        rows.append(("MFG, exact-flow twin", "exact", "exact", twin["table1"]["test"]["1"].get, fe))
    ours, fe = learned["table1"]["test"]["1"].get, learned.get("flow_error")
    rows.append(("MFG on the learned flow", "learned", "learned", ours, fe))
    rows.append(("MFG on the learned flow", "learned", flow_name, learned["dis_test"].get,
                 study_flow))  # fmt: skip
    table_rows = []
    for label, trained, tested, get, fe in rows:
        cells = [label, trained, tested, fmt(_test_epe(fe, "1"), 2), fmt(_test_epe(fe, "2"), 2),
                 fmt(_test_epe(fe, "1", "road"), 2), fmt(_test_epe(fe, "1", "far"), 2)]  # fmt: skip
        for s in SEQS:
            dagger, star = get(f"{s}/ate"), get(f"{s}/ate_central")
            cells += [fmt(dagger, 4), fmt(star, 4)]
        table_rows.append([*cells, fmt(get("rpe_trans"), 4), fmt(get("rpe_rot"), 5)])
    heads = ["model", "trained on", "tested on", "test flow EPE +1 (px)", "EPE +2 (px)",
             "EPE +1 road (px)", "EPE +1 far (px)"]  # fmt: skip
    for s in SEQS:
        heads += [f"ATE † {s} (m)", f"ATE * {s} (m)"]
    table_md = table([*heads, "RPE translation (m)", "RPE rotation (rad)"], table_rows)
    f = _against_seed_range(main, learned["table1"]["test"]["1"])
    f.epe = {r: (_test_epe(learned.get("flow_error"), "1", r), _test_epe(study_flow, "1", r))
             for r in ("all", "road", "far")}  # fmt: skip
    return lines("report/learned.md.j2", learned=learned, flow=flow_name, table=table_md, f=f,
                 n=len(main), seed=learned.get("seed"))  # fmt: skip


def _against_seed_range(main: Mapping[int, Any], learned: Mapping[str, Any]) -> LearnedFlow:
    """Where the one learned-flow model's test scores fall against the range of the main
    model's seeds (a single training beside a seed mean needs the spread to be read; none with
    fewer than two main seeds)."""
    keys = [*(f"{s}/{m}" for s in SEQS for m in ("ate", "ate_central")), "rpe_trans", "rpe_rot"]
    names = {"ate": "ATE †", "ate_central": "ATE *", "rpe_trans": "RPE translation",
             "rpe_rot": "RPE rotation"}  # fmt: skip
    scores = {}
    for key in keys:
        spread = spread_of(main, lambda v, key=key: v["table1"]["test"]["1"].get(key))
        if spread.n >= 2 and (value := learned.get(key)) is not None:
            seq, _, metric = key.rpartition("/")
            label, d = f"{names[metric]} {seq}".strip(), 5 if metric == "rpe_rot" else 4
            scores[label] = (value, min(spread.values), max(spread.values), d)
    return LearnedFlow(scores, {})


def _t2_row(label: str, t2: dict) -> list[list[str]]:
    """MFG (all units, k = 15 %) and IRLS and the best classical method of one Table 2 run."""
    classical = classical_metrics(t2["classical"])
    rot = {n: m.get("rpe_rot") for n, m in classical.items()}
    best = min(rot, key=lambda n: rot[n] if rot[n] is not None else math.inf, default=None)
    irls = next((n for n in rot if IRLS in n), None)
    mfg, k15 = t2["mfg"]["1"], t2["mfg"].get("0.15", {})
    out = [
        [label, "MFG (all units)", fmt(mfg.get("rpe_rot"), 5), fmt(mfg.get("rpe_trans"), 4)],
        [label, "MFG (k = 15 %)", fmt(k15.get("rpe_rot"), 5), fmt(k15.get("rpe_trans"), 4)],
    ]
    for name in dict.fromkeys(n for n in (irls, best) if n):
        m = classical[name]
        tag = " (best in rotation)" if name == best else ""
        out.append([label, name + tag, fmt(m.get("rpe_rot"), 5), fmt(m.get("rpe_trans"), 4)])
    if irls:
        out.append(
            [label, "MFG / IRLS, rotation", fmt(ratio(mfg.get("rpe_rot"), rot[irls]), 2), ""]
        )
    return out


def table2_flow_section(exact: dict | None, dis: dict | None) -> Lines:
    """Table 2's setting on the exact flow (the paper's protocol) beside DIS (the extension)."""
    runs = [(lab, r) for lab, r in (("exact flow (the paper's)", exact), ("DIS", dis)) if r]
    if not exact:
        return []
    rows = [row for lab, r in runs for row in _t2_row(lab, r)]
    heads = ("flow", "method", "RPE rotation (rad)", "RPE translation (m)")
    return lines("report/table2_flows.md.j2", exact=exact, dis=dis, printed=PRINTED_TABLE2_ROT,
                 table=table(heads, rows))  # fmt: skip


def size_points(size: Mapping[str, dict]) -> dict[int, list[dict]]:
    """The size curve's results by stride (largest first), each stride's seeds in a list."""
    by: dict[int, list[dict]] = {}
    for r in size.values():
        if "stride" in r:
            by.setdefault(int(r["stride"]), []).append(r)
    return dict(sorted(by.items(), reverse=True))


def size_section(size: Mapping[str, dict]) -> tuple[Lines, Any]:
    """MFG's RPE rotation (and translation) against the training set's size, the seeds' spread
    where there are several, beside the classical methods on the same test pairs."""
    from mfg_lightning.pictures.plots import line_figure

    points = size_points(size)
    if not points:
        return [], None
    classical = classical_metrics(size["classical"]["classical"]) if "classical" in size else {}
    rows, xs, sps = [], [], []
    for stride, runs in points.items():
        sp = {k: spread_of(dict(enumerate(runs)), lambda r, k=k: r["test"].get(k))
              for k in ("rpe_rot", "rpe_trans")}  # fmt: skip
        conv = sum(bool((r.get("convergence") or {}).get("converged")) for r in runs)
        # where the seeds trained: the curve's points may come from more than one machine
        where = sorted({f"{r.get('precision', '?')} on {r.get('cpu_kind', '?')}" for r in runs})
        xs.append(runs[0]["train_pairs"])
        rows.append([str(stride), str(xs[-1]), sp["rpe_rot"].text(5), sp["rpe_trans"].text(4),
                     f"{conv} of {len(runs)}", ", ".join(where)])  # fmt: skip
        sps.append(sp)
    label = "MFG (seed mean ± sd)" if any(sp["rpe_rot"].std is not None for sp in sps) else "MFG"
    panels = []
    for key, title in (("rpe_rot", "RPE rotation (rad)"), ("rpe_trans", "RPE translation (m)")):
        curves = {label: (xs, [sp[key].mean for sp in sps], [sp[key].std for sp in sps])}
        curves.update({_short(n): (xs, [m.get(key)] * len(xs)) for n, m in classical.items()})
        panels.append((title, curves))
    fig = line_figure(panels, "training pairs",
                      "Table 2's setting (exact flow) against the training set's size",
                      log_x=True, log_y=True)  # fmt: skip
    crows = [
        [n, fmt(m.get("rpe_rot"), 5), fmt(m.get("rpe_trans"), 4)] for n, m in classical.items()
    ]
    test = next(iter(points.values()))[0]["test_pairs"]
    heads = ("stride N", "training pairs", "RPE rotation (rad)", "RPE translation (m)",
             "converged", "trained")  # fmt: skip
    classical_md = table(("classical method", "RPE rotation (rad)", "RPE translation (m)"),
                         crows) if crows else ""  # fmt: skip
    return lines("report/size.md.j2", test=test, table=table(heads, rows),
                 classical=classical_md), fig  # fmt: skip
