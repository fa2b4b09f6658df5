"""The stage sequence of the reproduction study: each stage's inputs, in order, the report
rewritten after each (:func:`run`), and the config check (:func:`check`).

Stages are cached by :class:`mfg_lightning.study.stages.Study`; the rows and figures are built
by :mod:`mfg_lightning.study.claims` and written by :mod:`mfg_lightning.study.report`.
"""

from __future__ import annotations

import time
from functools import partial
from pathlib import Path

from omegaconf import DictConfig

from mfg_lightning.study import stages as S
from mfg_lightning.study.report import write_report
from mfg_lightning.study.verdicts import Thresholds


def check(cfg: DictConfig) -> None:
    """Refuse a config the study cannot run, naming the key."""
    if not cfg.poses_dir and any("trajectory=kitti" in str(o) for o in cfg.data):
        raise ValueError("poses_dir: set it to KITTI's poses/ directory (00.txt ... 10.txt)")
    if cfg.poses_dir and not Path(cfg.poses_dir).expanduser().is_dir():
        raise FileNotFoundError(f"poses_dir: no such directory: {cfg.poses_dir}")
    known = set(STAGES)
    unknown = [s for s in cfg.stages if s not in known]
    if unknown:
        raise ValueError(f"stages: unknown {unknown}; known: {', '.join(STAGES)}")
    for key in (
        "main_steps",
        "other_steps",
        "val_every",
        "batch_size",
        "eval_batch_size",
        "main_frame_stride",
    ):
        if int(cfg.budget[key]) <= 0:
            raise ValueError(f"budget.{key} must be positive, got {cfg.budget[key]}")
    Thresholds(**cfg.thresholds)


STAGES = (
    "data",
    "main",
    "table1",
    "sparsity",
    "table2",
    "robustness",
    "basis",
    "object_motion",
    "learning_curve",
    "recipe",
)


def run(study: S.Study, report: Path) -> Path:
    """Every selected stage in order, the report rewritten after each.

    The stages that score the main model (``robustness`` … ``learning_curve``) run only when
    ``main`` has a result; ``table1`` is then read from the cache only.
    """
    cfg = study.cfg
    th = Thresholds(**cfg.thresholds)
    main_extra = list(cfg.main)

    def write() -> Path:
        return write_report(study, report, th)

    study.stage("data", lambda: stage_data(study, main_extra))
    write()
    main = study.stage("main", lambda: study.train("main", main_extra, cfg.budget.main_steps))
    write()
    if main:
        t1 = study.stage("table1", lambda: stage_table1(study, main, main_extra))
    else:
        t1 = study.cached("table1")
    write()
    for name, extra, plain, w in sparsity_variants(cfg):
        study.stage(f"sparsity/{name}", partial(stage_sparsity, study, name, extra, plain, w))
        write()
    study.stage("table2", lambda: stage_table2(study))
    write()
    if main:
        study.stage("robustness", lambda: stage_robustness(study, main, main_extra, t1))
        write()
        study.stage("basis", lambda: stage_basis(study, main, main_extra))
        write()
        study.stage("object_motion", lambda: stage_object_motion(study, main, main_extra))
        write()
        study.stage("learning_curve", lambda: stage_learning_curve(main, t1))
        write()
    study.stage("recipe", lambda: stage_recipe(study))
    return write()


# --------------------------------------------------------------------------------------------
# The stages, in the order :func:`run` runs them. Each returns the stage's result (the JSON
# cached by :meth:`mfg_lightning.study.stages.Study.stage`); ``main`` is the main run's result,
# ``t1`` Table 1's (None when not computed).
# --------------------------------------------------------------------------------------------


def stage_data(study: S.Study, main_extra: list[str]) -> dict:
    """``data``: the pairs of every split, and the seconds building each DataModule took."""
    cfg = study.cfg
    out = {}
    for name, extra in (("main", main_extra), ("table2", list(cfg.table2.overrides))):
        start = time.perf_counter()
        dm = study.datamodule(study.train_config(name, extra, 1))
        out[name] = {
            "seconds": time.perf_counter() - start,
            **{f"{s}_pairs": len(dm.dataset(s)) for s in ("train", "val", "test")},
        }
    start = time.perf_counter()
    central = study.test_datamodule(main_extra)
    out["central_test"] = {
        "seconds": time.perf_counter() - start,
        "test_pairs": len(central.dataset("test")),
    }
    return out


def stage_table1(study: S.Study, main: dict, main_extra: list[str]) -> dict | None:
    """``table1``: the main model's scores at every top-k, on the central test and on val."""
    cfg = study.cfg
    model = study.model(main)
    dm = study.datamodule(study.train_config("main", main_extra, 1))
    ks = [float(k) for k in cfg.table1.top_k]
    central = study.test_datamodule(main_extra)
    return {
        "train_overrides": main_extra,
        "test": S.mfg_scores(model, study.loader(central, "test"), ks),
        "val": S.mfg_scores(model, study.loader(dm, "val"), ks),
    }


def sparsity_variants(cfg: DictConfig) -> list[tuple[str, list[str], bool, float]]:
    """The runs of the sparsity sweep, in order: ``(name, overrides, plain, w_s)`` per
    ``sparsity.w_s``, and for ``w_s = 100`` also one with ``sparsity.input_scale`` (not plain)."""
    variants = []
    for ws in cfg.sparsity.w_s:
        variants.append((f"ws{ws:g}", [f"model.loss.w_s={ws}"], True, ws))
        if float(ws) == 100.0:
            scale = cfg.sparsity.input_scale
            variants.append(
                (
                    f"ws{ws:g}_scale{scale:g}",
                    [f"model.loss.w_s={ws}", f"model.net.input_scale={scale}"],
                    False,
                    ws,
                )
            )
    return variants


def stage_sparsity(study: S.Study, name: str, extra: list[str], plain: bool, w: float) -> dict:
    """``sparsity/<name>``: train one variant; its smallest top-k within the val ATE tolerance
    (``k_star``), active fraction and test ATE with all units and at ``k_star``."""
    cfg = study.cfg
    trained = study.train(name, extra, cfg.budget.other_steps)
    model = study.model(trained)
    dm = study.datamodule(study.train_config(name, extra, 1))
    ks = [float(k) for k in cfg.table1.top_k]
    val = S.mfg_scores(model, study.loader(dm, "val"), ks)
    k_star = S.smallest_k(val, float(cfg.sparsity.ate_tolerance))
    test = S.mfg_scores(model, study.loader(dm, "test"), [1.0, k_star or 1.0])
    return {
        **trained,
        "w_s": float(w),
        "plain": plain,
        "val": val,
        "k_star": k_star,
        "active_fraction": S.active_fraction(model, study.loader(dm, "val")),
        "test_full": test["1"].get("ate"),
        "test_k_star": test[f"{k_star or 1.0:g}"].get("ate"),
    }


def stage_table2(study: S.Study) -> dict:
    """``table2``: train on the Table 2 data; MFG and the classical methods on its test split."""
    from mfg_lightning.analysis.scoring import classical_methods, score_methods, scored_rows

    cfg = study.cfg
    extra = list(cfg.table2.overrides)
    trained = study.train("table2", extra, cfg.budget.other_steps)
    model = study.model(trained)
    dm = study.datamodule(study.train_config("table2", extra, 1))
    test = study.loader(dm, "test", forward_only=True)
    ds = dm.dataset("test")
    rows = score_methods(classical_methods(ds.height, ds.width), list(test))
    return {
        **trained,
        "train_pairs": len(dm.dataset("train")),
        "test_pairs": len(ds),
        "mfg": S.mfg_scores(model, test, [float(k) for k in cfg.table2.top_k]),
        "classical": scored_rows(rows),
    }


def stage_robustness(
    study: S.Study, main: dict, main_extra: list[str], t1: dict | None
) -> dict | None:
    """``robustness``: rotation and translation errors by flow coverage bin, of the main model
    (all units, and at Table 1's ``k_star`` when it is sparse) and the classical methods."""
    from mfg_lightning.analysis.scoring import (
        Method,
        classical_methods,
        mfg_top_k_methods,
        score_methods,
    )

    cfg = study.cfg
    model = study.model(main)
    dm = study.datamodule(study.train_config("main", main_extra, 1))
    ds = dm.dataset("test")
    k_star = S.smallest_k(t1["val"], float(cfg.sparsity.ate_tolerance)) if t1 else None
    sparse = k_star is not None and k_star < 1
    predicts = mfg_top_k_methods(model, [None, k_star] if sparse else [None])
    rows = [Method("MFG (all units)", predicts[0])]
    if sparse:
        rows.append(Method(f"MFG k = {100 * k_star:g} % (val)", predicts[1]))
    rows += classical_methods(ds.height, ds.width, oracle=False)
    score_methods(rows, study.loader(dm, "test", forward_only=True))
    edges = [float(e) for e in cfg.robustness.coverage_bins]
    out = {}
    for m in rows:
        rot = S.bin_errors(m.coverage, m.rot_err, edges)
        out[m.name] = {
            "rot_bins": rot,
            "trans_bins": S.bin_errors(m.coverage, m.trans_err, edges),
            "growth": S.growth(rot),
        }
    return {
        "edges": edges,
        "counts": [b["n"] for b in out[rows[0].name]["rot_bins"]],
        "methods": out,
    }


def stage_basis(study: S.Study, main: dict, main_extra: list[str]) -> dict:
    """``basis``: the selectivity of the main model's units (intrinsics of the first test
    sample)."""
    model = study.model(main)
    dm = study.datamodule(study.train_config("main", main_extra, 1))
    K = dm.dataset("test")[0]["intrinsics"]
    return S.selectivity(model, K, int(study.cfg.basis.units))


def stage_object_motion(study: S.Study, main: dict, main_extra: list[str]) -> dict:
    """``object_motion``: the main model's object masks scored on the test split."""
    from hydra.utils import instantiate

    model = study.model(main)
    child = study.train_config("main", main_extra, 1)
    dm = study.datamodule(child)
    om = instantiate(child.object_motion)
    return S.object_motion_scores(
        model,
        study.loader(dm, "test", forward_only=True),
        om,
        float(study.cfg.object_motion.slow_px),
    )


def stage_learning_curve(main: dict, t1: dict | None) -> dict:
    """``learning_curve``: the main run's logged validation curve (samples seen per point) and
    Table 1's test ATE."""
    curve = S.logged_curve(Path(main["checkpoint"]).parents[1])
    for p in curve:
        p["samples"] = int(p["step"]) * main["batch_size"]
    return {"points": curve, "test_ate": (t1 or {}).get("test", {}).get("1", {}).get("ate")}


def stage_recipe(study: S.Study) -> dict:
    """``recipe``: the same number of samples at the CPU batch size and at the paper's recipe;
    each run's curve and its val and test ATE."""
    cfg = study.cfg
    samples = int(cfg.recipe.samples)
    out = {}
    for name, extra, batch in (
        ("cpu", [], int(cfg.budget.batch_size)),
        ("paper", list(cfg.recipe.paper), 1),
    ):
        steps = max(1, samples // batch)
        extra = [*extra, f"trainer.val_check_interval={max(1, steps // 4)}"]
        trained = study.train(f"recipe_{name}", extra, steps)
        model = study.model(trained)
        dm = study.datamodule(study.train_config(f"recipe_{name}", extra, steps))
        curve = S.logged_curve(Path(trained["checkpoint"]).parents[1])
        for p in curve:
            p["samples"] = int(p["step"]) * batch
        out[name] = {
            **trained,
            "curve": curve,
            "val_ate": S.mfg_scores(model, study.loader(dm, "val"), [1.0])["1"].get("ate"),
            "test_ate": S.mfg_scores(model, study.loader(dm, "test"), [1.0])["1"].get("ate"),
        }
    return out
