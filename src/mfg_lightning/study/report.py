"""The report of the reproduction study, rewritten from every cached stage result: one verdict
per quoted sentence of the paper (:mod:`mfg_lightning.study.sentences`) with its tolerance from
the seed spread (:mod:`mfg_lightning.study.noise`), the main model's headline numbers over the
seeds, the diagnostics beside the paper's tables (:mod:`mfg_lightning.study.claims`), the
generated reading (:mod:`mfg_lightning.study.prose`), the machine, the budget and the stages'
times. Each section's words are a template (``templates/report/<section>.md.j2``,
:mod:`mfg_lightning.study.render`); the code here computes its tables and figures."""

from __future__ import annotations

import os
import platform
import textwrap
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mfg_lightning.core.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.core.paths import portable_overrides, portable_path
from mfg_lightning.core.tables import fmt
from mfg_lightning.flow.cache import default_cache_dir
from mfg_lightning.pictures.plots import figure_png
from mfg_lightning.study import claims as C
from mfg_lightning.study import end_to_end as E
from mfg_lightning.study import plan
from mfg_lightning.study import prose as P
from mfg_lightning.study import stages as S
from mfg_lightning.study.config_findings import config_default, input_scale_finding
from mfg_lightning.study.figures import convergence_rows, verdict_figure
from mfg_lightning.study.intervals import (
    BLOCK_PAIRS,
    BOOTSTRAP_DRAWS,
    FLOORS,
    HOLDS,
    INCONCLUSIVE,
    NO_VERDICT,
    NOT_HOLD,
    PARTLY,
)
from mfg_lightning.study.noise import spread_of
from mfg_lightning.study.render import lines, table
from mfg_lightning.study.sentences import Judged, Settled, judge_all, seed_views, test_at
from mfg_lightning.study.settle_report import converge_section, settle_section

#: The main model's headline numbers: label, measurement on a seed's view, decimals.
HEADLINE = (
    ("validation ATE † (m)", lambda v: v["table1"]["val"]["1"].get("ate"), 4),
    ("test ATE † 09 (m)", lambda v: test_at(v, 1.0, "09/ate"), 4),
    ("test ATE † 10 (m)", lambda v: test_at(v, 1.0, "10/ate"), 4),
    ("test ATE * 09 (m)", lambda v: test_at(v, 1.0, "09/ate_central"), 4),
    ("test ATE * 10 (m)", lambda v: test_at(v, 1.0, "10/ate_central"), 4),
    ("test RPE translation (m)", lambda v: test_at(v, 1.0, "rpe_trans"), 4),
    ("test RPE rotation (rad)", lambda v: test_at(v, 1.0, "rpe_rot"), 5),
    ("test ATE † 09 at k = 5 % (m)", lambda v: test_at(v, 0.05, "09/ate"), 4),
    ("test ATE † 10 at k = 5 % (m)", lambda v: test_at(v, 0.05, "10/ate"), 4),
)


def _machine() -> dict[str, str]:
    import torch

    from mfg_lightning.core.machine import cpu_kind
    from mfg_lightning.run.runs import git_commit

    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 0
    return {
        "commit": (git_commit() or "-")[:12],
        "report written on": f"{platform.processor() or platform.machine()} ({cpu_kind()}), "
        f"{cores} cores usable of {os.cpu_count()}",
        "torch": f"{torch.__version__} ({torch.get_num_threads()} threads; CUDA "
        f"{'yes' if torch.cuda.is_available() else 'no'})",
        "date (UTC)": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
    }


def _sparsity_models(study: S.Study) -> dict[str, dict]:
    """The sweep's cached results by label, in the sweep's order."""
    out = {}
    for v in plan.sparsity_variants(study.cfg):
        if (r := study.cached(f"sparsity/{v.name}")) is not None:
            out[v.label] = r
    return out


def _trained_models(
    study: S.Study, sparsity: dict[str, dict], size: dict[str, dict], settled: Settled
) -> dict[str, dict]:
    """Every trained model's cached result, by the name the report gives it."""
    models = {}
    for name in ("main", "twin", "learned", "table2", "table2_exact", "balance"):
        if (r := study.cached(name)) is not None:
            models[{"balance": "balance_squared", "twin": "exact-flow twin"}.get(name, name)] = r
    for seed in study.cfg.seeds.extra:
        if (r := study.cached(f"seeds/seed{int(seed)}")) is not None:
            models[f"main, seed {int(seed)}"] = r
    for flow, by in settled.budget.items():
        models.update({f"table2 {flow}, seed {s}": r for s, r in sorted(by.items())})
    for variant, by in settled.converged.items():
        models.update({f"rotation rule, {variant}, seed {s}": r for s, r in sorted(by.items())})
    models.update({f"table2 strided, seed {s}": r for s, r in sorted(settled.strided.items())})
    for name, _ in E.runs(study.cfg):
        if "seed" in name and (r := study.cached(name)) is not None:
            kind, seed = name.split("/")[1].rsplit("_seed", 1)
            models[f"end to end: {kind.replace('_', '-')}, seed {seed}"] = r
    models.update({f"size {k}": v for k, v in size.items() if "steps" in v})
    models.update({f"sparsity {k}": v for k, v in sparsity.items()})
    if (rc := study.cached("recipe")) is not None:
        models.update({f"recipe {k}": v for k, v in rc.items() if isinstance(v, dict)})
    # a run that is another stage's model (``same_as``: the main model's, or one trained from an
    # equal config) has that model's row
    return {k: v for k, v in models.items() if not v.get("same_as")}


def _stage_rows(study: S.Study) -> tuple[list[dict], float]:
    """One row per cached stage result: seconds (training included), steps × batch, the
    commit and what reads it (its stage's ``read_by`` in the stage table)."""
    rows, total, readers = [], 0.0, plan.read_by(study.cfg)
    for path in sorted(study.results.glob("**/*.json")):
        name = str(path.relative_to(study.results).with_suffix(""))
        if name == "changes":
            # the record of changes made after a test number was seen, not a stage
            continue
        r = study.cached(name) or {}
        # a run that is another stage's (``same_as``) was trained there, not here
        trained = [r] if "steps" in r else [v for v in r.values() if isinstance(v, dict)
                                            and "steps" in v]  # fmt: skip
        trained = [t for t in trained if not t.get("same_as")]
        shape = ", ".join(f"{t['steps']} × {t['batch_size']}" for t in trained)
        train_s = sum(float(t.get("train_seconds", 0.0)) for t in trained)
        # a stage resumed in a later process records that process's seconds only; its training
        # time counts every session's, so it bounds the stage's time from below
        seconds = float(r.get("seconds", 0.0))
        resumed = train_s > seconds
        total += max(seconds, train_s)
        rows.append({"name": name, "seconds": max(seconds, train_s), "resumed": resumed,
                     "train": train_s, "shape": shape, "commit": r.get("commit"),
                     "read_by": readers.get(name, [])})  # fmt: skip
    return rows, total


def write_report(study: S.Study, report: Path) -> Path:
    """Rewrite the report from every cached stage; figures into ``<report stem>/`` (a figure no
    longer produced is removed, so none goes stale)."""
    cfg, cached = study.cfg, study.cached
    figdir, made = report.with_suffix(""), []

    def link(name: str, fig: Any) -> str:
        if fig is None:
            return ""
        made.append(name)
        atomic_write_bytes(figdir / name, figure_png(fig))
        return f"[{name}]({figdir.name}/{name})"

    sparsity = _sparsity_models(study)
    tol = float(cfg.sparsity.ate_tolerance)
    views = seed_views(cached, int(cfg.seed), [int(s) for s in cfg.seeds.extra])
    size = {n: r for n in [S.size_name(*p) for p in S.size_runs(cfg)] + ["classical"]
            if (r := cached(f"size/{n}")) is not None}  # fmt: skip
    settled = Settled.load(cached, cfg)
    judged = judge_all(views, settled, float(cfg.basis.residual), float(cfg.basis.one_motion), tol)
    t1 = cached("table1")
    row2, fig2, sweep = C.claim_sparsity(t1, sparsity, tol)
    built = [
        (C.claim_table1(t1), "table1.png"),
        ((row2, fig2), "sparsity.png"),
        (C.claim_table2(cached("table2"), _offsets(study, "table2")), "table2.png"),
        (C.claim_robustness(cached("methods")), "robustness.png"),
        (C.claim_basis(cached("basis"), float(cfg.basis.residual)), "basis.png"),
        (C.claim_object_motion(cached("object_motion")), "object_motion.png"),
        (C.claim_recipe(cached("recipe")), "recipe.png"),
    ]
    for (row, fig), name in built:
        row.figure = link(name, fig) or row.figure
    rows = [[r.number, r.claim, r.paper, r.ours, r.figure] for (r, _), _ in built]
    diagnostics = table(("#", "diagnostic", "paper", "ours (seed 0)", "figure"), rows)
    models = _trained_models(study, sparsity, size, settled)
    conv_rows, conv_fig = convergence_rows(models)
    conv_link = link("convergence.png", conv_fig)
    flow_lines = _flow_error_section(cached("flow_error"), link)
    causes = _causes_sections(study, views, size, settled, link)
    verdict_link = link("verdicts.png", verdict_figure(judged))
    _remove_stale(figdir, made)
    scale_model = next((m for k, m in sparsity.items() if "input_scale" in k), None)
    default_scale = float(config_default("model.net.input_scale"))
    scale_text = input_scale_finding(views, scale_model, cfg.sparsity.input_scale, default_scale)
    stage_rows, total = _stage_rows(study)
    flow = study_flow_name(study)
    conv_heads = (
        "model",
        "steps",
        "samples",
        "status",
        "best validation value (the rule's metric)",
        "training (min)",
    )
    text = [
        *_header(study, views, total, models),
        *lines("report/verdicts.md.j2", judged=judged, figure=verdict_link, flow=flow,
               draws=BOOTSTRAP_DRAWS, block=BLOCK_PAIRS, floors=FLOORS, table=table(
                   ("#", "the paper", "measured as", "flow", "ours (parts)", "verdict"),
                   [[j.sentence.key, f"“{j.sentence.quote}” ({j.sentence.where})",
                     j.sentence.measured, j.sentence.flow.format(study=flow),
                     "; ".join(p.text() for p in j.parts) or "not run yet", j.verdict]
                    for j in judged])),
        *_headline_section(views),
        *lines("report/diagnostics.md.j2", rules=C.RULES.values(), table=diagnostics, sweep=sweep),
        *_methods_section(cached("methods")),
        *flow_lines,
        *causes,
        *_balance_section(cached("basis"), cached("methods"), cached("balance"),
                          float(cfg.basis.residual)),
        *lines("report/converge.md.j2", conv_link=conv_link,
               conv_table=table(conv_heads, conv_rows) if conv_rows else ""),
        *P.reading(cached, views, judged, float(cfg.basis.residual),
                   float(config_default("object_motion.theta_d")), scale_text, size, settled,
                   list(cfg.data)),
        *_notes(cfg.get("notes")),
        *lines("report/stages.md.j2", stages=stage_rows,
               missing=[n for _, n, _ in plan.results(cfg) if cached(n) is None]),
    ]  # fmt: skip
    path = atomic_write_text(report, "\n".join(text))
    print(f"wrote {path}", flush=True)
    if cfg.get("readme"):
        write_readmetable(Path(cfg.readme), judged, report, models, total)
    return path


README_START, README_END = "<!-- reproduction-table:start -->", "<!-- reproduction-table:end -->"


def readmetable(
    judged: list[Judged], report: str, models: dict[str, dict], seconds: float
) -> list[str]:
    """The README's quoted table: the verdicts counted and the study's cost (its trained
    ``models``, the stages' ``seconds``, the machines), then one row per sentence: the claim,
    the part that decides it with its 95 % interval, the bound and the verdict."""
    counts = Counter(j.verdict for j in judged)
    order = [v for v in VERDICT_ORDER if counts[v]] + sorted(set(counts) - set(VERDICT_ORDER))
    kinds: Counter[str] = Counter()
    for kind, _, n in machines(models):
        kinds[kind] += n
    text = lines("report/readme.md.j2", report=report, judged=judged, hours=seconds / 3600,
                 counts=[(counts[v], v) for v in order], models=len(models),
                 kinds=kinds.most_common())  # fmt: skip
    # the README keeps its 100-column wrap: prose is wrapped, a table row is one line
    return [w for line in text for w in
            (textwrap.wrap(line, 100, break_on_hyphens=False) or [""]
             if not line.startswith("|") else [line])]  # fmt: skip


#: The order the README counts the verdicts in.
VERDICT_ORDER = (HOLDS, NOT_HOLD, INCONCLUSIVE, PARTLY, NO_VERDICT)


def write_readmetable(
    readme: Path, judged: list[Judged], report: Path, models: dict[str, dict], seconds: float
) -> None:
    """Replace the README's text between :data:`README_START` and :data:`README_END` with
    :func:`readmetable` (the report linked relative to the README); a README without both
    markers is left alone, with a warning."""
    if not readme.is_file():
        return
    text = readme.read_text()
    if README_START not in text or README_END not in text:
        print(f"warning: {readme} has no {README_START} … {README_END}: not updated", flush=True)
        return
    head, rest = text.split(README_START, 1)
    _, tail = rest.split(README_END, 1)
    rel = os.path.relpath(report.resolve(), readme.resolve().parent).replace(os.sep, "/")
    block = "\n".join(readmetable(judged, rel, models, seconds))
    atomic_write_text(readme, f"{head}{README_START}\n{block}\n{README_END}{tail}")


def _offsets(study: S.Study, stage: str) -> list[int] | None:
    """The frame offsets a trained model's pairs use (its overrides on the study's data)."""
    r = study.cached(stage)
    if r is None:
        return None
    if "config" in r:  # the config it trained from
        return [int(o) for o in r["config"]["dataset"].get("offsets", [1])]
    cfg = study.train_config(stage, list(r.get("overrides", [])), settings=r.get("settings"))
    return [int(o) for o in cfg.dataset.get("offsets", [1])]


def machines(models: dict[str, dict]) -> list[tuple[str, str, int]]:
    """Each machine kind and precision that trained ``models`` (their stage results by name),
    with how many models each trained, most first: ``(kind, precision, count)``; "not
    recorded" where a result lacks it (results from before the study recorded them)."""
    kinds = Counter(
        (str(m.get("cpu_kind") or "not recorded"), str(m.get("precision") or "not recorded"))
        for m in models.values()
    )
    return [(k, p, n) for (k, p), n in sorted(kinds.items(), key=lambda kv: (-kv[1], kv[0]))]


def _header(study: S.Study, views: dict, total: float, models: dict[str, dict]) -> list[str]:
    """The report's title, what produced it, the machine that wrote it and those that trained
    its ``models``, the main model, the budget, the deviations from the paper's data and the
    recipes (the paper's from ``recipe.paper``)."""
    from mfg_lightning.core.config import compose
    from mfg_lightning.data.rendered import RENDER_SIZE

    cfg = study.cfg
    main = study.cached("main")
    # Paths as a reader finds them (relative, ../shared, <cache>), not this machine's.
    here, cache = Path.cwd(), default_cache_dir()
    main_ov = dict(str(o).split("=", 1) for o in cfg.main if "=" in str(o))
    stride = int(cfg.budget.main_frame_stride)
    size = [str(o) for o in cfg.data if str(o).startswith(("dataset.height", "dataset.width"))]
    ds = compose("train", size).dataset
    paper = study.train_config("recipe_paper", [*cfg.main, *cfg.recipe.paper])
    # KITTI's poses are the reader's own folder: named by the key, never by this machine's path
    data = [o if not str(o).startswith("dataset.poses_dir=") else "dataset.poses_dir=<poses_dir>"
            for o in portable_overrides(cfg.data, here, cache)]  # fmt: skip
    return lines(
        "report/header.md.j2",
        results=portable_path(str(study.results), here, cache),
        data=" ".join(data),
        machine=_machine(),
        trained_on=machines(models),
        main=" ".join(portable_overrides(main["overrides"] if main else cfg.main, here, cache)),
        seeds=sorted(views), total=total, max_frames=cfg.budget.max_frames,
        rule=", ".join(f"{k}={v}" for k, v in cfg.convergence.items()),
        nth={1: "", 2: "2nd ", 3: "3rd "}.get(stride, f"{stride}th "),
        pairs=((study.cached("data") or {}).get("main") or {}).get("train_pairs"),
        offsets=len(main_ov.get("dataset.offsets", "[1]").strip("[]").split(",")),
        size=(ds.height, ds.width),
        render=(ds.flow.get("height") or RENDER_SIZE[0], ds.flow.get("width") or RENDER_SIZE[1]),
        t2=dict(str(o).split("=", 1) for o in cfg.table2.overrides if "=" in str(o)),
        cpu=main["recipe"] if main else None, paper=S.recipe_of(paper),
    )  # fmt: skip


def _headline_section(views: dict) -> list[str]:
    """The main model's headline numbers per seed, with their mean ± sd."""
    if not views:
        return []
    seeds = sorted(views)
    rows = []
    for label, measure, digits in HEADLINE:
        sp = spread_of(views, measure)
        per = {s: v for s, v in zip(sp.seeds, sp.values, strict=True)}
        rel = "–" if sp.relative_std is None else f"{100 * sp.relative_std:.1f} %"
        rows.append([label, *(fmt(per.get(s), digits) for s in seeds), sp.text(digits), rel])
    heads = ("quantity", *(f"seed {s}" for s in seeds), "mean ± sd", "relative sd")
    return lines("report/headline.md.j2", seeds=seeds, views=views, table=table(heads, rows))


def _flow_error_section(fe: dict | None, link: Any) -> list[str]:
    """DIS's error against the exact flow by frame offset (stage ``flow_error``): a table per
    region and its figure; nothing before the stage has run."""
    from mfg_lightning.metrics.flow_quality import QUALITY_REGIONS
    from mfg_lightning.pictures.plots import bar_figure

    if fe is None:
        return []
    test = dict(sorted(fe["test"].items(), key=lambda kv: int(kv[0])))

    def cells(regions: dict | None) -> list[str]:  # "–": a result from before noc was scored
        return [f"{fmt(regions[r]['epe'], 2)} / {fmt(regions[r]['fl'], 1)}" if regions else "–"
                for r in QUALITY_REGIONS]  # fmt: skip

    rows = [[f"{int(o):+d}", pixels, str(q["pairs"]), *cells(q.get(key))]
            for o, q in test.items()
            for pixels, key in (("noc", "regions_noc"), ("all", "regions"))]  # fmt: skip
    fig = bar_figure(
        [("mean end-point error (px)",
          {f"offset {int(o):+d}": [q["regions"][r]["epe"] for r in QUALITY_REGIONS]
           for o, q in test.items()})],
        list(QUALITY_REGIONS),
        "DIS's error by frame offset (test pairs)",
    )  # fmt: skip
    heads = ("offset", "pixels", "pairs", *(f"{r}: EPE (px) / Fl (%)" for r in QUALITY_REGIONS))
    return lines("report/flow_error.md.j2", figure=link("flow_error.png", fig),
                 table=table(heads, rows))  # fmt: skip


def _causes_sections(
    study: S.Study, views: dict, size: dict, settled: Settled, link: Any
) -> list[str]:
    """The causes separated (:mod:`mfg_lightning.study.causes`): the exact-flow twin, Table 2 on
    exact flow beside DIS, the size curve (``size``: its results by name); their figures
    written by ``link``."""
    from mfg_lightning.study import causes

    cached, twin = study.cached, study.cached("twin")
    sections = []
    for (text, fig), name in ((causes.twin_section(views, twin, cached("methods")), "twin.png"),
                              (causes.size_section(size), "size.png"),
                              (settle_section(settled), "settle.png")):  # fmt: skip
        if fig is not None:
            text[2] += " " + link(name, fig)
        sections.append(text)
    learned = causes.learned_section(
        views, twin, cached("learned"), cached("flow_error"), study_flow_name(study)
    )
    t2 = causes.table2_flow_section(cached("table2_exact"), cached("table2"))
    stale = {n: cached(n) for n in ("twin", "table2", "table2_exact", "size/classical")}
    twin_lines, size_lines, settle_lines = sections
    clamp = config_default("model.loss.balance_max")
    rule = converge_section(settled, list(study.cfg.converge.rule), clamp)
    e2e, fig = E.section(cached, study.cfg)
    if fig is not None:
        e2e[2] += " " + link("end_to_end.png", fig)
    return [*twin_lines, *learned, *settle_lines, *rule, *e2e, *t2, *size_lines,
            *stale_essential(stale)]  # fmt: skip


def study_flow_name(study: S.Study) -> str:
    """The study's own flow as the report names it (``flow=dis``: DIS)."""
    chosen = [str(d).split("=", 1)[1] for d in study.cfg.data if str(d).startswith("flow=")]
    name = chosen[-1] if chosen else "dis"
    return {"dis": "DIS", "exact": "exact"}.get(name, name)


def _remove_stale(figdir: Path, made: list[str]) -> None:
    """Remove the figures of the report's folder that this report no longer links."""
    for png in figdir.glob("*.png"):
        if png.name not in made:
            png.unlink()


#: The classical baselines' version with the essential-matrix cheirality fix
#: (:data:`mfg_lightning.motion.baselines.VERSION`): a stage result that records an earlier one,
#: or none (it predates the record), counts a slow pair's wrong decomposition (a rotation off by
#: π) as the method's error. Read from the result, so a checkout without git history agrees.
ESSENTIAL_FIX = 2


def stale_essential(results: dict[str, dict | None]) -> list[str]:
    """A note naming the stages (by name) whose essential-matrix rows predate the fix, or
    nothing."""
    stale = [n for n, r in results.items() if r and r.get("baselines_version", 1) < ESSENTIAL_FIX]
    return lines("report/stale.md.j2", stale=stale) if stale else []


def _methods_section(mt: dict | None) -> list[str]:
    """The main model against every classical baseline on every test pair (stage ``methods``)."""
    if mt is None:
        return []
    keys = ("09/ate", "10/ate", "09/ate_central", "10/ate_central", "rpe_trans", "rpe_rot")
    first_mfg = next((r["name"] for r in mt["rows"] if r["name"].startswith("MFG")), None)
    rows = []
    for r in mt["rows"]:
        ms, note = f"{r['ms_per_frame']:.1f}", r.get("note", "")
        if r["name"].startswith("MFG") and r["name"] != first_mfg:
            # the top-k rows reuse the first MFG row's encoder pass (analysis.scoring), so
            # their time is the decoders' and the top-k's alone
            ms = f"{ms} + encoder"
            note = f"decoders only: the encoder's pass is timed in {first_mfg}"
        rows.append([r["name"], *(fmt(r["metrics"].get(k), 5 if k == "rpe_rot" else 4)
                                  for k in keys), ms, note])  # fmt: skip
    heads = ("method", "ATE † 09 (m)", "ATE † 10 (m)", "ATE * 09 (m)", "ATE * 10 (m)",
             "RPE trans (m)", "RPE rot (rad)", "ms / pair", "note")  # fmt: skip
    return [*lines("report/methods.md.j2", mt=mt, table=table(heads, rows)),
            *stale_essential({"methods": mt})]  # fmt: skip


def _balance_section(
    basis: dict | None, methods: dict | None, balance: dict | None, residual: float
) -> list[str]:
    """The two readings of the balancing weights side by side (claims 3 and 5): the released
    code's (the main model) and the paper's printed squared ratio (stage ``balance``)."""
    if balance is None:
        return []

    def row(name: str, test: dict, bs: dict | None) -> list[str]:
        if bs is None:
            return [name, fmt(test.get("ate")), fmt(test.get("rpe_rot"), 5), *["–"] * 4]
        one = C.one_motion_fractions(bs, residual)
        clamped = bs["data"].get("omega_weight_clamped")
        return [
            name, fmt(test.get("ate")), fmt(test.get("rpe_rot"), 5),
            fmt(None if clamped is None else 100 * clamped, 1),
            fmt(100 * one["t"], 0), fmt(100 * one["omega"], 0), fmt(bs.get("ratio_typical"), 3),
        ]  # fmt: skip

    main_test = methods["rows"][0]["metrics"] if methods else {}
    heads = ("balancing (model)", "test ATE † (m)", "test RPE rot (rad)",
             "ω weight clamped (% of val)", "one motion, t units (%)",
             "one motion, ω units (%)", "|ω| / |t| typical")  # fmt: skip
    rows = [
        row("released code: norm ratio (main model)", main_test, basis),
        row(f"paper's print: squared ratio ({balance['steps']} steps)", balance.get("test", {}),
            balance.get("basis")),
    ]  # fmt: skip
    return lines("report/balance.md.j2", table=table(heads, rows))


def _notes(notes: str | None) -> list[str]:
    """The reading of the results that a person wrote (the ``notes`` file,
    ``bench/results/reproduction_notes.md``), kept apart so that a rerun of the study does not
    overwrite it (and printed as written); nothing when there is none."""
    if not notes or not (notes := Path(notes).expanduser()).is_file():
        return []
    return ["## Notes", "", notes.read_text().strip(), ""]
