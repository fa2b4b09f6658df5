"""The study's plan drives the study: conf/reproduce.yaml's stage table is the one list of
stages (each stage's runner, its results, what reads them), a stage added to it in a temporary
config runs and is reported with no Python change, and a results folder is never mixed from two
configurations."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf, open_dict

from mfg_lightning.core.config import compose
from mfg_lightning.study import plan
from mfg_lightning.study.quotes import SENTENCES

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results" / "reproduction"


def test_the_stage_table_is_the_one_list_the_study_runs() -> None:
    cfg = compose("reproduce", ["reproduce=tiny"])
    names = plan.stage_names(cfg)
    assert list(cfg.stages) == names  # the default selection is the table itself
    # every column is read: the runner and the results by the plan, read_by by the report
    assert {k for stage in cfg.stage_table.values() for k in stage} == {
        "runner", "results", "read_by"
    }  # fmt: skip
    assert all(callable(plan.runner(cfg, name)) for name in names)
    results = [r for _, r, _ in plan.results(cfg)]
    assert results[:3] == ["data", "flow_error", "main"] and len(set(results)) == len(results)
    assert "seeds/seed1" in results and "settle/strided_seed0" in results
    read = {k for stage in cfg.stage_table.values() for k in stage.read_by}
    assert set(SENTENCES) <= read  # every sentence names the stages it reads
    assert plan.read_by(cfg)["main"][0] == "S1"


def test_a_stage_the_table_names_badly_is_refused_by_key() -> None:
    cfg = compose("reproduce", ["reproduce=tiny"])
    cfg.stage_table.main.runner = "mfg_lightning.study.run.no_such_stage"
    with pytest.raises(ValueError, match=r"stage_table\.main\.runner: .*no_such_stage"):
        plan.check(cfg)


@pytest.mark.slow  # one process's tiny data stage: ~20 s on 2 cores
def test_a_stage_added_to_the_registry_runs_and_is_reported(tmp_path: Path) -> None:
    """A temporary config adds a stage (an existing runner under a new name, and what reads
    it) to the tiny study's table; the study runs it, caches its result under its name and
    lists it, with its readers, in the report. No Python changes."""
    from mfg_lightning.reproduce import reproduce

    extra = tmp_path / "probe.yaml"
    extra.write_text(
        "stage_table:\n"
        "  probe:\n"
        "    runner: mfg_lightning.study.run.stage_data\n"
        "    read_by: [a reader of the probe]\n"
    )
    out = tmp_path / "out"
    where = [f"work_dir={tmp_path / 'work'}", f"results_dir={out / 'results'}",
             f"report={out / 'r.md'}"]  # fmt: skip
    cfg = compose("reproduce", ["reproduce=tiny", *where])
    with open_dict(cfg):  # the composed config is struct: the new stage is a new key
        cfg.merge_with(OmegaConf.load(extra))
    cfg.stages = ["probe"]
    assert [n for _, n, _ in plan.results(cfg)][-1] == "probe"
    report = reproduce(cfg)
    probe = json.loads((out / "results" / "probe.json").read_text())
    assert probe["main"]["train_pairs"] > 0  # the data stage's result, under the new name
    rows = [r for r in report.read_text().splitlines() if r.startswith("| probe |")]
    assert len(rows) == 1 and rows[0].endswith("| a reader of the probe |")
    assert not (out / "results" / "data.json").exists()  # only the selected stage ran


def test_a_results_folder_refuses_results_of_other_settings(tmp_path: Path) -> None:
    cfg = compose("reproduce", ["reproduce=tiny", f"work_dir={tmp_path / 'work'}"])
    results = tmp_path / "results"
    plan.claim_results(cfg, results)
    recorded = yaml.safe_load((results / plan.SETTINGS_FILE).read_text())
    assert recorded["budget"]["main_steps"] == 6 and recorded["poses"] == "procedural"
    assert "results_dir" not in recorded and "statistics" not in recorded
    plan.claim_results(cfg, results)  # the same settings: the folder is this run's
    # a where-to key changes no result; a setting does, and is named
    cfg.report = str(tmp_path / "elsewhere.md")
    plan.claim_results(cfg, results)
    cfg.budget.main_steps = 7
    with pytest.raises(ValueError, match=r"other settings \(budget\.main_steps: 6 there, 7 here\)"):
        plan.claim_results(cfg, results)
    # results with no record of their settings are nobody's: refused too
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "main.json").write_text("{}")
    with pytest.raises(ValueError, match="holds results but no settings.yaml"):
        plan.claim_results(cfg, bare)


def test_a_new_folder_starts_from_the_committed_results_of_its_settings(tmp_path: Path) -> None:
    """The committed results record the default study's settings, so a default run starts from
    them (a fresh clone rebuilds the report without training); another setting starts empty."""
    cfg = compose("reproduce", [f"start_from={RESULTS}"])
    committed = yaml.safe_load((RESULTS / plan.SETTINGS_FILE).read_text())
    assert committed == plan.settings(cfg)
    plan.claim_results(cfg, tmp_path / "same")
    assert (tmp_path / "same" / "main.json").read_text() == (RESULTS / "main.json").read_text()
    assert not list((tmp_path / "same").glob("*.png"))  # the figures are the report's
    cfg.budget.other_steps = 1
    plan.claim_results(cfg, tmp_path / "other")
    assert not list((tmp_path / "other").glob("**/*.json"))


def test_a_model_is_composed_once_and_equal_configs_are_one_model(tmp_path: Path) -> None:
    """Each model's training config is composed once (its data read from it), its settings set
    as numbers; two stages whose composed configs are equal, wherever their runs go, train one
    model (``training_digest``), and a setting that differs makes another."""
    from mfg_lightning.study.plan import main_w_s, sparsity_variants
    from mfg_lightning.study.stages import Study, training_digest

    cfg = compose("reproduce", ["reproduce=tiny", f"work_dir={tmp_path}"])
    study = Study(cfg)
    ws = {"model.loss.w_s": 100.0}
    first = study.train_config("a", list(cfg.main), settings=ws)
    assert study.train_config("a", list(cfg.main), settings=ws) is first
    assert first.model.loss.w_s == 100.0 and isinstance(first.model.loss.w_s, float)
    other = study.train_config("b", list(cfg.main), settings=ws)
    assert other.paths.output_dir != first.paths.output_dir
    assert training_digest(other) == training_digest(first)
    lighter = study.train_config("c", list(cfg.main), settings={"model.loss.w_s": 10.0})
    assert training_digest(lighter) != training_digest(first)
    # the sweep's variants carry w_s as a number; the input scale is tried at the main setting's
    assert main_w_s(cfg) == 100.0
    variants = {v.name: v for v in sparsity_variants(cfg)}
    assert variants["ws100_scale0.2"].settings() == {
        "model.loss.w_s": 100.0, "model.net.input_scale": 0.2
    }  # fmt: skip
    assert variants["ws100_lr0.0001"].label == "w_s=100 (lr=0.0001)" and variants["ws0"].plain
