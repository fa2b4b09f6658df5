"""A Hydra multirun tabulated: :func:`write_report` reads its jobs and writes ``report.csv``,
``report.md``, ``seeds.csv`` and the sweep figures (the files are described by
:mod:`mfg_lightning.report`, its command line).

The jobs are read by :mod:`mfg_lightning.analysis.sweeps`, the tables built by
:mod:`mfg_lightning.analysis.result_tables` and the figures drawn by
:mod:`mfg_lightning.analysis.sweep_figures`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mfg_lightning.analysis.result_tables import (
    seeds_csv_table,
    seeds_table,
    sweep_csv_table,
    sweep_table,
)
from mfg_lightning.analysis.sweep_figures import sweep_figures
from mfg_lightning.analysis.sweeps import (
    JobRecord,
    SeedGroup,
    collect_jobs,
    common_overrides,
    optuna_note,
    seed_groups,
    swept_keys,
)
from mfg_lightning.core.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.core.tables import markdown_text
from mfg_lightning.pictures.plots import figure_png

__all__ = ["Report", "report_markdown", "write_report"]


@dataclass
class Report:
    """What :func:`write_report` produced."""

    multirun_dir: Path
    out_dir: Path
    jobs: list[JobRecord]
    swept: list[str]
    csv_path: Path
    markdown_path: Path
    markdown: str
    plots: dict[str, Path]
    skipped_plots: dict[str, str]
    #: groups of jobs that differ only in ``seed`` (empty when no seed is swept)
    seed_groups: list[SeedGroup] = field(default_factory=list)

    @property
    def n_failed(self) -> int:
        return sum(not j.ok for j in self.jobs)


def report_markdown(
    jobs: Sequence[JobRecord],
    swept: Sequence[str],
    title: str = "",
    groups: Sequence[SeedGroup] = (),
    notes: Sequence[str] = (),
) -> str:
    """``report.md``: the title, the common overrides, a row per job (swept values and main
    metrics), the failed jobs with their reasons, warnings, the seed table and the notes."""
    lines = [f"# {title}", ""] if title else []
    common = common_overrides(jobs, swept)
    if common:
        lines += ["Common overrides: " + " ".join(f"`{o}`" for o in common), ""]
    lines.append(sweep_table(jobs, swept).markdown().rstrip())
    failed = [j for j in jobs if not j.ok]
    if failed:
        lines += ["", f"Failed jobs ({len(failed)} of {len(jobs)}):", ""]
        lines += [f"- `{j.name}`: {markdown_text(j.reason)}" for j in failed]
    warned = [j for j in jobs if j.ok and j.reason]
    if warned:
        lines += ["", "Warnings:", ""] + [
            f"- `{j.name}`: {markdown_text(j.reason)}" for j in warned
        ]
    if groups:
        lines += ["", "## Across seeds", "",
                  "Mean ± standard deviation (ddof = 1) over the finished seeds of each group of "
                  "jobs that differ only in `seed`; n counts the finished seeds.", "",
                  seeds_table(groups, swept).markdown().rstrip()]  # fmt: skip
    if notes:
        lines += ["", *notes]
    return "\n".join(lines).rstrip() + "\n"


def write_report(
    multirun_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str] | None = None
) -> Report:
    """Collect the jobs of ``multirun_dir`` and write the CSV, Markdown and PNGs into ``out_dir``
    (default ``<multirun dir>/report``). Everything is computed before the first file is written.

    Raises:
        NotAMultirunError: see :func:`collect_jobs`.
    """
    root = Path(multirun_dir)
    out = Path(out_dir) if out_dir is not None else root / "report"
    jobs = collect_jobs(root, exclude=[out])
    swept = swept_keys(jobs)
    images, skipped = sweep_figures(jobs, swept)
    notes = optuna_note(root)
    notes += [f"Plot not drawn: `{name}` ({why})." for name, why in skipped.items()]
    notes += [f"![{name}]({name})" for name in images]
    n_ok = sum(j.ok for j in jobs)
    title = f"Sweep report: {root.resolve().name} ({n_ok} of {len(jobs)} jobs finished)"
    groups = seed_groups(jobs, swept)
    markdown = report_markdown(jobs, swept, title=title, groups=groups, notes=notes)
    csv_path, md_path = out / "report.csv", out / "report.md"
    pngs = {name: figure_png(fig) for name, fig in images.items()}
    seeds_text = seeds_csv_table(groups, swept).csv() if groups else None
    atomic_write_text(csv_path, sweep_csv_table(jobs, swept).csv())
    atomic_write_text(md_path, markdown)
    if seeds_text is not None:
        atomic_write_text(out / "seeds.csv", seeds_text)
    plots = {name: atomic_write_bytes(out / name, data) for name, data in pngs.items()}
    return Report(root, out, jobs, swept, csv_path, md_path, markdown, plots, skipped, groups)
