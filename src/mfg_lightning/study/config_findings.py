"""What the report says about the study's own settings: the recipes (row R), the convergence
rule's weakness and the input scale. The settings it names are read from the composed config
or from the stage results that record them (a run's ``recipe``:
:func:`mfg_lightning.study.stages.recipe_of`; its convergence record's ``rule``), never typed
into the text, and the study decides nothing for the config. The input scale is a finding:
whether validation would support changing the default, beside the default the config has
(``model.net.input_scale`` of the composed ``train`` config, ``conf/model/mfg.yaml``); the study
never changes it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from mfg_lightning.core.tables import fmt
from mfg_lightning.study.noise import spread_of, tolerance
from mfg_lightning.study.sentences import View
from mfg_lightning.study.wording import count, number, percent, position

__all__ = [
    "config_default",
    "input_scale_finding",
    "para_recipe",
    "para_rule",
    "recipe_text",
    "rule_met",
]

Cached = Callable[[str], Any]


def config_default(key: str, config_name: str = "train") -> Any:
    """The value at ``key`` (dotted) of the composed ``config_name`` config, with no overrides:
    the default a user gets."""
    from omegaconf import OmegaConf

    from mfg_lightning.core.config import compose

    return OmegaConf.select(compose(config_name), key)


def recipe_text(recipe: Mapping[str, Any]) -> str:
    """A run's recorded recipe in words ("batch 1, Adam lr 1e-5, betas 0.99 / 0.999")."""
    betas = recipe.get("betas") or []
    text = f"batch {recipe['batch_size']}, {recipe['optimizer']} lr {number(recipe['lr'])}"
    if betas:
        text += ", betas " + " / ".join(number(b) for b in betas)
    return text + (f", {recipe['scheduler']} schedule" if recipe.get("scheduler") else "")


def input_scale_finding(
    views: Mapping[int, View], scaled: dict | None, scale: float, default: float
) -> str:
    """The input scale as a finding: the model at ``scale``'s validation ATE † against the band
    of the ``default``-scale seeds' mean ± their tolerance (:func:`~mfg_lightning.study.noise.
    tolerance`), and what that evidence would support; the config keeps ``default`` whatever it
    says. Empty before the scaled model has run."""
    if scaled is None or not views:
        return ""
    scale = float(scale)  # a config value may arrive as a string or a Decimal-like node
    val = spread_of(views, lambda v: v["table1"]["val"]["1"].get("ate"))
    other = scaled["val"]["1"].get("ate")
    kept = (
        f"the config's default (`model.net.input_scale`, conf/model/mfg.yaml) is "
        f"{float(default)}, which the study does not change"
    )
    head = (
        f"**The input scale.** The released code feeds its network flow in quarter-resolution "
        f"pixels × 0.2; the paper is silent; {kept}. At input_scale={scale:g} (w_s = 100, the "
        f"sweep's model) the validation ATE † is {fmt(other)} against the default's "
        f"{val.text(4)}"
    )
    if val.n < 2 or other is None or not val.mean:
        return head + ": the seed spread needed to judge the difference is not measured yet."
    tol = tolerance(val)
    where = position(other, val.mean * (1 - tol.value), val.mean * (1 + tol.value))
    moved = f"{percent(abs(1 - other / val.mean))} {'lower' if other < val.mean else 'higher'}"
    relation, conclusion = {
        "below": ("beyond", "validation confirms the released code's reading and would support "
                  f"making {scale:g} the default; the config was not changed"),
        "inside": ("within", "validation does not confirm the released code's reading and gives "
                   f"no reason to change the default from {float(default)}"),
        "above": ("beyond", "validation contradicts the released code's reading and supports "
                  f"the default {float(default)}"),
    }[where]  # fmt: skip
    return head + (
        f", {moved}, {relation} the tolerance ({tol.text()}): {conclusion}; both are reported."
    )


def _best_before(curve: list[dict], step: float) -> float | None:
    """The lowest validation ATE † of a learning curve up to ``step``."""
    vals = [p["val/ate"] for p in curve if p["step"] <= step and math.isfinite(p["val/ate"])]
    return min(vals) if vals else None


def para_rule(cached: Cached) -> str | None:
    """The convergence rule's weakness on a noisy curve, measured on the w_s = 0 model."""
    ws0 = cached("sparsity/ws0")
    if ws0 is None or not ws0.get("curve"):
        return None
    c, rule = ws0["convergence"], ws0["convergence"].get("rule") or {}
    before = _best_before(ws0["curve"], float(c["decay_start"]))
    after = min(p["val/ate"] for p in ws0["curve"])
    gain = 1 - after / before if before else None
    least = float(rule.get("min_improvement", 0.0))  # what the rule itself counts as improving
    if gain is not None and gain > least:
        quoted = f"less than {percent(least, 0)} better over the last "
        quoted += f"{percent(rule.get('window'), 0)} of the steps"
        reading = f'at a constant rate the curve is noisy enough that "{quoted}" fires while the '
        reading += "model still improves"
    else:
        reading = f"the decay improved it by no more than the rule's {percent(least, 0)}, so "
        reading += "the rule did not stop a model that was still improving"
    moved = f"{percent(None if gain is None else abs(gain))} "
    moved += "higher" if (gain or 0) < 0 else "lower"
    return (
        f"**The rule's weakness, measured.** The sweep's w_s = 0 model {rule_met(c)} (best "
        f"validation ATE † {fmt(before)} by then) and its decay to step {count(c['decay_end'])} "
        f"took it to {fmt(after)} ({moved}): {reading}. The rule was left as stated before "
        "training."
    )


def rule_met(c: Mapping[str, Any], rule: str = "the rule") -> str:
    """Whether a run's convergence record ``c`` met ``rule`` (``reason`` "plateau") or stopped
    for another reason (a step, time or budget cap), and at which step its decay began."""
    start = c.get("decay_start")
    if c.get("converged", c.get("reason") == "plateau"):
        return f"met {rule}" + (f" at step {count(start)}" if start is not None else "")
    why = f"did not meet {rule} ({c.get('reason') or 'no reason recorded'})"
    return why + (f" and began its decay at step {count(start)}" if start is not None else "")


def para_recipe(cached: Cached) -> str | None:
    """Row R in words."""
    rc = cached("recipe")
    if rc is None:
        return None
    a, b = rc["cpu"], rc["paper"]
    return (
        "**Row R, the two recipes (a diagnostic).** The paper's recipe "
        f"({recipe_text(b['recipe'])}) {rule_met(b.get('convergence') or {})} and decayed to "
        f"{count(b['steps'])} ({fmt(b['epochs'], 2)} epochs, {count(b['train_seconds'])} s):"
        f" validation ATE † {fmt(b['val_ate'])} against the CPU recipe's {fmt(a['val_ate'])} "
        f"({fmt(a['epochs'], 2)} epochs), test {fmt(b['test_ate'])} against "
        f"{fmt(a['test_ate'])}."
    )
