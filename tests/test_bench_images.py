"""bench/images_to_poses.py in its tiny setting, in this process: it writes its section of
throughput.md between its markers with the expected rows and positive rates, leaves the rest of
the file as it was, and replaces its README line; ``bench/throughput.py``'s rewrite of the file
(``Report.write``) keeps the section. The numbers of a tiny run mean nothing."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from bench_pages import bench_in_this_process, own_section, table_rows
from conftest import bench_module
from mfg_lightning.core.machine import cpu_kind

OTHER = "# Throughput: training, inference, data, memory\n\n## Training\n\nkeep me\n\n"


def test_images_to_poses_writes_its_section(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threads_kept: None
) -> None:
    bench = bench_in_this_process("images_to_poses", "throughput.md", OTHER, tmp_path, monkeypatch)
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\n<!-- images-to-poses:start -->\nSTALE\n<!-- images-to-poses:end -->"
                      "\n\nend\n")  # fmt: skip
    path = bench.main(["--tiny", "--threads", "1", "--out", str(tmp_path), "--readme", str(readme)])
    text = path.read_text()
    # the rest of the file as it was, the section once, before the file's environment
    section = own_section(text, bench, OTHER)
    assert "bench/images_to_poses.py" in section  # the command that wrote it
    rates = table_rows(section, bench.HEADING)
    # DIS's rows, then the learned flow's (the shipped weights) and an end-to-end checkpoint's
    # network at the same size
    flows = (("DIS", "DIS"), ("learned (`flow=learned`)", "learned"),
             ("end-to-end (`experiment=end_to_end`'s network)", "end-to-end"))  # fmt: skip
    assert [(r[1], r[3]) for r in rates] == [
        (flow, pipeline)
        for flow, first in flows
        for pipeline in (
            "MFG: `predict`, end to end (the whole call)",
            "MFG: `predict` after its start-up",
            "MFG: its stages alone",
            f"{first} flow + essential matrix + MAGSAC++ (OpenCV): its stages",
        )
    ]
    for row in rates:
        assert row[0] == "48 × 128" and row[2] == cpu_kind()
        if "after its start-up" in row[3]:
            continue  # a difference of two timings: on a loaded machine and 5 pairs, any sign
        assert float(row[4]) > 0 and float(row[5]) > 0, row
    for flow in ("learned", "end-to-end"):
        net = {r[0]: r for r in table_rows(section, f"### Where the time goes, 48 × 128, {flow}")}
        assert float(net["flow"][2]) > 0 and float(net["network"][2]) > 0
    stages = {r[0]: r for r in table_rows(section, "### Where the time goes, 48 × 128, DIS flow")}
    assert list(stages) == ["read", "flow", "network", "recovery", "composition", "method",
                            "the rest of `predict`", "total"]  # fmt: skip
    for name in ("read", "flow", "network", "recovery", "composition"):
        assert float(stages[name][2]) > 0, stages[name]
    for name in ("read", "flow", "method", "composition"):
        assert float(stages[name][4]) > 0, stages[name]
    classical = sum(float(stages[n][4]) for n in ("read", "flow", "method", "composition"))
    assert math.isclose(float(stages["total"][4]), classical, rel_tol=1e-2, abs_tol=0.03)
    # the README's line between its markers, the rest of the README as it was
    lines = readme.read_text().splitlines()
    assert lines[:3] == ["# x", "", "<!-- images-to-poses:start -->"]
    assert lines[3].startswith("Images to poses: `predict` on a folder of 48 × 128 PNG frames")
    assert "with `flow=learned`" in lines[3] and "; end to end " in lines[3]
    assert re.search(r"CPU cores \(20\d\d-\d\d-\d\d\)\.", lines[3]), "each rate's date"
    assert lines[4:] == ["<!-- images-to-poses:end -->", "", "end"]
    # bench/throughput.py rewriting the file keeps the section
    common = bench_module("_common")
    report = common.Report("throughput", "Throughput: training, inference, data, memory", tmp_path)
    report.add("## Training\n\nnew numbers")
    rewritten = report.write().read_text()
    assert "new numbers" in rewritten and "keep me" not in rewritten
    assert section in rewritten
    assert rewritten.index("<!-- images-to-poses:end -->") < rewritten.index("\n## Environment")


def test_a_marked_block_is_replaced_in_place_or_inserted_before_a_heading() -> None:
    common = bench_module("_common")
    text = "# t\n\n## a\n\n## Environment\n\nx\n"
    once = common.replace_marked(text, "m", "## M\n\none")
    assert once.endswith("<!-- m:start -->\n## M\n\none\n<!-- m:end -->\n")  # no anchor: appended
    before = common.replace_marked(text, "m", "## M\n\none", before="## Environment")
    assert before == "# t\n\n## a\n\n<!-- m:start -->\n## M\n\none\n<!-- m:end -->\n\n" + (
        "## Environment\n\nx\n"
    )
    again = common.replace_marked(before, "m", "## M\n\ntwo", before="## Environment")
    assert again == before.replace("one", "two")
    assert common.marked_blocks(again) == ["<!-- m:start -->\n## M\n\ntwo\n<!-- m:end -->\n"]
