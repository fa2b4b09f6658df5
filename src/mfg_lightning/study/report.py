"""The report of the reproduction study, rewritten from every cached stage result: one verdict
per quoted sentence of the paper (:mod:`mfg_lightning.study.sentences`) with its tolerance from
the seed spread (:mod:`mfg_lightning.study.noise`), the main model's headline numbers over the
seeds, the diagnostics beside the paper's tables (:mod:`mfg_lightning.study.claims`), the
generated reading (:mod:`mfg_lightning.study.prose`), the machine, the budget and the stages'
times."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import Any

from mfg_lightning.core.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.core.paths import portable_overrides, portable_path
from mfg_lightning.core.tables import Column, Table, fmt
from mfg_lightning.flow.cache import default_cache_dir
from mfg_lightning.pictures.plots import figure_png
from mfg_lightning.study import claims as C
from mfg_lightning.study import config_findings as F
from mfg_lightning.study import prose as P
from mfg_lightning.study import settle as T
from mfg_lightning.study import stages as S
from mfg_lightning.study.intervals import FLOORS, bootstrap_method
from mfg_lightning.study.noise import spread_of
from mfg_lightning.study.sentences import Judged, Settled, judge_all, seed_views, test_at
from mfg_lightning.study.settle_report import settle_section

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
        "machine": f"{platform.processor() or platform.machine()} ({cpu_kind()}), {cores} cores "
        f"usable of {os.cpu_count()} (this session's; each trained model's stage result names "
        "its own precision and CPU kind where recorded)",
        "torch": f"{torch.__version__} ({torch.get_num_threads()} threads; CUDA "
        f"{'yes' if torch.cuda.is_available() else 'no'})",
        "date (UTC)": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
    }


def _sparsity_models(study: S.Study) -> dict[str, dict]:
    """The sweep's cached results by label, in the sweep's order."""
    out = {}
    for name, extra, plain, ws in S.sparsity_variants(study.cfg):
        if (r := study.cached(f"sparsity/{name}")) is not None:
            keys = [
                e.split("=")[0].rsplit(".", 1)[-1] + "=" + e.split("=", 1)[1] for e in extra[1:]
            ]
            tail = "" if plain else " (" + ", ".join(keys) + ")"
            out[f"w_s={ws:g}{tail}"] = r
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
    for flow, by in settled.seeds.items():
        models.update({f"table2 {flow}, seed {s}": r for s, r in sorted(by.items())})
    models.update({f"table2 strided, seed {s}": r for s, r in sorted(settled.strided.items())})
    models.update({f"size {k}": v for k, v in size.items() if "steps" in v})
    # a run that is the main model's (``same_as``) has the main model's row
    models.update({f"sparsity {k}": v for k, v in sparsity.items() if not v.get("same_as")})
    if (rc := study.cached("recipe")) is not None:
        # the CPU recipe's run is the main model's (``same_as``): its row is the main one
        models.update(
            {
                f"recipe {k}": v
                for k, v in rc.items()
                if isinstance(v, dict) and not v.get("same_as")
            }
        )
    return models


def _stage_rows(study: S.Study) -> tuple[list[str], float]:
    """One row per cached stage: seconds (training included), steps × batch, the commit."""
    rows, total = [], 0.0
    for path in sorted(study.results.glob("**/*.json")):
        name = str(path.relative_to(study.results).with_suffix(""))
        if name == "changes":
            # the record of changes made after a test number was seen, not a stage
            continue
        r = study.cached(name) or {}
        seconds = float(r.get("seconds", 0.0))
        total += seconds
        # a run that is another stage's (``same_as``) was trained there, not here
        trained = [r] if "steps" in r else [v for v in r.values() if isinstance(v, dict)
                                            and "steps" in v]  # fmt: skip
        trained = [t for t in trained if not t.get("same_as")]
        shape = ", ".join(f"{t['steps']} × {t['batch_size']}" for t in trained)
        train_s = sum(float(t.get("train_seconds", 0.0)) for t in trained)
        rows.append(
            f"| {name} | {seconds:.0f} | {train_s:.0f} | {shape} | {r.get('commit') or '-'} |"
        )
    return rows, total


def write_report(study: S.Study, report: Path) -> Path:
    """Rewrite the report from every cached stage; figures into ``<report stem>/`` (a figure no
    longer produced is removed, so none goes stale)."""
    cfg = study.cfg
    figdir = report.with_suffix("")
    sparsity = _sparsity_models(study)
    tol = float(cfg.sparsity.ate_tolerance)
    views = seed_views(study.cached, int(cfg.seed), [int(s) for s in cfg.seeds.extra])
    twin = study.cached("twin")
    size = {n: r for n in [S.size_name(*p) for p in S.size_runs(cfg)] + ["classical"]
            if (r := study.cached(f"size/{n}")) is not None}  # fmt: skip
    settled = Settled.load(study.cached, cfg)
    judged = judge_all(views, settled, float(cfg.basis.residual), float(cfg.basis.one_motion), tol)
    t1 = study.cached("table1")
    row2, fig2, sweep = C.claim_sparsity(t1, sparsity, tol)
    built = [
        (C.claim_table1(t1), "table1.png"),
        ((row2, fig2), "sparsity.png"),
        (C.claim_table2(study.cached("table2"), _offsets(study, "table2")), "table2.png"),
        (C.claim_robustness(study.cached("methods")), "robustness.png"),
        (C.claim_basis(study.cached("basis"), float(cfg.basis.residual)), "basis.png"),
        (C.claim_object_motion(study.cached("object_motion")), "object_motion.png"),
        (C.claim_recipe(study.cached("recipe")), "recipe.png"),
    ]
    made = []
    for (row, fig), name in built:
        if fig is not None:
            row.figure = _figure(figdir, name, fig)
            made.append(name)
    table = Table(
        [Column(h) for h in ("#", "diagnostic", "paper", "ours (seed 0)", "figure")],
        [[r.number, r.claim, r.paper, r.ours, r.figure] for (r, _), _ in built],
    )
    models = _trained_models(study, sparsity, size, settled)
    conv_rows, conv_fig = C.convergence_rows(models)
    conv_link = _figure(figdir, "convergence.png", conv_fig) if conv_fig is not None else ""
    made += ["convergence.png"] if conv_fig is not None else []
    flow_lines, flow_fig = _flow_error_section(study.cached("flow_error"))
    if flow_fig is not None:
        flow_lines[2] += " " + _figure(figdir, "flow_error.png", flow_fig)
        made.append("flow_error.png")
    causes = _causes_sections(study, views, twin, size, settled, figdir, made)
    verdict_fig = _verdict_figure(judged)
    verdict_link = _figure(figdir, "verdicts.png", verdict_fig) if verdict_fig else ""
    made += ["verdicts.png"] if verdict_fig is not None else []
    _remove_stale(figdir, made)
    scale_model = next((m for k, m in sparsity.items() if "input_scale" in k), None)
    default_scale = float(F.config_default("model.net.input_scale"))
    scale_text = F.input_scale_finding(views, scale_model, cfg.sparsity.input_scale, default_scale)
    stage_rows, total = _stage_rows(study)
    text = [
        *_header(study, views, total),
        *_verdicts_section(judged, verdict_link, study_flow_name(study)),
        *_headline_section(views),
        *_diagnostics_section(table, sweep),
        *_methods_section(study.cached("methods")),
        *flow_lines,
        *causes,
        *_balance_section(
            study.cached("basis"), study.cached("methods"), study.cached("balance"),
            float(cfg.basis.residual),
        ),
        "## Did it converge",
        "",
        "Not a claim of the paper (it says only that it trains to convergence): each model's "
        f"status by the rule above. {conv_link}",
        "",
        Table(
            [Column(h) for h in ("model", "steps", "samples", "status", "best val ATE †",
                                 "training (min)")],
            conv_rows,
        ).markdown()
        if conv_rows
        else "no model trained yet",
        "",
        "## Reading the results",
        "",
        "Generated from the stage results (`mfg_lightning.study.prose`).",
        "",
        *P.reading(study.cached, views, judged, float(cfg.basis.residual),
                   float(F.config_default("object_motion.theta_d")), scale_text, size, settled,
                   list(cfg.data)),
        *_notes(report),
        "## Stages",
        "",
        *_pending(study),
        "| stage | seconds | of which training | trained (steps × batch) | commit |",
        "|---|---:|---:|---:|---|",
        *stage_rows,
        "",
    ]  # fmt: skip
    path = atomic_write_text(report, "\n".join(text))
    print(f"wrote {path}", flush=True)
    if cfg.get("readme"):
        write_readme_table(Path(cfg.readme), judged, views, report)
    return path


README_START, README_END = "<!-- reproduction-table:start -->", "<!-- reproduction-table:end -->"


def readme_table(judged: list[Judged], views: dict, report: str) -> list[str]:
    """The README's quoted table: every sentence's short name, our values and the verdict."""
    rows = [
        [j.sentence.key, j.sentence.short,
         "; ".join(f"{p.label} {p.show(p.iv.value) if p.iv else '–'}" for p in j.parts) or "–",
         j.verdict]
        for j in judged
    ]  # fmt: skip
    seeds = len(views)
    return [
        f"Latest report ([{report}]({report})): one verdict per quoted sentence of the paper, "
        f"each part's value the mean over the seeds ({seeds} of the main model for S1–S3, S7 and "
        "S8; the Table-2-sized models' for S4–S6, S9 and S10), judged by its 95 % interval: "
        "holds on the claimed side of the bound, does not hold on the other, inconclusive "
        "across it (the report quotes each sentence and gives every bound and interval):",
        "",
        Table(
            [Column(h) for h in ("#", "the paper says", "ours (parts)", "verdict")], rows
        ).markdown(),
    ]


def write_readme_table(readme: Path, judged: list[Judged], views: dict, report: Path) -> None:
    """Replace the README's text between :data:`README_START` and :data:`README_END` with
    :func:`readme_table` (the report linked relative to the README); a README without both
    markers is left alone, with a warning."""
    if not readme.is_file():
        return
    text = readme.read_text()
    if README_START not in text or README_END not in text:
        print(f"warning: {readme} has no {README_START} … {README_END}: not updated", flush=True)
        return
    head, rest = text.split(README_START, 1)
    _, tail = rest.split(README_END, 1)
    rel = os.path.relpath(report.resolve(), readme.resolve().parent)
    block = "\n".join(readme_table(judged, views, rel.replace(os.sep, "/")))
    atomic_write_text(readme, f"{head}{README_START}\n{block}\n{README_END}{tail}")


def _offsets(study: S.Study, stage: str) -> list[int] | None:
    """The frame offsets a trained model's pairs use (its overrides on the study's data)."""
    r = study.cached(stage)
    if r is None:
        return None
    cfg = study.train_config(stage, list(r.get("overrides", [])), 1)
    return [int(o) for o in cfg.dataset.get("offsets", [1])]


def _diagnostics_section(table: Table, sweep: list[str]) -> list[str]:
    """The paper's tables beside ours, and the w_s sweep: read, not judged."""
    return [
        "## Diagnostics: the paper's tables beside ours (not verdicts)",
        "",
        "The shape of the paper's tables and figures, with each deviation from the paper's "
        "figure; Table 1's ratios at every k, ATE * / ATE †, Table 2's ratios, row R and the w_s "
        "sweep are read here, not judged.",
        "",
        *(f"- **{r.number}. {r.claim}.** " + "; ".join(r.parts) + "." for r in C.RULES.values()),
        "",
        table.markdown(),
        "",
        "### The w_s sweep (this project's extension)",
        "",
        *([f"- {line}" for line in sweep] or ["not run yet"]),
        "",
    ]


def _header(study: S.Study, views: dict, total: float) -> list[str]:
    """The report's title, what produced it, the machine, the main model and the budget."""
    cfg = study.cfg
    main = study.cached("main")
    recipe = main["recipe"] if main else None
    # Paths as a reader finds them (relative, ../shared, <cache>), not this machine's.
    data = " ".join(portable_overrides(cfg.data, Path.cwd(), default_cache_dir()))
    main_overrides = main["overrides"] if main else cfg.main
    main_text = " ".join(portable_overrides(main_overrides, Path.cwd(), default_cache_dir()))
    rule = ", ".join(f"{k}={v}" for k, v in cfg.convergence.items())
    return [
        "# Reproduction of the paper's claims",
        "",
        "Produced by `python -m mfg_lightning.reproduce` (one command; every figure and every "
        "number below comes from it; a fresh clone rebuilds this report from the committed stage "
        f"results in `{portable_path(str(study.results), Path.cwd(), default_cache_dir())}/` "
        "without retraining): synthetic worlds rendered along "
        f"the real KITTI trajectories, overrides `{data}`; choices made on the validation tails "
        "of the training sequences only, then fixed.",
        "",
        *(f"- **{k}**: {v}" for k, v in _machine().items()),
        f"- **main model**: `{main_text}`, seeds {', '.join(str(s) for s in sorted(views))} "
        "trained",
        f"- **convergence rule** (every model, stated before training): {rule}",
        f"- **budget used**: {total / 60:.1f} min over the stages below (training included), "
        f"frames per sequence {cfg.budget.max_frames or 'all'}",
        *_deviations(study),
        "- **recipe**: "
        + (
            f"CPU: batch {recipe['batch_size']}, {recipe['optimizer']} lr {recipe['lr']:g}, betas "
            f"{recipe['betas']}, constant until the rule is met, w_s {recipe['w_s']:g}; the "
            "paper: batch 1, Adam lr 1e-5, betas (0.99, 0.999), constant (row R compares them)."
            if recipe
            else "not run yet"
        ),
        "",
    ]


def _deviations(study: S.Study) -> list[str]:
    """The header's list of every way the study's data differ from the paper's."""
    cfg = study.cfg
    data = study.cached("data") or {}
    main_ov = dict(str(o).split("=", 1) for o in cfg.main if "=" in str(o))
    offsets = len(main_ov.get("dataset.offsets", "[1]").strip("[]").split(","))
    pairs = (data.get("main") or {}).get("train_pairs")
    stride = int(cfg.budget.main_frame_stride)
    frames = f"about {pairs // offsets:,} source frames ({pairs:,} pairs)" if pairs else "–"
    from mfg_lightning.core.config import compose
    from mfg_lightning.data.rendered import RENDER_SIZE

    size = [str(o) for o in cfg.data if str(o).startswith(("dataset.height", "dataset.width"))]
    ds = compose("train", size).dataset
    render = (ds.flow.get("height") or RENDER_SIZE[0], ds.flow.get("width") or RENDER_SIZE[1])
    t2 = dict(str(o).split("=", 1) for o in cfg.table2.overrides if "=" in str(o))
    nth = {1: "", 2: "2nd ", 3: "3rd "}.get(stride, f"{stride}th ")
    return [
        "- **deviations from the paper's data**: "
        f"(1) *frame stride*: the main model trains on every {nth}source frame of 00–08, "
        f"{frames}, against the paper's ~20.4K frames (every frame); validation and test use "
        "every frame; "
        f"(2) *resolution*: the model reads {ds.height} × {ds.width} flow (downsampled from the "
        f"{render[0]} × {render[1]} render, as the released code feeds PWC-Net's "
        "quarter-resolution output; the paper states no input size); "
        "(3) *flow*: OpenCV's DIS on rendered frames where the paper used PWC-Net on KITTI's "
        "images, and the rendered worlds' exact flow where it used Virtual KITTI's ground "
        "truth; "
        "(4) *scenes*: synthetic worlds rendered along the real KITTI trajectories (00–10), not "
        "KITTI's or Virtual KITTI's images; the Table-2-sized set is the first "
        f"{t2.get('dataset.max_frames', '?')} frames of sequences "
        f"{t2.get('dataset.train_sequences', '?')} in place of Virtual KITTI's egomotion split "
        "(1,679 training frames).",
    ]


def _floors_text() -> str:
    units = {
        "rotation": "rad of rotation error",
        "translation": "m of translation error",
        "fraction": "for a fraction",
        "pairs": "test pairs holding the objects of a bin",
    }
    return ", ".join(f"{v:g} {units.get(k, k)}" for k, v in FLOORS.items())


def _verdicts_section(judged: list[Judged], figure: str, flow_name: str = "DIS") -> list[str]:
    """The sentences, their measurement, the flow it uses (``flow_name``: the study's own) and
    verdict: one row per sentence."""
    rows = [
        [j.sentence.key, f"“{j.sentence.quote}” ({j.sentence.where})", j.sentence.measured,
         j.sentence.flow.format(study=flow_name),
         "; ".join(p.text() for p in j.parts) or "not run yet", j.verdict]
        for j in judged
    ]  # fmt: skip
    return [
        "## Verdicts, one per sentence of the paper",
        "",
        "Each sentence is quoted and measured in the direction it claims, in parts. Each part is "
        "a value with a 95 % interval: Student's t over the seeds' values (t · sd / √n) where "
        "several models were trained (for S3's k, a grid value, the exact sign test's interval "
        "of the seeds' median), plus, where the stage kept per-pair values, 1.96 standard errors "
        "of a paired moving-block bootstrap over the test pairs, added in quadrature. "
        f"{bootstrap_method()} A bound read off the paper's printed numbers is known only to "
        "their print precision (a printed 0.012 stands for [0.0115, 0.0125)), so the "
        "interval is widened by that fraction of the bound on each side. A part **holds** when "
        "its whole interval lies on the claimed side of the bound, **does not hold** when it "
        "lies wholly on the other side, and is **inconclusive** when it straddles the bound or "
        "covers every value the quantity can take. A ratio whose denominator is below its floor "
        f"({_floors_text()}) is **no verdict**. The parts of one sentence are one family: "
        "Holm's step-down procedure decides them at a family level of 95 % (the most decisive "
        "part, by its distance from the bound in half-widths, at 1 − 0.05 / m, the next at "
        "1 − 0.05 / (m − 1)…; the first part not decided at its level leaves itself and every "
        "later part inconclusive), and a part judged at more than 95 % prints that interval "
        "beside its 95 % one. A sentence holds when every part holds, does not "
        "hold when one part does not, and is otherwise **partly** (some parts hold, the rest are "
        "inconclusive) or **inconclusive** (none holds). Ratios of errors are judged as the log "
        "of the ratio and printed as ×ratio. The rules are data in "
        "`mfg_lightning.study.sentences.SENTENCES` and the construction is "
        f"`mfg_lightning.study.intervals`. The flow column names the input flow each "
        f"verdict's models read ({flow_name}: the flow estimated on the rendered frames; exact: "
        "the renderer's exact flow; the learned flow's models are a diagnostic, no verdict "
        f"reads them). {figure}",
        "",
        Table(
            [
                Column(h)
                for h in ("#", "the paper", "measured as", "flow", "ours (parts)", "verdict")
            ],
            rows,
        ).markdown(),
        "",
        *[f"- {j.sentence.key}: {j.beside}" for j in judged if j.beside],
        "",
    ]


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
    kinds = "; ".join(
        f"seed {s}: {views[s]['trained'].get('precision', 'precision not recorded')}, "
        f"{views[s]['trained'].get('cpu_kind', 'CPU kind not recorded')}"
        for s in seeds
    )
    return [
        "## The main model's headline numbers (seed mean ± sd)",
        "",
        f"The main setting trained at {len(seeds)} seed{'s' if len(seeds) > 1 else ''} "
        f"(same pairs, rule and caps; {kinds}).",
        "",
        Table(
            [
                Column(h)
                for h in ("quantity", *(f"seed {s}" for s in seeds), "mean ± sd", "relative sd")
            ],
            rows,
        ).markdown(),
        "",
    ]


def _flow_error_section(fe: dict | None) -> tuple[list[str], Any]:
    """DIS's error against the exact flow by frame offset (stage ``flow_error``): a table per
    region and its figure; nothing before the stage has run."""
    from mfg_lightning.data.rendered import QUALITY_REGIONS
    from mfg_lightning.pictures.plots import bar_figure

    if fe is None:
        return [], None
    test = dict(sorted(fe["test"].items(), key=lambda kv: int(kv[0])))
    rows = [
        [f"{int(o):+d}", str(q["pairs"]),
         *(f"{fmt(q['regions'][r]['epe'], 2)} / {fmt(q['regions'][r]['fl'], 1)}"
           for r in QUALITY_REGIONS)]
        for o, q in test.items()
    ]  # fmt: skip
    fig = bar_figure(
        [("mean end-point error (px)",
          {f"offset {int(o):+d}": [q["regions"][r]["epe"] for r in QUALITY_REGIONS]
           for o, q in test.items()})],
        list(QUALITY_REGIONS),
        "DIS's error by frame offset (test pairs)",
    )  # fmt: skip
    heads = ("offset", "pairs", *(f"{r}: EPE (px) / Fl (%)" for r in QUALITY_REGIONS))
    return [
        "## The flow by offset (what ATE * / ATE † also measures)",
        "",
        "DIS's error against the rendered worlds' exact flow on the central test pairs, by frame "
        "offset (target − source) and image region, at the render resolution; Fl is KITTI's "
        "outlier rate (end-point error above 3 px and 5 % of the motion).",
        "",
        Table([Column(h) for h in heads], rows).markdown(),
        "",
    ], fig


def _causes_sections(
    study: S.Study,
    views: dict,
    twin: dict | None,
    size: dict,
    settled: Settled,
    figdir: Path,
    made: list[str],
) -> list[str]:
    """The causes separated (:mod:`mfg_lightning.study.causes`): the exact-flow twin, Table 2 on
    exact flow beside DIS, the size curve (``size``: its results by name); their figures
    written and added to ``made``."""
    from mfg_lightning.study import causes

    twin_lines, twin_fig = causes.twin_section(views, twin, study.cached("methods"))
    size_lines, size_fig = causes.size_section(size)
    for lines, fig, name in ((twin_lines, twin_fig, "twin.png"), (size_lines, size_fig,
                                                                  "size.png")):  # fmt: skip
        if fig is not None:
            lines[2] += " " + _figure(figdir, name, fig)
            made.append(name)
    settle_lines, settle_fig = settle_section(settled)
    if settle_fig is not None:
        settle_lines[2] += " " + _figure(figdir, "settle.png", settle_fig)
        made.append("settle.png")
    t2 = causes.table2_flow_section(study.cached("table2_exact"), study.cached("table2"))
    learned = causes.learned_section(
        views, twin, study.cached("learned"), study.cached("flow_error"), study_flow_name(study)
    )
    stale = {n: study.cached(n) for n in ("twin", "table2", "table2_exact")}
    stale["size/classical"] = study.cached("size/classical")
    return [*twin_lines, *learned, *settle_lines, *t2, *size_lines, *stale_essential(stale)]


def study_flow_name(study: S.Study) -> str:
    """The study's own flow as the report names it (``flow=dis``: DIS)."""
    chosen = [str(d).split("=", 1)[1] for d in study.cfg.data if str(d).startswith("flow=")]
    name = chosen[-1] if chosen else "dis"
    return {"dis": "DIS", "exact": "exact"}.get(name, name)


def _pending(study: S.Study) -> list[str]:
    """The configured stages whose result is not cached yet, in the order the study runs them
    (what a reader should not look for in the report yet)."""
    cfg = study.cfg
    names = [
        "data", "flow_error", "main", "table1", "basis", "object_motion", "methods",
        *[f"seeds/seed{int(s)}" for s in cfg.seeds.extra], "twin", "learned", "table2",
        "table2_exact",
        *[f"settle_classical/{f}" for f in cfg.settle.flows],
        *[f"settle/{f}_seed{s}" for f, s in T.seed_runs(cfg)],
        *[f"settle/strided_seed{s}" for s in T.strided_runs(cfg)],
        *[f"size/{S.size_name(*p)}" for p in S.size_runs(cfg)], "size/classical",
        *[f"sparsity/{v[0]}" for v in S.sparsity_variants(cfg)], "balance", "recipe",
    ]  # fmt: skip
    missing = [n for n in names if study.cached(n) is None]
    if not missing:
        return ["Every stage has run.", ""]
    return [f"Not run yet, in the study's order: {', '.join(f'`{n}`' for n in missing)}.", ""]


def _verdict_figure(judged: list[Judged]) -> Any:
    """Every judged part's interval against its bound, on one axis: the distance from the bound
    in half-widths of the part's own interval, signed so that the claimed side is on the left
    for every part (holds: the whole bar left of 0; does not hold: right of it)."""
    from matplotlib.figure import Figure

    parts = [(j.sentence.key, p) for j in judged for p in j.parts if p.judged is not None]
    if not parts:
        return None
    lim = 6.0
    colour = {"holds": "tab:green", "does not hold": "tab:red"}
    fig = Figure(figsize=(10, 0.32 * len(parts) + 1.8))
    ax = fig.subplots()
    for i, (_, p) in enumerate(parts):
        iv = p.judged
        half = max((iv.hi - iv.lo) / 2, 1e-300)
        sign = 1.0 if p.direction == "<=" else -1.0
        centre = sign * (iv.value - p.bound) / half
        c = colour.get(p.verdict, "0.5")
        shown = min(max(centre, -lim), lim)
        if iv.hi == iv.lo:
            # no spread at all (the same value in every seed and pair): a point, not a bar
            ax.plot(shown, i, "D", color=c)
            continue
        lo, hi = max(centre - 1, -lim), min(centre + 1, lim)
        if lo < hi:
            ax.plot([lo, hi], [i, i], color=c, lw=4, solid_capstyle="butt")
        ax.plot(shown, i, "o" if shown == centre else ">" if centre > lim else "<", color=c)
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_xlim(-lim - 0.5, lim + 0.5)
    ax.set_yticks(range(len(parts)))
    # S10's bins name their size and speed last: shortened so that the tick label keeps them
    short = [p.label.replace("velocity error, ", "").replace(" of the image", "") for _, p in parts]
    ax.set_yticklabels([f"{k} {lab[:70]}" for (k, _), lab in zip(parts, short, strict=True)],
                       fontsize=7)  # fmt: skip
    ax.set_xlabel(
        "distance from the bound, in half-widths of the part's 95 % interval\n"
        "(left of 0: the claimed side; a triangle: beyond the axis; a diamond: no spread)"
    )
    ax.invert_yaxis()
    ax.set_title(
        "Verdicts per part\ngreen holds · red does not hold · grey inconclusive", fontsize=10
    )
    fig.tight_layout()
    return fig


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
    if not stale:
        return []
    return [
        f"The essential-matrix rows of {', '.join(f'`{n}`' for n in stale)} were computed at a "
        "commit without the cheirality fix (`motion.baselines._cheirality_pose`): their "
        "failures on slow pairs in far scenes (a rotation off by π) are that bug's, not the "
        "method's, and their means are too large; the 2 × 2's classical methods "
        "(`settle_classical/*`) have the fix.",
        "",
    ]


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
    return [
        "## The method comparison (every test pair of 09 and 10, DIS flow)",
        "",
        f"The main model against every classical baseline on the {mt['test_pairs']} test pairs "
        f"(±1, ±2; † and RPE from the {mt['forward_pairs']} +1 pairs). The classical methods see "
        "one pair and cannot know the scale: their translation is given the ground-truth length.",
        "",
        Table([Column(h) for h in heads], rows).markdown(),
        "",
        *stale_essential({"methods": mt}),
    ]


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
        row(
            f"paper's print: squared ratio ({balance['steps']} steps)",
            balance.get("test", {}),
            balance.get("basis"),
        ),
    ]
    return [
        "## The balancing weights, two readings (claims 3 and 5)",
        "",
        "The released code weighs the rotational term by the ratio of the fields' norms, the "
        "paper's equation by its square (`model.loss.balance_squared=true`); both clamped at "
        "the same maximum, on the main model's data and rule.",
        "",
        Table([Column(h) for h in heads], rows).markdown(),
        "",
    ]


def _figure(figdir: Path, name: str, fig: Any) -> str:
    atomic_write_bytes(figdir / name, figure_png(fig))
    return f"[{name}]({figdir.name}/{name})"


def _notes(report: Path) -> list[str]:
    """The reading of the results that a person wrote beside the report
    (``<report stem>_notes.md``), kept apart so that a rerun of the study does not overwrite it;
    nothing when there is none."""
    notes = report.with_name(f"{report.stem}_notes.md")
    if not notes.is_file():
        return []
    return ["## Notes", "", notes.read_text().strip(), ""]
