"""What the tests of the benchmark scripts share (tests/test_bench*.py): a script's results page
set up in a temporary folder for a run in this process, the script's own section of it read
back, and a table's rows read back from the Markdown a script writes."""

from __future__ import annotations

import sys
from pathlib import Path
from types import ModuleType

import pytest

from conftest import bench_module

#: The environment section that ends a results page; a script's own section goes before it.
ENVIRONMENT = "## Environment\n\n| a | b |\n|---|---:|\n| c | d |\n"


def bench_in_this_process(
    name: str, page: str, other: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> ModuleType:
    """``bench/<name>.py``, imported to run in this process with ``--tiny`` in ``tmp_path`` (its
    working directory, with its flow cache below), where its results page ``page`` holds
    ``other`` and :data:`ENVIRONMENT`."""
    monkeypatch.setenv("MFG_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / page).write_text(other + ENVIRONMENT)
    monkeypatch.setattr(sys, "argv", [f"bench/{name}.py", "--tiny"])
    return bench_module(name)


def own_section(text: str, bench: ModuleType, other: str) -> str:
    """The section of ``bench`` (between its markers) in the page ``text`` it wrote, with its
    heading and its environment; the rest of the page as it was (``other`` before it,
    :data:`ENVIRONMENT` after it), and the section there once."""
    assert text.startswith(other) and text.endswith(ENVIRONMENT)
    assert text.count(f"<!-- {bench.MARKER}:start -->") == 1
    section = text.split(f"<!-- {bench.MARKER}:start -->")[1].split(f"<!-- {bench.MARKER}:end")[0]
    assert f"## {bench.HEADING}" in section and "### Environment of this section" in section
    return section


def table_rows(text: str, heading: str) -> list[list[str]]:
    """The body rows of the first table after ``heading``, as lists of cells."""
    lines = text.split(heading, 1)[1].splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("|"))
    table = []
    for ln in lines[start:]:
        if not ln.startswith("|"):
            break
        table.append([c.strip() for c in ln.strip().strip("|").split("|")])
    return table[2:]  # without the header and the |---| line
