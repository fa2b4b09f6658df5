"""The report's words: Jinja2 templates (``study/templates/``) rendered from the findings.

The templates hold every sentence of the report; the Python code computes the numbers and the
findings they read (:mod:`mfg_lightning.study.findings`). A conclusion word is never typed into a
template: it comes from a filter of :mod:`mfg_lightning.study.wording` applied to the number it
describes (``{{ r | compare }}`` writes "several times worse than" at ×5 and "worse than" at
×1.2).

A template is written in short lines for its reader; :func:`unwrap` joins a paragraph's lines
into one Markdown line, as the report has always printed them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jinja2

from mfg_lightning.core.tables import Column, Table, fmt
from mfg_lightning.study import wording
from mfg_lightning.study.noise import ratio

__all__ = ["TEMPLATES", "lines", "paragraph", "table", "unwrap"]

#: The templates' folder (shipped in the wheel with the package: ``[tool.hatch.build]``).
TEMPLATES = Path(__file__).with_name("templates")


def _times(x: float | None, digits: int = 2) -> str:
    """A ratio as the report prints it: ``×1.23`` (``×–`` when undefined)."""
    return f"×{fmt(x, digits)}"


def _plural(n: int, word: str = "", many: str = "s") -> str:
    """``word`` with ``many`` appended unless ``n`` is 1 ("seed" / "seeds")."""
    return word + (many if n != 1 else "")


def _environment() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        undefined=jinja2.StrictUndefined,  # a finding the template names must exist
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=False,
        autoescape=False,  # Markdown, not HTML
    )
    env.filters.update(
        fmt=fmt,
        times=_times,
        plural=_plural,
        count=wording.count,
        percent=wording.percent,
        spelled=wording.spelled,
        number=wording.number,
        compare=wording.compare,
        change=wording.change,
        position=wording.position,
        side=wording.side,
        rule_met=wording.rule_met,
        recipe_text=wording.recipe_text,
        degrees=math.degrees,
        exp=math.exp,
        tick=lambda x: f"`{x}`",
        sqrt=math.sqrt,
    )
    env.globals.update(ratio=ratio, SAME=wording.SAME, MUCH=wording.MUCH)
    return env


ENV = _environment()


def unwrap(text: str) -> list[str]:
    """The rendered ``text`` as the report's lines: a paragraph's lines joined by a space; a
    table row, a list item or a heading starts its own line; blank lines are kept."""
    out: list[str] = []
    for line in text.split("\n"):
        joins = bool(out) and bool(out[-1]) and bool(line)
        if joins and not out[-1].startswith(("|", "#")) and not line.startswith(("|", "- ", "#")):
            out[-1] += " " + line
        else:
            out.append(line)
    return out


def lines(template: str, **findings: Any) -> list[str]:
    """``template`` (a path under :data:`TEMPLATES`) rendered from ``findings``, as lines."""
    return unwrap(ENV.get_template(template).render(**findings))


def paragraph(template: str, **findings: Any) -> str:
    """``template`` rendered from ``findings`` as one paragraph (no line breaks)."""
    return " ".join(x for x in lines(template, **findings) if x)


def table(heads: Any, rows: list) -> str:
    """A Markdown table of ``heads`` and ``rows`` (cells as text), as a template inserts it."""
    return Table([Column(h) for h in heads], rows).markdown()
