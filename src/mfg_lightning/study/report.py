"""The report of the reproduction study: one row per claim with its figure, the machine, the
budget and the stages' times, rewritten from every cached stage result."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

from mfg_lightning.core.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.core.paths import portable_overrides
from mfg_lightning.core.tables import Column, Table
from mfg_lightning.flow.cache import default_cache_dir
from mfg_lightning.pictures.plots import figure_png
from mfg_lightning.study import claims as C
from mfg_lightning.study import stages as S
from mfg_lightning.study.verdicts import Thresholds


def _machine() -> dict[str, str]:
    import torch

    from mfg_lightning.run.runs import git_commit

    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 0
    return {
        "commit": (git_commit() or "-")[:12],
        "machine": f"{platform.processor() or platform.machine()}, {cores} cores usable of "
        f"{os.cpu_count()}",
        "torch": f"{torch.__version__} ({torch.get_num_threads()} threads; CUDA "
        f"{'yes' if torch.cuda.is_available() else 'no'})",
        "date (UTC)": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
    }


def write_report(study: S.Study, report: Path, th: Thresholds) -> Path:
    """Rewrite the report from every cached stage; figures into ``<report stem>/``."""
    cfg = study.cfg
    figdir = report.with_suffix("")
    sparsity = {}
    for ws in cfg.sparsity.w_s:
        names = [f"ws{ws:g}"] + (
            [f"ws{ws:g}_scale{cfg.sparsity.input_scale:g}"] if float(ws) == 100 else []
        )
        for n in names:
            if (r := study.cached(f"sparsity/{n}")) is not None:
                label = f"w_s={ws:g}" + (
                    "" if r["plain"] else f", input ×{cfg.sparsity.input_scale:g}"
                )
                sparsity[label] = r
    built = [
        C.claim_table1(study.cached("table1"), th),
        C.claim_sparsity(sparsity, th, float(cfg.sparsity.ate_tolerance)),
        C.claim_table2(study.cached("table2"), th),
        C.claim_robustness(study.cached("robustness")),
        C.claim_basis(study.cached("basis"), float(cfg.basis.residual)),
        C.claim_object_motion(study.cached("object_motion")),
        C.claim_learning_curve(study.cached("learning_curve"), th),
        C.claim_recipe(study.cached("recipe"), th),
    ]
    for row, fig in built:
        if fig is not None:
            name = f"claim{row.number}.png"
            atomic_write_bytes(figdir / name, figure_png(fig))
            row.figure = f"[{name}]({figdir.name}/{name})"
    table = Table(
        [
            Column("#"),
            Column("claim"),
            Column("paper"),
            Column("ours"),
            Column("verdict"),
            Column("figure"),
        ],
        [[r.number, r.claim, r.paper, r.ours, r.verdict, r.figure] for r, _ in built],
    )
    stage_rows = []
    total = 0.0
    for path in sorted(study.work.glob("**/*.json")):
        if path.parent.name == "models" or "models" in path.relative_to(study.work).parts:
            continue
        name = str(path.relative_to(study.work).with_suffix(""))
        r = study.cached(name) or {}
        total += r.get("seconds", 0.0)
        trained = f"{r['steps']} × {r['batch_size']}" if "steps" in r else ""
        stage_rows.append(f"| {name} | {r.get('seconds', 0.0):.0f} | {trained} |")
    main = study.cached("main")
    recipe = main["recipe"] if main else None
    machine = _machine()
    # Paths as a reader finds them (relative, ../shared, <cache>), not this machine's.
    data = " ".join(portable_overrides(cfg.data, Path.cwd(), default_cache_dir()))
    main_overrides = main["overrides"] if main else cfg.main
    main_text = " ".join(portable_overrides(main_overrides, Path.cwd(), default_cache_dir()))
    text = [
        "# Reproduction of the paper's claims",
        "",
        "Produced by `python -m mfg_lightning.reproduce` (one command; every figure below comes "
        "from it): synthetic worlds rendered along the real KITTI trajectories, "
        f"overrides `{data}`; choices made on the validation tails of the training "
        "sequences only, then fixed.",
        "",
        *(f"- **{k}**: {v}" for k, v in machine.items()),
        f"- **main model**: `{main_text}`",
        f"- **budget used**: {total / 60:.1f} min over the stages below (each trained "
        "model's steps × batch in its row, from its cached result), frames per sequence "
        f"{cfg.budget.max_frames or 'all'}",
        "- **recipe**: "
        + (
            f"CPU: batch {recipe['batch_size']}, {recipe['optimizer']} lr {recipe['lr']:g}, betas "
            f"{recipe['betas']}, schedule {recipe['scheduler'] or 'constant'}, "
            f"w_s {recipe['w_s']:g}; "
            "the paper: batch 1, Adam lr 1e-5, betas (0.99, 0.999), constant (row R compares them)."
            if recipe
            else "not run yet"
        ),
        f"- **verdicts**: relative deviation from the paper's figure or ratio, {th.text()}; "
        "otherwise does not hold. Claims of several parts: all met holds, some partly.",
        "",
        table.markdown(),
        *_notes(report),
        "## Stages",
        "",
        "| stage | seconds | trained (steps × batch) |",
        "|---|---:|---:|",
        *stage_rows,
        "",
    ]
    path = atomic_write_text(report, "\n".join(text))
    print(f"wrote {path}", flush=True)
    return path


def _notes(report: Path) -> list[str]:
    """The reading of the results that a person wrote beside the report
    (``<report stem>_notes.md``), kept apart so that a rerun of the study does not overwrite it;
    nothing when there is none."""
    notes = report.with_name(f"{report.stem}_notes.md")
    if not notes.is_file():
        return []
    return ["## Reading the results", "", notes.read_text().strip(), ""]
