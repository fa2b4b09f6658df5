"""bench/data_preparation.py in its tiny setting, in this process: its section of scaleout.md
between its markers, a row per process count with the CPU kind named, the rest of the file kept,
and a rerun served from the cached stages. The numbers of a tiny run mean nothing."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench_pages import bench_in_this_process, own_section
from mfg_lightning.core.machine import cpu_kind

pytestmark = pytest.mark.slow

OTHER = "# Scale-out: data-parallel training (DDP)\n\n## Training throughput\n\nkeep me\n\n"


def test_data_preparation_writes_its_scaling_section(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threads_kept: None
) -> None:
    bench = bench_in_this_process("data_preparation", "scaleout.md", OTHER, tmp_path, monkeypatch)
    work = tmp_path / "work"
    argv = ["--tiny", "--out", str(tmp_path), "--work", str(work)]
    text = bench.main(argv).read_text()
    section = own_section(text, bench, OTHER)
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
