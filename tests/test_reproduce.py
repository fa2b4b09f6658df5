"""``python -m mfg_lightning.reproduce``: the tiny study end to end (a real subprocess, real
trainings on KITTI trajectories), resumed with every stage cached; verdicts against hand values."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mfg_lightning.study.verdicts import (
    HOLDS,
    NOT_HOLD,
    PARTLY,
    Thresholds,
    count_verdict,
    relative_deviation,
    relative_verdict,
    worst,
)

REPO = Path(__file__).resolve().parents[1]
POSES = REPO.parent / "shared" / "data" / "kitti_odometry" / "poses"


def _run(tmp: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "mfg_lightning.reproduce", *args, f"hydra.run.dir={tmp / 'hydra'}"],
        capture_output=True, text=True, env=env, cwd=tmp, timeout=900,
    )  # fmt: skip


def test_verdicts_against_hand_values() -> None:
    th = Thresholds(0.05, 0.20)
    assert relative_deviation(0.0126, 0.012) == pytest.approx(0.05)
    assert relative_verdict(0.0125, 0.012, th) == HOLDS  # 4.2 %
    assert relative_verdict(0.0140, 0.012, th) == PARTLY  # 16.7 %
    assert relative_verdict(0.0148, 0.012, th) == NOT_HOLD  # 23.3 %
    assert relative_verdict(0.0100, 0.012, th) == PARTLY  # 16.7 % below
    assert relative_verdict(None, 0.012, th) == NOT_HOLD
    assert relative_verdict(math.nan, 1.0, th) == NOT_HOLD
    assert worst([HOLDS, PARTLY, HOLDS]) == PARTLY
    assert worst([HOLDS, NOT_HOLD, PARTLY]) == NOT_HOLD
    assert count_verdict(2, 2) == HOLDS
    assert count_verdict(1, 3) == PARTLY
    assert count_verdict(0, 2) == NOT_HOLD
    with pytest.raises(ValueError, match="holds <= partly"):
        Thresholds(0.3, 0.2)


def test_bad_config_is_one_error_line(tmp_path: Path) -> None:
    res = _run(tmp_path, "reproduce=tiny", "poses_dir=null", f"work_dir={tmp_path / 'w'}")
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith("error: poses_dir")


@pytest.mark.skipif(not POSES.is_dir(), reason="KITTI poses not found beside the repository")
def test_tiny_study_runs_and_resumes(tmp_path: Path) -> None:
    work, report = tmp_path / "work", tmp_path / "out" / "reproduction.md"
    args = ("reproduce=tiny", f"poses_dir={POSES}", f"work_dir={work}", f"report={report}")
    first = _run(tmp_path, *args)
    assert first.returncode == 0, first.stderr[-3000:]
    text = report.read_text()
    rows = [line for line in text.splitlines() if line.startswith("| ") and ".png" in line]
    assert [r.split("|")[1].strip() for r in rows] == ["1", "2", "3", "4", "5", "6", "7", "R"]
    for r in rows:
        assert any(v in r for v in (HOLDS, PARTLY, NOT_HOLD)) and "not run yet" not in r
        png = report.parent / r.split("](")[1].split(")")[0]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 1000
    assert "commit" in text and "cores" in text and "torch" in text
    checkpoints = {p: p.stat().st_mtime_ns for p in work.glob("models/*/checkpoints/*.ckpt")}
    assert len({p.parts[-3] for p in checkpoints}) == 7  # main, 3 sparsity, table2, 2 recipes

    second = _run(tmp_path, *args)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "ran:" not in second.stdout and "cached: main" in second.stdout
    assert {p: p.stat().st_mtime_ns for p in work.glob("models/*/checkpoints/*.ckpt")} == (
        checkpoints
    )
    assert report.read_text().split("## Stages")[1] == text.split("## Stages")[1]


def test_a_run_whose_val_ate_was_never_defined_is_evaluated_at_its_last_checkpoint(
    tmp_path: Path,
) -> None:
    """Validation on every 3rd frame has no five-frame snippet: val/ate is NaN at every
    validation, and the "best" checkpoint is merely the first. The study takes last.ckpt then,
    and the best one when some validation defined val/ate."""
    from mfg_lightning.study.stages import chosen_checkpoint

    ckpts = tmp_path / "checkpoints"
    ckpts.mkdir()
    for name in ("best-000500.ckpt", "last.ckpt"):
        (ckpts / name).write_bytes(b"")
    (tmp_path / "csv").mkdir()
    log = tmp_path / "csv" / "metrics.csv"
    log.write_text(
        "step,train/loss,val/ate,val/ate_central\n0,1.0,,\n499,,nan,0.13\n999,,nan,0.05\n"
    )
    assert chosen_checkpoint(tmp_path) == (
        ckpts / "last.ckpt",
        "last (val/ate undefined at every validation)",
    )
    log.write_text("step,val/ate\n499,0.2\n999,nan\n")
    assert chosen_checkpoint(tmp_path) == (ckpts / "best-000500.ckpt", "val/ate")
    (ckpts / "best-000500.ckpt").unlink()
    assert chosen_checkpoint(tmp_path) == (ckpts / "last.ckpt", "last (no validation)")


def test_learning_curve_falls_back_to_the_centre_frame_ate_when_the_chain_is_undefined() -> None:
    from mfg_lightning.study.claims import claim_learning_curve

    th = Thresholds(holds=0.05, partly=0.20)
    pts = [
        {"samples": s, "val/ate": math.nan, "val/ate_central": a, "val/rpe_trans": 0.1}
        for s, a in ((100, 0.2), (300, 0.104), (400, 0.1))
    ]
    row, fig = claim_learning_curve({"points": pts, "test_ate": 0.05}, th)
    assert row.ours.startswith("val ATE * (no † ATE") and "0.1040 (75 %)" in row.ours
    assert row.verdict == HOLDS and fig is not None  # 4 % over the last quarter
    pts = [{**p, "val/ate": 2 * p["val/ate_central"]} for p in pts]
    row, _ = claim_learning_curve({"points": pts, "test_ate": 0.05}, th)
    assert row.ours.startswith("val ATE † 0.4000") and "0.2080 (75 %)" in row.ours
