"""The report needs no git history: a stage result says itself which version of the classical
baselines computed it (``baselines_version``), so an unpacked release or a copy without
``.git`` flags the same stale essential-matrix rows as a full checkout, and no others."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import KITTI_POSES, NO_KITTI_POSES, REPO, entry_point_env, run_command
from mfg_lightning.motion.baselines import VERSION
from mfg_lightning.study.report import ESSENTIAL_FIX, stale_essential

RESULTS = REPO / "bench" / "results" / "reproduction"
POSES = KITTI_POSES
#: The stages whose essential-matrix rows the report checks (report.stale_essential's callers).
CHECKED = ("methods", "twin", "table2", "table2_exact", "size/classical")


def test_stale_rows_come_from_the_result_not_from_git(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", "")  # no git to ask
    assert VERSION >= ESSENTIAL_FIX  # what a stage records now has the fix
    assert stale_essential({"a": {"commit": "0" * 12, "baselines_version": VERSION}}) == []
    note = stale_essential({
        "fixed": {"commit": None, "baselines_version": ESSENTIAL_FIX},
        "before": {"commit": "226e6b3cd5b6", "baselines_version": ESSENTIAL_FIX - 1},
        "unrecorded": {"commit": "226e6b3cd5b6"},  # predates the record: not known to be fixed
        "not run": None,
    })  # fmt: skip
    assert "`before`, `unrecorded`" in note[0] and "`fixed`" not in note[0]


def _stale_named(report: str) -> set[str]:
    """The stages the report's notes (under the method comparison and the causes) name stale."""
    notes = [s for s in report.splitlines() if s.startswith("The essential-matrix rows of ")]
    return {n for s in notes for n in re.findall(r"`([\w/]+)`", s.split(" were computed")[0])}


@pytest.mark.slow
@pytest.mark.skipif(not POSES.is_dir(), reason=NO_KITTI_POSES)
def test_a_copy_without_git_rebuilds_the_report_and_flags_only_what_its_results_say(
    tmp_path: Path,
) -> None:
    """The package, its configs and the committed stage results copied where no git history
    is: ``stages=[]`` rebuilds the report without training, and the stages flagged stale are
    exactly those whose results record baselines before the fix (not every stage, as when
    staleness was asked of git)."""
    root = tmp_path / "release"
    shutil.copytree(REPO / "src", root / "src", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(REPO / "conf", root / "conf")
    results = root / "bench" / "results" / "reproduction"
    shutil.copytree(RESULTS, results, ignore=shutil.ignore_patterns("*.png"))
    env = entry_point_env(root, PYTHONPATH=str(root / "src"), GIT_CEILING_DIRECTORIES=str(tmp_path))
    git = run_command(["git", "rev-parse", "--git-dir"], cwd=root, env=env, timeout=30)
    assert git.returncode != 0, "the copy must not be inside a git checkout"
    probe = "import mfg_lightning; print(mfg_lightning.__file__)"
    where = run_command([sys.executable, "-c", probe], cwd=root, env=env, timeout=60)
    assert where.stdout.strip().startswith(str(root)), where.stdout + where.stderr

    report = root / "bench" / "results" / "reproduction.md"
    proc = run_command(
        [sys.executable, "-m", "mfg_lightning.reproduce", f"poses_dir={POSES}", "stages=[]",
         f"results_dir={results}", f"report={report}", f"work_dir={tmp_path / 'work'}",
         "readme=null"],
        cwd=root, env=env, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "ran:" not in proc.stdout  # rebuilt from the results: no stage ran
    text = report.read_text()
    assert "- **commit**: -" in text  # no git: the report says so and goes on

    recorded = {n: json.loads((results / f"{n}.json").read_text()) for n in CHECKED}
    expected = {n for n, r in recorded.items() if r.get("baselines_version", 1) < ESSENTIAL_FIX}
    assert "size/classical" not in expected  # computed after the fix: git-less, it was flagged
    assert _stale_named(text) == expected

    # the same copy with every result recording the fixed baselines: nothing is flagged
    for n, r in recorded.items():
        r["baselines_version"] = ESSENTIAL_FIX
        (results / f"{n}.json").write_text(json.dumps(r, indent=1) + "\n")
    subprocess.run(proc.args, cwd=root, env=env, timeout=600, check=True, capture_output=True)
    assert _stale_named(report.read_text()) == set()
    assert "were computed at a commit without the cheirality fix" not in report.read_text()
