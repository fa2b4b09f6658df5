"""``python -m mfg_lightning.reproduce``: the tiny study end to end (a real subprocess, real
trainings on KITTI trajectories), resumed with every stage cached; verdicts against hand values."""

from __future__ import annotations

import json
import math
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import KITTI_POSES, NO_KITTI_POSES, entry_point_env, run_command
from mfg_lightning.study.intervals import HOLDS, INCONCLUSIVE, NO_VERDICT, NOT_HOLD, PARTLY
from mfg_lightning.study.verdicts import relative_deviation

REPO = Path(__file__).resolve().parents[1]
VERDICTS = (HOLDS, PARTLY, NOT_HOLD, INCONCLUSIVE, NO_VERDICT)
POSES = KITTI_POSES


def _run(tmp: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "mfg_lightning.reproduce", *args, f"hydra.run.dir={tmp / 'hydra'}"],
        capture_output=True, text=True, env=env, cwd=tmp, timeout=900,
    )  # fmt: skip


def test_relative_deviation_against_hand_values() -> None:
    assert relative_deviation(0.0126, 0.012) == pytest.approx(0.05)
    assert relative_deviation(0.0100, 0.012) == pytest.approx(1 / 6)
    assert relative_deviation(None, 0.012) == math.inf
    assert relative_deviation(math.nan, 1.0) == math.inf
    assert relative_deviation(0.3, 0.0) == pytest.approx(0.3)


def test_bad_config_is_one_error_line(tmp_path: Path) -> None:
    """The full study on KITTI's trajectories without their poses: refused by key when its
    first stage needs them, before anything is trained."""
    res = _run(tmp_path, "poses_dir=null", "start_from=null", f"work_dir={tmp_path / 'w'}",
               f"results_dir={tmp_path / 'r'}", f"report={tmp_path / 'r.md'}")  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith("error: poses_dir")
    assert not (tmp_path / "w" / "models").exists()


def _readme_tiny_command() -> list[str]:
    """The tiny study's command exactly as the README gives it in a code block (its comment
    dropped)."""
    code = (REPO / "README.md").read_text().split("```")[1::2]  # the fenced blocks' insides
    for line in (line for block in code for line in block.splitlines()):
        if line.startswith("python -m mfg_lightning.reproduce") and "reproduce=tiny" in line:
            argv = shlex.split(line.split("#")[0])
            return [sys.executable if argv[0] == "python" else argv[0], *argv[1:]]
    raise AssertionError("README.md gives no `python -m mfg_lightning.reproduce reproduce=tiny`")


def _clean_checkout(tmp: Path) -> Path:
    """The repository's files (tracked, and untracked ones git does not ignore) committed in a
    new git repository: a clean checkout whose ``git status`` a command can be held to."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, capture_output=True, check=True,
    ).stdout.decode().split("\0")  # fmt: skip
    root = tmp / "checkout"
    for name in filter(None, listed):
        if (REPO / name).is_file():
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, root / name)
    for git in (["init", "-q"], ["add", "-A"], ["commit", "-q", "-m", "checkout"]):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *git], cwd=root,
                       check=True, capture_output=True)  # fmt: skip
    return root


@pytest.mark.slow  # the whole study, tiny: ~100 s on 2 cores
def test_tiny_study_runs_resumes_and_rebuilds_from_committed_results(tmp_path: Path) -> None:
    """The README's tiny command in a clean checkout: it writes its results and report under
    outputs/ and leaves ``git status`` clean (no poses needed: procedural trajectories). Then
    again (every stage cached, nothing retrained); then as a fresh clone sees it: the stage
    results only (a new, empty work_dir, no checkpoint, no flow cache), which rebuild the same
    report without training anything; a run of other settings refuses the folder, by key."""
    root = _clean_checkout(tmp_path)
    env = entry_point_env(tmp_path, PYTHONPATH=str(root / "src"))  # the cache: outside it
    command = _readme_tiny_command()

    def run(*extra: str) -> subprocess.CompletedProcess:
        return run_command([*command, *extra], cwd=root, env=env, timeout=1200)

    first = run()
    assert first.returncode == 0, first.stderr[-3000:]
    status = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True,
                            text=True, check=True)  # fmt: skip
    assert status.stdout == "", status.stdout
    results = root / "outputs" / "reproduce_tiny" / "reproduction"
    report = root / "outputs" / "reproduce_tiny" / "reproduction.md"
    work = tmp_path / "cache" / "reproduce_tiny"
    text = report.read_text()
    assert "../" not in text.split("## Verdicts")[0]  # the header names no path outside
    # one verdict per quoted sentence of the paper, each judged on the tiny study's results
    verdicts = text.split("## Verdicts, one per sentence of the paper")[1].split("\n## ")[0]
    rows = [line for line in verdicts.splitlines() if line.startswith("| S")]
    assert [r.split("|")[1].strip() for r in rows] == [f"S{i}" for i in range(1, 11)]
    for r in rows:
        assert r.split("|")[-2].strip() in VERDICTS, r
        # every judged part gives its 95 % interval, or says why it has none
        assert "“" in r and any(x in r for x in ("] ", "no verdict", "not measured")), r
    # the main model at its two seeds in the headline table
    assert "| quantity | seed 0 | seed 1 | mean ± sd |" in text
    # the diagnostics, each with its figure and without a verdict
    diag = text.split("## Diagnostics")[1].split("###")[0]
    rows = [line for line in diag.splitlines() if line.startswith("| ") and ".png" in line]
    assert [r.split("|")[1].strip() for r in rows] == ["1", "2", "3", "4", "5", "6", "R"]
    for r in rows:
        assert "not run yet" not in r
        png = report.parent / r.split("](")[1].split(")")[0]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 1000
    assert "## Did it converge" in text and "## Reading the results" in text
    assert "commit" in text and "cores" in text and "torch" in text
    # every trained model's convergence row, and no absolute path of this machine
    conv = text.split("## Did it converge")[1].split("## ")[0]
    for name in ("main", "main, seed 1", "exact-flow twin", "learned", "table2", "table2_exact",
                 "size stride4", "size stride2", "balance_squared", "sparsity w_s=0",
                 "recipe paper", "table2 exact, seed 1", "table2 strided, seed 0",
                 "rotation rule, exact, seed 1", "rotation rule, unclamped, seed 0",
                 "rotation rule, largest, seed 1", "end to end: joint, seed 0",
                 "end to end: frozen, seed 0"):  # fmt: skip
        assert f"| {name} |" in conv, name
    assert str(tmp_path) not in text
    # the causes separated: the exact-flow twin, Table 2 on exact flow beside the study's flow,
    # the size curve, each with its table (and figure)
    for head, png in (("## The flow against the method", "twin.png"),
                      ("## Table 2's setting on exact flow", None),
                      ("## The learned flow: the main setting on flow=learned", None),
                      ("## Table 2's setting at every seed", "settle.png"),
                      ("## Table 2's setting trained until validation rotation", None),
                      ("## Images to egomotion trained end to end", "end_to_end.png"),
                      ("## Claim 3's data size", "size.png")):  # fmt: skip
        section = text.split(head)[1].split("\n## ")[0]
        assert "|---" in section, head
        assert png is None or f"(reproduction/{png})" in section, head
    assert "S9: The exact-flow Table-2-sized models (2 seeds)" in text
    # the 2 × 2's verdicts read the converged models, S9 and S10 on the object test set
    assert "(S4–S6, S9, S10) read these converged models" in text
    assert "They are tested on the object test set" in text
    assert "S4: Table 2's setting (" in text and "training pairs) at 2 seeds on exact flow" in text
    checkpoints = {p: p.stat().st_mtime_ns for p in work.glob("models/*/checkpoints/*.ckpt")}
    # main, its second seed, its exact-flow twin, its learned-flow run, table2 on both flows,
    # the size curve's two strides, 4 sparsity models (w_s 0, 100, input scale, low rate),
    # balance, 2 recipes: the tiny main model runs past the other models' 2-step cap, so no
    # model reuses its run
    assert {p.parts[-3] for p in checkpoints} == {
        "main", "seed1", "twin", "learned", "table2", "table2_exact", "size_stride4",
        "size_stride2", "ws0", "ws100", "ws100_scale0.2", "ws100_lr0.0001", "balance_squared",
        "recipe_cpu", "recipe_paper", "settle_exact_seed0", "settle_exact_seed1",
        "settle_strided_seed0", *(f"converge_{v}_seed{s}" for v in ("exact", "unclamped",
        "largest") for s in (0, 1)), "e2e_two_stage_seed0", "e2e_joint_seed0", "e2e_frozen_seed0",
    }  # fmt: skip
    recipe = json.loads((results / "recipe.json").read_text())
    assert "same_as" not in recipe["cpu"] and recipe["cpu"]["epochs"] >= 0.5
    assert recipe["paper"]["epochs"] >= 0.5 and recipe["paper"]["batch_size"] == 1
    stage_files = sorted(p.relative_to(results) for p in results.glob("**/*.json"))
    # 20, and the 2 × 2's: the classical methods, two seeds and one strided seed; the rotation
    # rule's 3 variants at 2 seeds and the object test set's 2 evaluations; the end-to-end
    # comparison's three models and its flow reference
    assert len(stage_files) == 36
    # a rule on validation rotation evaluates the schedule's end: the best checkpoints rank val/ate
    for f in ("exact_seed0", "unclamped_seed1", "largest_seed0"):
        rule = json.loads((results / "converge" / f"{f}.json").read_text())
        assert rule["selected_on"] == "last (rule on val/rot_err)", f
        assert rule["checkpoint"].endswith("checkpoints/last.ckpt"), f
    for f in stage_files:
        assert str(tmp_path) not in (results / f).read_text(), f

    second = run()
    assert second.returncode == 0, second.stderr[-3000:]
    assert "ran:" not in second.stdout and "cached: main" in second.stdout
    assert {p: p.stat().st_mtime_ns for p in work.glob("models/*/checkpoints/*.ckpt")} == (
        checkpoints
    )
    assert report.read_text().split("## Stages")[1] == text.split("## Stages")[1]

    other = run("budget.main_steps=7")
    assert other.returncode == 2 and "budget.main_steps: 6 there, 7 here" in other.stderr

    fresh = tmp_path / "fresh_work"
    third = run(f"work_dir={fresh}")
    assert third.returncode == 0, third.stderr[-3000:]
    # nothing trained: the new work_dir holds only the procedural poses the study wrote
    assert "ran:" not in third.stdout and not (fresh / "models").exists()
    rebuilt = report.read_text()
    assert rebuilt.split("## Verdicts")[1] == text.split("## Verdicts")[1]

    # Row R on a fresh clone whose main model met the rule within the other caps: the CPU
    # recipe is the main model, scored by Table 1's k = 100 % row, and the main model is not
    # trained again for it (only the paper recipe trains)
    served = tmp_path / "served"
    shutil.copytree(results, served)
    (served / "recipe.json").unlink()
    main = json.loads((served / "main.json").read_text())
    main["convergence"]["converged"] = True
    main["steps"] = 2  # within the other models' step cap (budget.other_steps)
    (served / "main.json").write_text(json.dumps(main))
    fourth = run(f"results_dir={served}", f"report={tmp_path / 'served.md'}",
                 f"work_dir={tmp_path / 'served_work'}", "stages=[recipe]")  # fmt: skip
    assert fourth.returncode == 0, fourth.stderr[-3000:]
    assert "ran: recipe" in fourth.stdout
    trained = {p.parts[-3] for p in (tmp_path / "served_work").glob("models/*/checkpoints/*")}
    assert trained == {"recipe_paper"}
    cpu = json.loads((served / "recipe.json").read_text())["cpu"]
    t1 = json.loads((served / "table1.json").read_text())
    assert cpu["same_as"] == "main"
    assert (cpu["val_ate"], cpu["test_ate"]) == (t1["val"]["1"]["ate"], t1["test"]["1"]["ate"])

    # Results whose classical rows predate a fix of the baselines: the report marks them stale;
    # refresh_classical computes those rows again (no model, no training), keeps the MFG rows
    # as they were, and the report no longer marks them
    old = tmp_path / "old"
    shutil.copytree(results, old)
    for name, key in (("methods", "rows"), ("table2", "classical")):
        r = json.loads((old / f"{name}.json").read_text())
        r["baselines_version"] = 1
        for row in r[key]:
            row["metrics"]["rpe_rot"] = 9.5  # a row this result's data could not have given
        (old / f"{name}.json").write_text(json.dumps(r))
    stale_args = (f"results_dir={old}", "stages=[]", f"report={tmp_path / 'old.md'}",
                  f"work_dir={tmp_path / 'old_work'}")  # fmt: skip
    fifth = run(*stale_args)
    assert fifth.returncode == 0, fifth.stderr[-3000:]
    stale_note = "were computed at a commit without the cheirality fix"
    assert stale_note not in text
    marked = (tmp_path / "old.md").read_text()
    assert all(f"rows of `{n}` {stale_note}" in marked for n in ("methods", "table2"))
    sixth = run(*stale_args, "refresh_classical=[methods,table2,twin]")
    assert sixth.returncode == 0, sixth.stderr[-3000:]
    assert "refreshed: methods" in sixth.stdout and "refreshed: table2" in sixth.stdout
    assert "refreshed: twin" not in sixth.stdout  # already current
    assert not (tmp_path / "old_work" / "models").exists()  # nothing trained
    assert stale_note not in (tmp_path / "old.md").read_text()
    for name, key in (("methods", "rows"), ("table2", "classical")):
        rows = json.loads((results / f"{name}.json").read_text())[key]
        before = {r["name"]: r["metrics"] for r in rows}
        after = json.loads((old / f"{name}.json").read_text())
        assert after["baselines_version"] >= 2 and after["classical_refresh"]["from_version"] == 1
        for row in after[key]:
            m = row["metrics"]
            if row["name"].startswith("MFG"):
                assert m["rpe_rot"] == 9.5  # the model's rows are not recomputed
            elif "essential" not in row["name"]:  # deterministic: the same numbers as before
                assert m == pytest.approx(before[row["name"]], rel=1e-6, nan_ok=True), row["name"]
            else:
                assert m["rpe_rot"] < 9.5


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


def test_diagnostics_on_hand_made_results() -> None:
    """The diagnostics print each deviation from the paper and no verdict; a recipe shorter than
    one epoch says so; a collapsed sweep model is reported as collapsed."""
    from mfg_lightning.study import claims as C

    full = {"rpe_trans": 0.1, "rpe_rot": 0.00308}
    mfg = {"1": full, **{f"{k:g}": {"rpe_trans": 0.1 * r, "rpe_rot": 0.003}
                         for k, r in ((0.25, 1.0), (0.2, 1.01), (0.15, 1.07), (0.1, 1.61),
                                      (0.05, 3.94))}}  # fmt: skip
    t2 = {
        "mfg": mfg,
        "classical": [{"name": "MAGSAC++", "metrics": {"rpe_trans": 0.2, "rpe_rot": 0.00193}}],
        "train_pairs": 10,
        "test_pairs": 5,
        "overrides": ["flow=exact"],
    }
    row, _ = C.claim_table2(t2)
    assert "exact flow" in row.ours and "5 % ×3.94 (3.94, " in row.ours
    assert "MAGSAC++ 0.00193" in row.ours and not hasattr(row, "verdict")
    row, _ = C.claim_recipe(
        {
            "cpu": {"epochs": 0.2, "val_ate": 1.0, "test_ate": 1.0, "recipe": {"batch_size": 16,
                    "lr": 1e-3}, "curve": []},
            "paper": {"epochs": 0.2, "val_ate": 1.0, "test_ate": 1.0, "recipe": {"batch_size": 1,
                      "lr": 1e-5}, "curve": []},
        },
    )  # fmt: skip
    assert "shorter than one epoch" in row.ours
    sweep_model = {"active_fraction": 0.0, "collapsed": True, "k_star": 1.0, "test_full": 1.03,
                   "test_k_star": 1.03}  # fmt: skip
    t1 = {"val": {"1": {"ate": 0.01}, "0.05": {"ate": 0.0104}, "0.02": {"ate": 0.02}}}
    row, _, sweep = C.claim_sparsity(t1, {"w_s=1000": sweep_model}, 0.05)
    assert "5.0 %" in row.ours
    assert "collapsed" in sweep[0]


def test_main_run_serves_only_a_converged_run_within_the_other_caps() -> None:
    """A model of the main setting reuses the main run only when that run met the rule within
    the other models' step and time caps (else the caps would have made another run)."""
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from mfg_lightning.study.stages import _seconds, main_run_serves

    budget = {"other_steps": 30000, "other_max_time": "00:00:30:00"}
    study = SimpleNamespace(cfg=OmegaConf.create({"budget": budget}))
    main = {"steps": 8000, "train_seconds": 1158.0, "convergence": {"converged": True}}
    assert _seconds("00:01:00:00") == 3600.0 and _seconds(None) == math.inf
    assert main_run_serves(study, main)
    assert not main_run_serves(study, None)
    assert not main_run_serves(study, {**main, "convergence": {"converged": False}})
    assert not main_run_serves(study, {**main, "steps": 30001})
    assert not main_run_serves(study, {**main, "train_seconds": 1801.0})
    # a longer cap of its own (the paper recipe's) admits a longer main run
    assert main_run_serves(study, {**main, "train_seconds": 3000.0}, "00:01:00:00")


@pytest.mark.skipif(not POSES.is_dir(), reason=NO_KITTI_POSES)
def test_the_size_curve_runs_on_the_main_models_frames_only() -> None:
    """The size curve's points: every stride, then the extra seeds at the largest; a stride off
    the main model's training frames (whose pairs the flow cache has) is refused, by key."""
    from mfg_lightning.core.config import compose
    from mfg_lightning.study.plan import check
    from mfg_lightning.study.stages import size_name, size_runs

    cfg = compose("reproduce", [f"poses_dir={POSES}"])
    assert size_runs(cfg) == [(24, None), (12, None), (6, None), (3, None), (24, 1), (24, 2)]
    assert size_name(24, 1) == "stride24_seed1" and size_name(3, None) == "stride3"
    check(cfg)
    with pytest.raises(ValueError, match=r"size\.strides: \[4\] must be positive multiples"):
        check(compose("reproduce", [f"poses_dir={POSES}", "size.strides=[6,4]"]))
