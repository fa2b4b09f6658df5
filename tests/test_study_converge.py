"""The rotation rule's models in the report: which models the 2 × 2's verdicts read, and the
words of its section follow the numbers."""

from __future__ import annotations

import numpy as np
from omegaconf import OmegaConf

from mfg_lightning.study.parts import IRLS, Settled
from mfg_lightning.study.settle_report import converge_section

CFG = OmegaConf.create({
    "settle": {"flows": ["exact"], "seeds": [0, 1, 2], "strided": {"seeds": []}},
    "converge": {"seeds": [0, 1, 2], "variants": [["exact", "unclamped"]]},
})  # fmt: skip


def _run(mean: float, seed: int, converged: bool = False) -> dict:
    rng = np.random.default_rng(seed)
    errs = mean * (1 + 0.1 * rng.standard_normal(60))
    return {"flow": "exact", "steps": 9000 if converged else 6000,
            "mfg": {"1": {"rot_err": list(errs)}}, "convergence": {"converged": converged},
            "objects": {"own": seed}}  # fmt: skip


def _cached(budget: float, rule: float, unclamped: float, seeds: int = 3, objects: int = 3) -> dict:
    out: dict = {"settle_classical/exact": {"classical": [{"name": IRLS, "rot_err": [1e-3] * 60}]}}
    for s in range(3):
        out[f"settle/exact_seed{s}"] = _run(budget * (1 + 0.03 * s), s)
    for s in range(seeds):
        out[f"converge/exact_seed{s}"] = _run(rule * (1 + 0.03 * s), 10 + s, True)
        out[f"converge/unclamped_seed{s}"] = _run(unclamped * (1 + 0.03 * s), 20 + s, True)
    for s in range(objects):
        out[f"objects/seed{s}"] = {"objects": {"object_set": s}, "world": ["+dataset.world.x=1"]}
    return out


def test_the_verdicts_read_the_converged_models_once_every_seed_has_run() -> None:
    partial = Settled.load(_cached(2e-3, 1e-3, 1e-3, seeds=2).get, CFG)
    assert partial.reads == "settle" and partial.seeds["exact"][0]["steps"] == 6000
    assert partial.seeds["exact"][0]["objects"] == {"own": 0}  # not the object set's
    full = Settled.load(_cached(2e-3, 1e-3, 1e-3).get, CFG)
    assert full.reads == "converge" and full.seeds["exact"][1]["steps"] == 9000
    assert full.budget["exact"][1]["steps"] == 6000
    # S9 and S10 read the object test set's evaluations once every seed has one
    assert [full.seeds["exact"][s]["objects"] for s in range(3)] == [{"object_set": s}
                                                                    for s in range(3)]  # fmt: skip
    assert full.converged["exact"][0]["objects"] == {"own": 10}
    some = Settled.load(_cached(2e-3, 1e-3, 1e-3, objects=2).get, CFG)
    assert [some.seeds["exact"][s]["objects"] for s in range(3)] == [{"own": 10 + s}
                                                                    for s in range(3)]  # fmt: skip


def test_the_rotation_rule_section_says_what_moved_from_the_numbers() -> None:
    def text(budget: float, rule: float, unclamped: float) -> str:
        return "\n".join(converge_section(Settled.load(_cached(budget, rule, unclamped).get, CFG)))

    lower = text(2e-3, 0.5e-3, 0.5e-3)
    assert "its error over the equal budget's models' error is ×0.24" in lower
    assert "], below ×1." in lower and "above ×1" not in lower
    assert "read these converged models" in lower
    same = text(1e-3, 1e-3, 3e-3)
    assert "its error over the equal budget's models' error is ×0.99" in same
    assert "], not distinguishable from ×1." in same
    assert "under the same rule is ×3.0" in same and "], above ×1." in same
    # MFG over IRLS (1 mrad on every pair): below it at 0.5 mrad, above it at 3
    assert "below IRLS's error" in lower and "above IRLS's error" in same
