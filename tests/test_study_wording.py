"""The report's conclusion words follow the numbers they describe: each comparative comes from
:mod:`mfg_lightning.study.wording` at its stated thresholds, intervals are read as intervals,
and a paragraph rendered from two results on either side of a bound says different things
(ratios from ×1.2 to ×5, intervals from below to overlapping, verdicts from holds to does not
hold). Settings named in the text are read from the results and the composed config."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from mfg_lightning.core.config import config_dir
from mfg_lightning.study import prose
from mfg_lightning.study.config_findings import config_default, para_recipe, para_rule
from mfg_lightning.study.sentences import Settled, judge_all
from mfg_lightning.study.settle_report import para_settle
from mfg_lightning.study.wording import (
    MUCH,
    SAME,
    SEVERAL,
    change,
    compare,
    number,
    position,
    side,
    spelled,
)

IRLS = "continuous LS + IRLS (Cauchy)"


@pytest.mark.parametrize(
    ("r", "words"),
    [
        (1.0, "about as good as"),
        (SAME * 0.999, "about as good as"),
        (1.2, "worse than"),
        (MUCH, "much worse than"),
        (SEVERAL, "several times worse than"),
        (5.0, "several times worse than"),
        (1 / 1.2, "better than"),
        (1 / 5.0, "several times better than"),
        (None, "not comparable with"),
        (0.0, "not comparable with"),
    ],
)
def test_compare_names_the_factor_at_its_thresholds(r: float | None, words: str) -> None:
    assert compare(r) == words


def test_intervals_ranges_and_changes_are_read_on_both_ends() -> None:
    assert side(-2.0, -1.0) == "below" and side(1.0, 2.0) == "above"
    assert side(-1.0, 1.0) == "not distinguishable from"  # the point estimate decides nothing
    assert side(0.5, 0.9, bound=1.0) == "below" and side(0.5, 1.1, bound=1.0) != "below"
    assert [position(v, 1.0, 2.0) for v in (0.5, 1.0, 1.5, 2.0, 2.5)] == [
        "below", "inside", "inside", "inside", "above"
    ]  # fmt: skip
    assert change(0.00193, 0.00017, 1) == "falls ×11.4"
    assert change(1.0, 2.0) == "rises ×2.00" and change(1.0, 1.05) == "stays within 10 %"
    assert change(None, 1.0) == "is not measured"
    assert number(1e-5) == "1e-5" and number(0.999) == "0.999" and number(1e-3) == "0.001"
    assert spelled(1) == "one" and spelled(12) == "12"


def _view(star09: float = 1.8, growth: float = 1.0) -> dict:
    """A seed's results as the paragraphs read them: Table 1 at all units and 5 %, the
    central test's ATE * / ATE † (``star09`` on 09), MFG's growth with object coverage."""
    full = {"09/ate": 0.010, "09/ate_central": 0.010 * star09, "10/ate": 0.010,
            "10/ate_central": 0.017, "rpe_trans": 0.1, "rpe_rot": 0.001}  # fmt: skip
    at5 = {"09/ate": 0.010, "10/ate": 0.010, "rpe_trans": 0.1, "rpe_rot": 0.001}
    at2 = {"09/ate": 0.014, "10/ate": 0.012, "rpe_trans": 0.2, "rpe_rot": 0.002}
    bins = [{"n": 10, "mean": 1.0}, {"n": 5, "mean": growth}]
    return {
        "trained": {},
        "table1": {"test": {"1": full, "0.05": at5, "0.02": at2},
                   "val": {"1": {"ate": 0.02}, "0.05": {"ate": 0.0201}, "0.02": {"ate": 0.03}}},
        "methods": {"bins": {"MFG (all units)": {"rot_bins": bins, "trans_bins": bins}}},
        "basis": None,
        "object_motion": None,
    }  # fmt: skip


def _classical(name: str, star: float) -> dict:
    m = {f"{s}/{k}": v for s in ("09", "10") for k, v in (("ate", 1.0), ("ate_central", star))}
    return {"name": name, "metrics": m}


def _flow_error(far: float) -> dict:
    """DIS's end-point error by offset: 1 px at ±1, ``far`` px at ±2."""
    test = {o: {"regions": {"all": {"epe": far if abs(int(o)) == 2 else 1.0, "fl": 10.0,
                                    "pixels": 100}}} for o in ("-2", "-1", "1", "2")}  # fmt: skip
    return {"test": test}


def test_the_offset_ratio_and_the_classical_range_decide_the_central_words() -> None:
    """ "Several times worse" at ×5, not at ×1.2; "measures the flow" only where MFG's ratio lies
    inside the classical methods' range."""
    methods = {"rows": [_classical("continuous least squares", 1.5), _classical(IRLS, 2.0)]}
    views = {s: _view() for s in range(3)}

    def central(far: float, seeds: dict = views) -> str:
        results = {"methods": methods, "flow_error": _flow_error(far)}
        return prose.para_central(results.get, seeds)

    near, far = central(1.2), central(5.0)
    assert "flows worse than the † one" in near and "several times" not in near
    assert "flows several times worse than the † one" in far
    assert "inside that range on 09 and 10: the ratio measures the flow" in near
    above = central(5.0, {s: _view(star09=3.0) for s in range(3)})
    assert "above that range on 09, inside that range on 10" in above
    assert "measures the flow at offsets ±2 at least" not in above and "mixes the flow" in above


def _t2(mfg: float, irls: float) -> dict:
    return {"mfg": {"1": {"rpe_rot": mfg}}, "classical": [{"name": IRLS,
            "metrics": {"rpe_rot": irls}}], "steps": 6000, "train_pairs": 1696}  # fmt: skip


def _exact_against_dis(exact: dict, dis: dict) -> str:
    """The Table-2-sized paragraph from one run on each flow (no main model's seeds)."""
    return prose.para_table2({"table2_exact": exact, "table2": dis}.get, {})


def test_the_exact_flow_explanation_needs_irls_to_gain_much_more_than_mfg() -> None:
    unequal = _exact_against_dis(_t2(0.00256, 0.00017), _t2(0.00283, 0.00193))
    assert "falls ×11.4 and MFG's falls ×1.11" in unequal
    assert "helping IRLS several times more than MFG: on flow without estimation noise" in unequal
    alike = _exact_against_dis(_t2(0.001, 0.001), _t2(0.0012, 0.0012))
    assert "helping IRLS about as much as MFG." in alike and "regressor" not in alike
    worse = _exact_against_dis(_t2(0.003, 0.001), _t2(0.002, 0.002))
    assert "MFG's rises ×1.50" in worse


def test_the_robustness_reading_follows_the_essential_matrix_growths() -> None:
    views = {s: _view() for s in range(3)}

    def robust(g: float) -> str:
        bins = {"essential matrix + RANSAC": {"growth": g}, IRLS: {"growth": 5.0}}
        mt = {"edges": [0.0, 0.1, 1.0], "counts": [10, 5], "bins": bins}
        return prose.para_robustness({"methods": mt}.get, views)

    falls = "the essential-matrix methods' rotation errors are lower where moving objects cover"
    assert falls in robust(0.3)
    assert falls not in robust(1.4) and robust(1.4).endswith("×5.00.")


def test_the_size_curve_compares_irls_with_mfg_from_the_numbers() -> None:
    def size(irls: float) -> dict:
        point = {"stride": 3, "train_pairs": 6400, "test": {"rpe_rot": 0.0008}}
        return {"stride3": point, "classical": {"classical": [{"name": IRLS,
                "metrics": {"rpe_rot": irls}}]}}  # fmt: skip

    assert "an error several times smaller than MFG's lowest" in prose.para_size(size(0.0002))
    assert "an error smaller than MFG's lowest" in prose.para_size(size(0.0007))
    assert "an error about as large as MFG's lowest" in prose.para_size(size(0.00079))


def _run(mean: float, seed: int, sequences: str | None = None) -> dict:
    rng = np.random.default_rng(seed)
    over = [f"dataset.train_sequences={sequences}"] if sequences else ["dataset.frame_stride=12"]
    return {"mfg": {"1": {"rot_err": list(mean * (1 + 0.1 * rng.standard_normal(60)))}},
            "overrides": over, "train_pairs": 1696 if sequences else 1621}  # fmt: skip


def _settled(mfg: float, strided: float) -> Settled:
    contiguous = {s: _run(mfg * (1 + 0.05 * s), s, "[0,1,2,3,4,5,6,7]") for s in range(3)}
    irls = [{"name": IRLS, "rot_err": [0.001] * 60}]
    strided_runs = {s: _run(strided * (1 + 0.05 * s), 10 + s) for s in range(3)}
    return Settled({"exact": contiguous}, {"exact": {"classical": irls}}, strided_runs,
                   budget={"exact": contiguous})  # fmt: skip


def test_the_two_by_two_reads_its_intervals_and_the_sequences_from_the_runs() -> None:
    """MFG against IRLS from above to below (a verdict's side flips); strided against
    contiguous from below to overlapping; the caveat counts the sequences the runs name."""
    data = ["dataset.train_sequences=[0,1,2,3,4,5,6,7,8]"]
    better = para_settle(_settled(0.002, 0.001), data)
    assert "above IRLS's" in better and "the strided set is better" in better
    assert "(the strided set also holds one more sequence)" in better
    same = para_settle(_settled(0.0005, 0.00052), data)
    assert "below IRLS's" in same and "cannot be told apart" in same
    assert "better" not in same and "more sequence" not in same
    assert "more sequence" not in para_settle(_settled(0.002, 0.001))  # the sequences unknown


def test_the_verdict_count_follows_the_verdicts() -> None:
    holds = judge_all({s: _view() for s in range(3)}, None, 0.1, 0.8, 0.05)
    worse = {s: _view() for s in range(3)}
    for s, v in worse.items():
        v["table1"]["test"]["0.05"]["09/ate"] = 0.0112 + 0.0001 * s  # ×1.12 > 1 + 8.3 %
    fails = judge_all(worse, None, 0.1, 0.8, 0.05)
    assert "holds: S1" in prose.para_verdicts(holds)
    assert "does not hold: S1" in prose.para_verdicts(fails)


def test_the_rule_and_the_recipes_are_read_from_the_results_and_the_config() -> None:
    curve = [{"step": 1000, "val/ate": 0.030}, {"step": 4000, "val/ate": 0.0275},
             {"step": 5000, "val/ate": 0.0202}]  # fmt: skip
    rule = {"window": 0.25, "min_improvement": 0.02}
    ws0 = {
        "curve": curve,
        "convergence": {
            "converged": True,
            "reason": "plateau",
            "decay_start": 4000,
            "decay_end": 5000,
            "rule": rule,
        },
    }
    text = para_rule({"sparsity/ws0": ws0}.get)
    assert '"less than 2 % better over the last 25 % of the steps" fires' in text
    curve[-1]["val/ate"] = 0.0272  # 1.1 % lower: within the rule's own 2 %
    assert "did not stop a model that was still improving" in para_rule({"sparsity/ws0": ws0}.get)
    recipe = {"batch_size": 1, "optimizer": "Adam", "lr": 1e-5, "betas": [0.99, 0.999],
              "scheduler": None}  # fmt: skip
    run = {"recipe": recipe, "convergence": {"converged": True, "decay_start": 38000},
           "steps": 42000, "epochs": 1.63, "train_seconds": 3292.0, "val_ate": 0.023,
           "test_ate": 0.0235}  # fmt: skip
    cpu = {"val_ate": 0.0202, "epochs": 4.95, "test_ate": 0.0192}
    assert "(batch 1, Adam lr 1e-5, betas 0.99 / 0.999) met the rule at step 38" in para_recipe(
        {"recipe": {"cpu": cpu, "paper": run}}.get
    )
    recipe.update(lr=3e-4, betas=[0.9, 0.99])
    assert "Adam lr 0.0003, betas 0.9 / 0.99" in para_recipe(
        {"recipe": {"cpu": cpu, "paper": run}}.get
    )
    mfg_yaml = OmegaConf.load(config_dir() / "model" / "mfg.yaml")
    assert config_default("model.net.input_scale") == mfg_yaml.net.input_scale
