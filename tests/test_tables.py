"""The one table writer: the same rows as Markdown, CSV and LaTeX."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

from mfg_lightning.core.tables import Column, Table, fmt


def _table() -> Table:
    columns = [Column("method"), Column("ATE", "m", 3), Column("t_err", "%", 2), Column("poses")]
    return Table(
        columns,
        [["a|b", 0.123456, None, 10], ["x_y & z", 1e-9, float("nan"), 3]],
        title="Sequence 09, sim3 ± 1",
    )


def test_number_format() -> None:
    assert fmt(0.123456) == "0.1235" and fmt(2.5, 1) == "2.5"
    assert fmt(1e-9) == "1.0e-09"  # an error floor is not 0.0000
    assert fmt(0.0) == "0.0000" and fmt(7) == "7"
    assert fmt(None) == fmt(float("nan")) == fmt(math.inf) == "–"


def test_markdown() -> None:
    md = _table().markdown()
    assert md.splitlines() == [
        "**Sequence 09, sim3 ± 1**",
        "",
        "| method | ATE (m) | t_err (%) | poses |",
        "|---|---:|---:|---:|",
        "| a\\|b | 0.123 | – | 10 |",
        "| x_y & z | 1.0e-09 | – | 3 |",
    ]


def test_csv_keeps_full_precision() -> None:
    rows = list(csv.reader(_table().csv().splitlines()))
    assert rows == [
        ["method", "ATE (m)", "t_err (%)", "poses"],
        ["a|b", "0.123456", "", "10"],
        ["x_y & z", "1e-09", "", "3"],
    ]


def test_latex_is_escaped() -> None:
    tex = _table().latex()
    assert "\\caption{Sequence 09, sim3 $\\pm$ 1}" in tex
    assert "\\begin{tabular}{lrrr}" in tex and "\\toprule" in tex and "\\bottomrule" in tex
    assert "method & ATE (m) & t\\_err (\\%) & poses \\\\" in tex
    assert "x\\_y \\& z & 1.0e-09 & -- & 3 \\\\" in tex


def test_write_and_bad_rows(tmp_path: Path) -> None:
    table = _table()
    paths = table.write(tmp_path / "sub" / "table_09")
    assert [p.name for p in paths] == ["table_09.md", "table_09.csv", "table_09.tex"]
    assert paths[0].read_text() == table.markdown() and paths[2].read_text() == table.latex()
    with pytest.raises(ValueError, match="a row of 2 cells for 4 columns"):
        table.add_row(["only", 1.0])
