"""bench/data_preparation.py in its tiny setting, in this process: its section of scaleout.md
between its markers, a row per process count with the CPU kind named, the rest of the file kept,
and a rerun served from the cached stages. The numbers of a tiny run mean nothing."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from conftest import bench_module
from mfg_lightning.core.machine import cpu_kind

pytestmark = pytest.mark.slow

OTHER = "# Scale-out: data-parallel training (DDP)\n\n## Training throughput\n\nkeep me\n\n"
ENVIRONMENT = "## Environment\n\n| a | b |\n|---|---:|\n| c | d |\n"


def test_data_preparation_writes_its_scaling_section(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threads_kept: None
) -> None:
    monkeypatch.setenv("MFG_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scaleout.md").write_text(OTHER + ENVIRONMENT)
    bench = bench_module("data_preparation")
    monkeypatch.setattr(sys, "argv", ["bench/data_preparation.py", "--tiny"])
    work = tmp_path / "work"
    argv = ["--tiny", "--out", str(tmp_path), "--work", str(work)]
    text = bench.main(argv).read_text()
    assert text.startswith(OTHER) and text.endswith(ENVIRONMENT)
    section = text.split(f"<!-- {bench.MARKER}:start -->")[1].split(f"<!-- {bench.MARKER}:end")[0]
    assert f"## {bench.HEADING}" in section and "### Environment of this section" in section
    assert f"CPU **{cpu_kind()}**" in section
    lines = section.split(f"## {bench.HEADING}")[1].splitlines()
    rows = [ln.strip("|").split("|") for ln in lines if ln.startswith("| ")][1:]
    rows = [[c.strip() for c in r] for r in rows if r[0].strip().isdigit()]
    assert [r[0] for r in rows] == ["1", "2"]
    assert rows[0][1] == "none (this process)" and rows[1][1] == "≥ 2 pairs"
    for row in rows:
        assert row[2] == "22" and float(row[4]) > 0, row  # 2 trajectories of 12 frames
    assert rows[0][5] == "1.00" and rows[0][6] == "100 %"
    # a rerun measures nothing again: the stages are cached under --work
    stages = sorted(work.glob("rate-*.json"))
    assert len(stages) == 2
    before = [p.stat().st_mtime_ns for p in stages]
    bench.main(argv)
    assert [p.stat().st_mtime_ns for p in stages] == before
