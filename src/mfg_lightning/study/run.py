"""The stage sequence of the reproduction study: each stage's inputs, in order, the report
rewritten after each (:func:`run`), and the config check (:func:`check`).

Stages are cached by :class:`mfg_lightning.study.stages.Study`; the rows and figures are built
by :mod:`mfg_lightning.study.claims` and written by :mod:`mfg_lightning.study.report`.
"""

from __future__ import annotations

import time
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
    """Every selected stage in order, the report rewritten after each."""
    cfg = study.cfg
    th = Thresholds(**cfg.thresholds)
    main_extra = list(cfg.main)
    write = lambda: write_report(study, report, th)  # noqa: E731

    def data() -> dict:
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

    study.stage("data", data)
    write()
    main = study.stage("main", lambda: study.train("main", main_extra, cfg.budget.main_steps))
    write()

    def table1() -> dict | None:
        model = study.model(main)
        dm = study.datamodule(study.train_config("main", main_extra, 1))
        ks = [float(k) for k in cfg.table1.top_k]
        central = study.test_datamodule(main_extra)
        return {
            "train_overrides": main_extra,
            "test": S.mfg_scores(model, study.loader(central, "test"), ks),
            "val": S.mfg_scores(model, study.loader(dm, "val"), ks),
        }

    t1 = study.stage("table1", table1) if main else study.cached("table1")
    write()

    for ws in cfg.sparsity.w_s:
        variants = [(f"ws{ws:g}", [f"model.loss.w_s={ws}"], True, ws)]
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
        for name, extra, plain, w in variants:

            def sparsity(name=name, extra=extra, plain=plain, w=w) -> dict:
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

            study.stage(f"sparsity/{name}", sparsity)
            write()

    def table2() -> dict:
        from mfg_lightning.analysis.scoring import classical_methods, score_methods, scored_rows

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

    study.stage("table2", table2)
    write()

    def robustness() -> dict | None:
        from mfg_lightning.analysis.scoring import (
            Method,
            classical_methods,
            mfg_top_k_methods,
            score_methods,
        )

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

    if main:
        study.stage("robustness", robustness)
        write()

        def basis() -> dict:
            model = study.model(main)
            dm = study.datamodule(study.train_config("main", main_extra, 1))
            K = dm.dataset("test")[0]["intrinsics"]
            return S.selectivity(model, K, int(cfg.basis.units))

        study.stage("basis", basis)
        write()

        def object_motion() -> dict:
            from hydra.utils import instantiate

            model = study.model(main)
            child = study.train_config("main", main_extra, 1)
            dm = study.datamodule(child)
            om = instantiate(child.object_motion)
            return S.object_motion_scores(
                model,
                study.loader(dm, "test", forward_only=True),
                om,
                float(cfg.object_motion.slow_px),
            )

        study.stage("object_motion", object_motion)
        write()

        def learning_curve() -> dict:
            curve = S.logged_curve(Path(main["checkpoint"]).parents[1])
            for p in curve:
                p["samples"] = int(p["step"]) * main["batch_size"]
            return {"points": curve, "test_ate": (t1 or {}).get("test", {}).get("1", {}).get("ate")}

        study.stage("learning_curve", learning_curve)
        write()

    def recipe() -> dict:
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

    study.stage("recipe", recipe)
    return write()
