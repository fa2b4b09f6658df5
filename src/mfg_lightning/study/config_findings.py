"""What the report says about the study's own settings: the recipes (row R), the convergence
rule's weakness and the input scale. The settings it names are read from the composed config
or from the stage results that record them (a run's ``recipe``:
:func:`mfg_lightning.study.stages.recipe_of`; its convergence record's ``rule``), never typed
into the text, and the study decides nothing for the config. The input scale is a finding
(:class:`~mfg_lightning.study.findings.InputScale`): whether validation would support changing
the default, beside the default the config has (``model.net.input_scale`` of the composed
``train`` config, ``conf/model/mfg.yaml``); the study never changes it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from mfg_lightning.study.findings import Cached, InputScale, RuleWeakness
from mfg_lightning.study.noise import spread_of
from mfg_lightning.study.render import paragraph
from mfg_lightning.study.sentences import View

__all__ = ["config_default", "input_scale_finding", "para_recipe", "para_rule"]


def config_default(key: str, config_name: str = "train") -> Any:
    """The value at ``key`` (dotted) of the composed ``config_name`` config, with no overrides:
    the default a user gets."""
    from omegaconf import OmegaConf

    from mfg_lightning.core.config import compose

    return OmegaConf.select(compose(config_name), key)


def input_scale_finding(
    views: Mapping[int, View], scaled: dict | None, scale: float, default: float
) -> str:
    """The input scale as a finding: the model at ``scale``'s validation ATE † against the band
    of the ``default``-scale seeds' mean ± their tolerance (:func:`~mfg_lightning.study.noise.
    tolerance`), and what that evidence would support; the config keeps ``default`` whatever it
    says. Empty before the scaled model has run."""
    if scaled is None or not views:
        return ""
    val = spread_of(views, lambda v: v["table1"]["val"]["1"].get("ate"))
    # a config value may arrive as a string or a Decimal-like node
    f = InputScale(float(scale), float(default), val, scaled["val"]["1"].get("ate"))
    return paragraph("reading/input_scale.md.j2", f=f)


def para_rule(cached: Cached) -> str | None:
    """The convergence rule's weakness on a noisy curve, measured on the w_s = 0 model."""
    ws0 = cached("sparsity/ws0")
    if ws0 is None or not ws0.get("curve"):
        return None
    c, curve = ws0["convergence"], ws0["curve"]
    rule = c.get("rule") or {}
    # the lowest validation ATE † up to the decay's start
    vals = [p["val/ate"] for p in curve
            if p["step"] <= float(c["decay_start"]) and math.isfinite(p["val/ate"])]  # fmt: skip
    f = RuleWeakness(
        c, min(vals) if vals else None, min(p["val/ate"] for p in curve),
        float(rule.get("min_improvement", 0.0)),  # what the rule itself counts as improving
        rule.get("window"),
    )  # fmt: skip
    return paragraph("reading/rule.md.j2", f=f)


def para_recipe(cached: Cached) -> str | None:
    """Row R in words."""
    rc = cached("recipe")
    return (
        None if rc is None else paragraph("reading/recipe.md.j2", cpu=rc["cpu"], paper=rc["paper"])
    )
