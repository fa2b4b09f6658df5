"""Result tables, written once: the same rows as Markdown, CSV and LaTeX, one number format.

A :class:`Table` holds columns (name, unit, decimals) and rows of cells (text, numbers, or None
for a value that is undefined, e.g. drift on a path shorter than 100 m). Markdown and LaTeX show
numbers with :func:`fmt`; CSV keeps every number at full precision (the shortest text that reads
back to the same float64), with an empty cell for None, so scripts lose nothing.

This module imports the standard library only, so command-line tools stay quick to start.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from mfg_lightning.core.atomic import atomic_write_text

__all__ = ["Column", "Table", "finite_or_none", "fmt", "markdown_text", "pm"]

Cell = str | float | int | None

#: Shown for a value that is undefined (None, NaN or infinite).
MISSING = "–"


def finite_or_none(value: object) -> float | None:
    """A value as a finite float, or None for what is not one (NaN, infinity, text, None):
    the undefined cell of a table and ``null`` in JSON."""
    try:
        f = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def fmt(x: float | int | None, digits: int = 4) -> str:
    """A number for a table: ``digits`` decimals; scientific notation for a non-zero value too
    small to show (an error of 1e-8 is not 0.0000); :data:`MISSING` for None, NaN or infinity.
    Integers are written as they are."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return MISSING
    if isinstance(x, int) and not isinstance(x, bool):
        return str(x)
    x = float(x)
    if x != 0 and abs(x) < 0.5 * 10.0**-digits:
        return f"{x:.1e}"
    return f"{x:.{digits}f}"


def pm(
    mean: float | None, std: float | None, digits: int = 4, std_digits: int | None = None
) -> str:
    """``mean ± std`` for a table cell, each with :func:`fmt` (``std_digits`` defaults to
    ``digits``); :data:`MISSING` alone when the mean is undefined."""
    if fmt(mean) == MISSING:
        return MISSING
    return f"{fmt(mean, digits)} ± {fmt(std, digits if std_digits is None else std_digits)}"


def markdown_text(text: str) -> str:
    """Text for one Markdown table cell or list item: ``|`` escaped, line breaks as spaces."""
    return text.replace("|", "\\|").replace("\n", " ")


@dataclass(frozen=True)
class Column:
    """A table column.

    Attributes:
        name: the heading.
        unit: shown in brackets after the heading (``"m"`` → ``ATE (m)``); empty for none.
        digits: decimals of numbers in Markdown and LaTeX.
    """

    name: str
    unit: str = ""
    digits: int = 4

    @property
    def heading(self) -> str:
        return f"{self.name} ({self.unit})" if self.unit else self.name


def _csv_cell(value: Cell) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
    "±": r"$\pm$",
    "–": "--",
    "°": r"$^\circ$",
    "Δ": r"$\Delta$",
}


def _latex(text: str) -> str:
    return "".join(_LATEX_SPECIAL.get(ch, ch) for ch in text)


@dataclass
class Table:
    """Rows under columns, rendered as Markdown, CSV or LaTeX.

    Attributes:
        columns: the columns.
        rows: one list of cells per row, as many as columns (text, a number, or None).
        title: a caption (LaTeX ``\\caption``; a bold line above the Markdown table).
    """

    columns: Sequence[Column]
    rows: list[list[Cell]] = field(default_factory=list)
    title: str = ""

    def __post_init__(self) -> None:
        for row in self.rows:
            self._check(row)

    def _check(self, row: Sequence[Cell]) -> None:
        if len(row) != len(self.columns):
            raise ValueError(f"a row of {len(row)} cells for {len(self.columns)} columns: {row}")

    def add_row(self, row: Sequence[Cell]) -> None:
        """Append one row (as many cells as columns)."""
        self._check(row)
        self.rows.append(list(row))

    def _shown(self, value: Cell, column: Column) -> str:
        return value if isinstance(value, str) else fmt(value, column.digits)

    def markdown(self) -> str:
        """A GitHub Markdown table (``|`` in cells escaped), the title in bold above it."""

        lines = [f"**{markdown_text(self.title)}**", ""] if self.title else []
        lines.append("| " + " | ".join(markdown_text(c.heading) for c in self.columns) + " |")
        lines.append(
            "|" + "|".join("---" if i == 0 else "---:" for i in range(len(self.columns))) + "|"
        )
        for row in self.rows:
            shown = [
                markdown_text(self._shown(v, c)) for v, c in zip(row, self.columns, strict=True)
            ]
            lines.append("| " + " | ".join(shown) + " |")
        return "\n".join(lines) + "\n"

    def csv(self) -> str:
        """CSV with a header row; numbers at full precision, undefined values empty."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow([c.heading for c in self.columns])
        writer.writerows([[_csv_cell(v) for v in row] for row in self.rows])
        return buf.getvalue()

    def latex(self) -> str:
        """A ``table`` environment with a booktabs ``tabular`` (needs ``\\usepackage{booktabs}``);
        text escaped for LaTeX."""
        spec = "l" + "r" * (len(self.columns) - 1)
        lines = [r"\begin{table}[t]", r"\centering"]
        if self.title:
            lines.append(rf"\caption{{{_latex(self.title)}}}")
        lines += [rf"\begin{{tabular}}{{{spec}}}", r"\toprule"]
        lines.append(" & ".join(_latex(c.heading) for c in self.columns) + r" \\")
        lines.append(r"\midrule")
        for row in self.rows:
            shown = [_latex(self._shown(v, c)) for v, c in zip(row, self.columns, strict=True)]
            lines.append(" & ".join(shown) + r" \\")
        lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
        return "\n".join(lines) + "\n"

    def write(self, stem: str | Path) -> list[Path]:
        """Write ``<stem>.md``, ``<stem>.csv`` and ``<stem>.tex`` (each atomically).

        Returns:
            The three paths.
        """
        stem = Path(stem)
        paths = []
        for suffix, text in (
            (".md", self.markdown()),
            (".csv", self.csv()),
            (".tex", self.latex()),
        ):
            path = stem.with_name(stem.name + suffix)
            atomic_write_text(path, text)
            paths.append(path)
        return paths
