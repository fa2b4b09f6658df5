"""The end-to-end section of the report (``mfg_lightning.study.end_to_end``) from stage results
made here: the words comparing the end-to-end model with its two-stage start follow the
intervals, and the far field's sentence follows the flow's error before and after."""

from __future__ import annotations

import numpy as np
import pytest

from mfg_lightning.core.config import compose
from mfg_lightning.study import end_to_end as E
from mfg_lightning.study import plan

REGIONS = {"road": 3.0, "structure": 1.0, "moving": 6.0, "far": 1.2, "all": 2.0}


def _quality(far: float) -> dict:
    regions = {r: {"epe": far if r == "far" else v, "fl": 10.0, "pixels": 1.0}
               for r, v in REGIONS.items()}  # fmt: skip
    return {"regions": regions, "regions_noc": regions, "pairs": 50}


def _result(seed: int, rot_scale: float, far: float, kind: str) -> dict:
    rng = np.random.default_rng(seed)
    rot = rng.uniform(0.001, 0.003, 50) * rot_scale
    trans = rng.uniform(0.05, 0.1, 50)
    metrics = {"ate": 0.02, "rpe_trans": float(trans.mean()), "rpe_rot": float(rot.mean())}
    return {
        "seed": seed, "steps": 400 if kind == "joint" else 6000, "train_seconds": 600.0,
        "train_pairs": 1696, "test_pairs": 50, "batch_size": 8, "precision": "32-true",
        "cpu_kind": "avx512_bf16",
        "recipe": {"batch_size": 8, "optimizer": "Adam", "lr": 1e-4, "betas": [0.9, 0.999]},
        "mfg": {"1": {"metrics": metrics, "rot_err": rot.tolist(), "trans_err": trans.tolist()}},
        "flow_quality": _quality(far),
    }  # fmt: skip


def _section(joint_rot: float, far_after: float) -> str:
    cfg = compose("reproduce", ["poses_dir=null"])
    results = {}
    for s in (0, 1, 2):
        results[f"end_to_end/two_stage_seed{s}"] = _result(s, 1.0, 1.2, "two_stage")
        # the same pairs' errors scaled: the joint model of a seed starts from its two-stage one
        results[f"end_to_end/joint_seed{s}"] = _result(s, joint_rot, far_after, "joint")
        for flow in ("dis", "exact"):
            results[f"settle/{flow}_seed{s}"] = _result(s + 10, 1.0, 1.2, "two_stage")
    results["end_to_end/dis_flow"] = {"flow_quality": _quality(1.3)}
    text, fig = E.section(results.get, cfg)
    assert fig is not None and len(fig.axes) >= 2
    return "\n".join(text)


@pytest.mark.parametrize(
    ("joint_rot", "far_after", "rot_words", "far_words"),
    [
        (0.7, 0.9, "lower than the two-stage model's", "The rotation error followed it down."),
        (1.3, 0.9, "higher than the two-stage model's", "did not follow it at these seeds"),
        (
            1.0,
            1.2,
            "not distinguishable from the two-stage model's",
            "The far field did not improve, and neither did the rotation error.",
        ),
        (0.7, 1.2, "lower than the two-stage model's", "fell without a matching change"),
    ],
)
def test_the_words_follow_the_intervals_and_the_far_field(
    joint_rot: float, far_after: float, rot_words: str, far_words: str
) -> None:
    text = _section(joint_rot, far_after)
    assert f"its rotation error is {rot_words}" in text
    assert far_words in text
    # the translation errors are the same pairs' in both: not distinguishable
    assert "×1.000 [×1.000, ×1.000]: not distinguishable from the two-stage model's" in text
    # the four models at 3 seeds, each with an interval
    rows = [r for r in text.splitlines() if r.startswith("| ") and "| 0, 1, 2 |" in r]
    assert len(rows) == 4 and all(r.count("[") == 3 for r in rows)
    assert "| shipped network (before) | noc |" in text and "| DIS | all |" in text


def test_no_section_before_a_joint_model_and_the_plan_names_every_result() -> None:
    cfg = compose("reproduce", ["poses_dir=null"])
    assert E.section({}.get, cfg) == ([], None)
    names = [n for stage, n, _ in plan.results(cfg) if stage == "end_to_end"]
    assert names == ["end_to_end/dis_flow"] + [
        f"end_to_end/{k}_seed{s}" for s in (0, 1, 2) for k in ("two_stage", "joint")
    ]
