"""The study's plan: the stage table of ``conf/reproduce.yaml`` (``stage_table``: per stage, its
runner, the function naming the results it writes and what reads them) expanded into the stage
results, in the order the study runs them.

:func:`mfg_lightning.study.run.run` runs this plan and the report lists its results (cached,
or not run yet) with what reads each, so the two cannot disagree; ``stages`` (default: the
table's names) selects. A stage that writes one result per seed, flow, stride or sweep variant
names its results with a function here, named by its ``results``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.utils import get_method
from omegaconf import DictConfig

from mfg_lightning.study import end_to_end as E
from mfg_lightning.study import settle as T
from mfg_lightning.study import stages as S

__all__ = [
    "SparsityVariant",
    "check",
    "claim_results",
    "read_by",
    "results",
    "runner",
    "settings",
    "sparsity_variants",
    "stage_names",
]


def stage_names(cfg: DictConfig) -> list[str]:
    """The stages of the table, in the order they run."""
    return [str(k) for k in cfg.stage_table]


def runner(cfg: DictConfig, stage: str) -> Callable[..., dict | None]:
    """The function ``stage_table.<stage>.runner`` names: ``runner(study, arg)``."""
    return get_method(str(cfg.stage_table[stage].runner))


def _expand(cfg: DictConfig, stage: str) -> list[tuple[str, Any]]:
    """The results one stage writes, ``(name, argument of its runner)``: those its
    ``results`` function names, else one result named as the stage."""
    entry = cfg.stage_table[stage]
    if not entry.get("results"):
        return [(stage, None)]
    return [(str(n), arg) for n, arg in get_method(str(entry.results))(cfg)]


def results(cfg: DictConfig) -> list[tuple[str, str, Any]]:
    """Every stage result of the plan: ``(stage, result name, runner argument)`` in order."""
    return [(stage, name, arg) for stage in stage_names(cfg) for name, arg in _expand(cfg, stage)]


def read_by(cfg: DictConfig) -> dict[str, list[str]]:
    """Per result name of the plan, what reads it (its stage's ``read_by``)."""
    return {name: [str(r) for r in cfg.stage_table[stage].get("read_by") or []]
            for stage, name, _ in results(cfg)}  # fmt: skip


@dataclass(frozen=True)
class SparsityVariant:
    """One model of the w_s sweep on the main model's data: its ``w_s`` and, for the two runs
    beside the sweep, the input scale or the learning rate it changes (numbers, set on the
    composed config as numbers)."""

    w_s: float
    input_scale: float | None = None
    lr: float | None = None

    @property
    def plain(self) -> bool:
        """Whether only ``w_s`` differs from the main setting."""
        return self.input_scale is None and self.lr is None

    @property
    def name(self) -> str:
        """The stage (and model) name: ``ws100``, ``ws100_scale0.2``, ``ws1000_lr0.0001``."""
        tail = "" if self.input_scale is None else f"_scale{self.input_scale:g}"
        return f"ws{self.w_s:g}{tail}" + ("" if self.lr is None else f"_lr{self.lr:g}")

    @property
    def label(self) -> str:
        """The report's name: ``w_s=100``, ``w_s=100 (input_scale=0.2)``."""
        changed = [f"{k}={v:g}" for k, v in (("input_scale", self.input_scale),
                                              ("lr", self.lr)) if v is not None]  # fmt: skip
        return f"w_s={self.w_s:g}" + (f" ({', '.join(changed)})" if changed else "")

    def settings(self) -> dict[str, float]:
        """The model's settings, by dotted key of the ``train`` config."""
        out = {"model.loss.w_s": self.w_s}
        if self.input_scale is not None:
            out["model.net.input_scale"] = self.input_scale
        if self.lr is not None:
            out["model.optimizer.lr"] = self.lr
        return out


def main_w_s(cfg: DictConfig) -> float:
    """The main setting's w_s: the ``train`` config's with the study's main overrides."""
    from mfg_lightning.core.config import compose

    return float(compose("train", [str(o) for o in cfg.main]).model.loss.w_s)


def sparsity_variants(cfg: DictConfig) -> list[SparsityVariant]:
    """The runs of the sparsity sweep, in order: one per ``sparsity.w_s``; at the main
    setting's w_s (:func:`main_w_s`) also one at ``sparsity.input_scale``, and at the largest
    w_s also one at ``sparsity.low_lr`` (to separate a collapse from the rate)."""
    weights = [float(w) for w in cfg.sparsity.w_s]
    main, largest = main_w_s(cfg), max(weights)
    low_lr = cfg.sparsity.get("low_lr")
    variants = []
    for ws in weights:
        variants.append(SparsityVariant(ws))
        if ws == main:
            variants.append(SparsityVariant(ws, input_scale=float(cfg.sparsity.input_scale)))
        if ws == largest and low_lr:
            variants.append(SparsityVariant(ws, lr=float(low_lr)))
    return variants


# The ``results`` functions the stage table names: a stage's results from the config.


def table2_exact_results(cfg: DictConfig) -> list[tuple[str, bool]]:
    """``table2_exact``: Table 2's setting on the exact flow (the runner's ``exact``)."""
    return [("table2_exact", True)]


def seed_results(cfg: DictConfig) -> list[tuple[str, int]]:
    """``seeds``: the main setting at each of ``seeds.extra``."""
    return [(f"seeds/seed{int(s)}", int(s)) for s in cfg.seeds.extra]


def settle_classical_results(cfg: DictConfig) -> list[tuple[str, str]]:
    """``settle_classical``: the classical methods on each flow of the 2 × 2."""
    return [(f"settle_classical/{f}", str(f)) for f in cfg.settle.flows]


def settle_results(cfg: DictConfig) -> list[tuple[str, tuple[str, int]]]:
    """``settle``: each flow at each seed, then the strided seeds."""
    runs = [(f"settle/{f}_seed{s}", (f, s)) for f, s in T.seed_runs(cfg)]
    return runs + [(f"settle/strided_seed{s}", ("strided", s)) for s in T.strided_runs(cfg)]


def converge_results(cfg: DictConfig) -> list[tuple[str, tuple[str, int]]]:
    """``converge``: each variant at each seed, in the order they train."""
    return [(f"converge/{v}_seed{s}", (v, s)) for v, s in T.converge_runs(cfg)]


def objects_results(cfg: DictConfig) -> list[tuple[str, int]]:
    """``objects``: the object test set at each seed of the converged models."""
    return [(f"objects/seed{int(s)}", int(s)) for s in cfg.converge.seeds]


def end_to_end_results(cfg: DictConfig) -> list[tuple[str, Any]]:
    """``end_to_end``: the comparison's models (:func:`mfg_lightning.study.end_to_end.runs`)."""
    return E.runs(cfg)


def size_results(cfg: DictConfig) -> list[tuple[str, Any]]:
    """``size``: each point of the curve, then the classical methods on its test pairs."""
    return [*((f"size/{S.size_name(*p)}", p) for p in S.size_runs(cfg)), ("size/classical", None)]


def sparsity_results(cfg: DictConfig) -> list[tuple[str, Any]]:
    """``sparsity``: each variant of the sweep (:func:`sparsity_variants`)."""
    return [(f"sparsity/{v.name}", v) for v in sparsity_variants(cfg)]


def check(cfg: DictConfig) -> None:
    """Refuse a config the study cannot run, naming the key."""
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
    for stage in stage_names(cfg):
        for key in ("runner", "results"):
            where = cfg.stage_table[stage].get(key)
            if key == "runner" or where:
                try:
                    get_method(str(where))
                except Exception as e:
                    raise ValueError(f"stage_table.{stage}.{key}: {where}: not a function "
                                     f"({e})") from None  # fmt: skip
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


#: The file of a results folder that records the settings its results were computed with.
SETTINGS_FILE = "settings.yaml"
#: The keys of the config that say where the study reads and writes, what it runs now and how
#: the report reads the results: none of them changes a stage result, so a results folder does
#: not record them.
NOT_SETTINGS = (
    *("task_name", "poses_dir", "procedural_poses", "work_dir", "results_dir", "start_from"),
    *("flow_cache_dir", "report", "notes", "readme", "fresh", "stages", "refresh_classical"),
    *("stage_table", "statistics", "trainer", "paths", "hydra"),
)


def settings(cfg: DictConfig) -> dict[str, Any]:
    """The settings a results folder's results depend on: the config without
    :data:`NOT_SETTINGS`, interpolations kept as written (``${poses_dir}``, not this machine's
    path), and which poses the worlds follow (KITTI's, or procedural ones)."""
    from omegaconf import OmegaConf

    every = OmegaConf.to_container(cfg, resolve=False)
    out = {k: v for k, v in every.items() if k not in NOT_SETTINGS}
    out["poses"] = "procedural" if _procedural(cfg) else "KITTI (poses_dir)"
    return out


def _procedural(cfg: DictConfig) -> bool:
    """Whether the study's worlds follow :func:`write_procedural_poses`'s trajectories."""
    folder = Path(str(cfg.work_dir)).expanduser() / "procedural_poses"
    return bool(cfg.get("procedural_poses")) and cfg.poses_dir in (None, str(folder))


def write_procedural_poses(cfg: DictConfig) -> Path | None:
    """Where ``poses_dir`` is not given and ``procedural_poses`` is: procedural driving
    trajectories (:func:`mfg_lightning.scene.camera.procedural_trajectory`, seeded per
    sequence) written as KITTI pose files ``<NN>.txt`` to ``<work_dir>/procedural_poses``, so
    that a study on them (``reproduce=tiny``) needs no download; their folder, or None."""
    spec = cfg.get("procedural_poses")
    if cfg.poses_dir or not spec:
        return None
    from mfg_lightning.scene.camera import procedural_trajectory
    from mfg_lightning.scene.seeding import seeded_rng
    from mfg_lightning.trajectory.pose_io import write_kitti_poses

    folder = Path(str(cfg.work_dir)).expanduser() / "procedural_poses"
    folder.mkdir(parents=True, exist_ok=True)
    for seq in spec.sequences:
        rng = seeded_rng(int(cfg.seed), "procedural_poses", f"{int(seq):02d}")
        write_kitti_poses(folder / f"{int(seq):02d}.txt",
                          procedural_trajectory(rng, int(spec.frames)))  # fmt: skip
    return folder


def _first_difference(a: Any, b: Any, key: str = "") -> str | None:
    """The first dotted key at which ``a`` and ``b`` differ (None: equal)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in [*a, *(k for k in b if k not in a)]:
            if (d := _first_difference(a.get(k), b.get(k), f"{key}.{k}" if key else k)) is not None:
                return d
        return None
    return None if a == b else key


def claim_results(cfg: DictConfig, results: Path) -> None:
    """Make ``results`` this run's results folder, never one mixed from two configurations:
    a new folder starts from ``start_from`` (the committed results) when that folder's
    settings are this run's, and records this run's settings; a folder whose recorded settings
    differ refuses, naming the first key that differs.

    Raises:
        ValueError: ``results`` holds results of other settings, or results with no record of
            their settings.
    """
    import shutil

    import yaml

    mine = settings(cfg)
    record = results / SETTINGS_FILE
    if record.is_file():
        theirs = yaml.safe_load(record.read_text()) or {}
        if (key := _first_difference(theirs, mine)) is not None:
            raise ValueError(
                f"results_dir: {results} holds results computed with other settings ({key}: "
                f"{_at(theirs, key)!r} there, {_at(mine, key)!r} here); name another "
                "results_dir, or set fresh=true to discard those results"
            )
        return
    if any(results.glob("**/*.json")):
        raise ValueError(
            f"results_dir: {results} holds results but no {SETTINGS_FILE} recording their "
            "settings; name another results_dir, or set fresh=true to discard them"
        )
    start = Path(str(cfg.get("start_from") or "")).expanduser() if cfg.get("start_from") else None
    if start is not None and not cfg.fresh and (start / SETTINGS_FILE).is_file():
        theirs = yaml.safe_load((start / SETTINGS_FILE).read_text()) or {}
        if (key := _first_difference(theirs, mine)) is None:
            shutil.copytree(start, results, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("*.png"))  # fmt: skip
            print(f"started from {start}", flush=True)
        else:
            print(f"start_from: {start} has other settings ({key}); starting empty", flush=True)
    results.mkdir(parents=True, exist_ok=True)
    head = (
        "# The settings these results were computed with (mfg_lightning.study.plan.settings):"
        "\n# a run of the study with other settings refuses this folder, naming the key.\n"
    )
    record.write_text(head + yaml.safe_dump(mine, sort_keys=False, allow_unicode=True))


def _at(tree: Any, key: str) -> Any:
    for k in key.split("."):
        tree = tree.get(k) if isinstance(tree, dict) else None
    return tree
