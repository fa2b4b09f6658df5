"""The study's plan: the stage table of ``conf/reproduce.yaml`` (``stage_table``: per stage, the
config blocks of its overrides, the models it trains and what reads its results) expanded into
the stage results it writes, in the order the study runs them.

:func:`mfg_lightning.study.run.run` runs this plan and the report lists the results of it that
are not cached yet, so the two cannot disagree; ``stages`` (default: the table's names) selects.
A stage that writes one result per seed, flow, stride or sweep variant names its results here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mfg_lightning.study import end_to_end as E
from mfg_lightning.study import settle as T
from mfg_lightning.study import stages as S

__all__ = ["check", "results", "stage_names"]


def stage_names(cfg: DictConfig) -> list[str]:
    """The stages of the table, in the order they run."""
    return [str(k) for k in cfg.stage_table]


def _expand(cfg: DictConfig, stage: str) -> list[tuple[str, Any]]:
    """The results one stage writes, ``(name, argument of its runner)``."""
    if stage == "seeds":
        return [(f"seeds/seed{int(s)}", int(s)) for s in cfg.seeds.extra]
    if stage == "settle_classical":
        return [(f"settle_classical/{f}", str(f)) for f in cfg.settle.flows]
    if stage == "settle":
        runs = [(f"settle/{f}_seed{s}", (f, s)) for f, s in T.seed_runs(cfg)]
        return runs + [(f"settle/strided_seed{s}", ("strided", s)) for s in T.strided_runs(cfg)]
    if stage == "converge":
        return [(f"converge/{v}_seed{s}", (v, s)) for v, s in T.converge_runs(cfg)]
    if stage == "objects":
        return [(f"objects/seed{int(s)}", int(s)) for s in cfg.converge.seeds]
    if stage == "end_to_end":
        return E.runs(cfg)
    if stage == "size":
        runs = [(f"size/{S.size_name(*p)}", p) for p in S.size_runs(cfg)]
        return [*runs, ("size/classical", None)]
    if stage == "sparsity":
        return [(f"sparsity/{v[0]}", v) for v in S.sparsity_variants(cfg)]
    return [(stage, None)]


def results(cfg: DictConfig) -> list[tuple[str, str, Any]]:
    """Every stage result of the plan: ``(stage, result name, runner argument)`` in order."""
    return [(stage, name, arg) for stage in stage_names(cfg) for name, arg in _expand(cfg, stage)]


def check(cfg: DictConfig) -> None:
    """Refuse a config the study cannot run, naming the key."""
    if not cfg.poses_dir and any("trajectory=kitti" in str(o) for o in cfg.data):
        raise ValueError("poses_dir: set it to KITTI's poses/ directory (00.txt ... 10.txt)")
    if cfg.poses_dir and not Path(cfg.poses_dir).expanduser().is_dir():
        raise FileNotFoundError(f"poses_dir: no such directory: {cfg.poses_dir}")
    variants = [str(v) for group in cfg.converge.variants for v in group]
    odd = sorted(set(variants) - set(T.VARIANTS))
    missing = [str(f) for f in cfg.settle.flows if str(f) not in variants]
    if odd or missing:
        # a flow of the 2 x 2 without its converged models would keep the verdicts on the equal
        # budget's for ever
        raise ValueError(f"converge.variants: unknown {odd} or missing the 2 × 2's flows "
                         f"{missing}; known: {', '.join(T.VARIANTS)}")  # fmt: skip
    known = stage_names(cfg)
    unknown = [s for s in cfg.stages if s not in known]
    if unknown:
        raise ValueError(f"stages: unknown {unknown}; known: {', '.join(known)}")
    from mfg_lightning.study.classical_refresh import REFRESHABLE

    odd = [s for s in cfg.get("refresh_classical") or [] if s not in REFRESHABLE]
    if odd:
        raise ValueError(f"refresh_classical: unknown {odd}; known: {', '.join(REFRESHABLE)}")
    budget = ("main_steps", "other_steps", "val_every", "batch_size", "eval_batch_size")
    for key in (*budget, "main_frame_stride"):
        if int(cfg.budget[key]) <= 0:
            raise ValueError(f"budget.{key} must be positive, got {cfg.budget[key]}")
    seeds = [int(s) for s in cfg.seeds.extra]
    if int(cfg.seed) in seeds or len(set(seeds)) != len(seeds):
        raise ValueError(
            f"seeds.extra: {seeds} must be distinct and differ from the main model's seed "
            f"({cfg.seed})"
        )
    main_stride = int(cfg.budget.main_frame_stride)
    bad = [int(n) for n in cfg.size.strides if int(n) <= 0 or int(n) % main_stride]
    if bad:
        # a stride off the main model's frames would render pairs the flow cache does not have
        raise ValueError(
            f"size.strides: {bad} must be positive multiples of budget.main_frame_stride "
            f"({main_stride}), the source frames whose pairs the main model's data rendered"
        )
    if int(cfg.seed) in [int(s) for s in cfg.size.seeds]:
        raise ValueError(
            f"size.seeds: {list(cfg.size.seeds)} must not hold the study's seed ({cfg.seed}), "
            "whose run at each stride is the curve's own"
        )
