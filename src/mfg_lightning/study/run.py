"""The stage sequence of the reproduction study: each stage's inputs, in order, the report
rewritten after each (:func:`run`), and the config check (:func:`check`).

Stages are cached by :class:`mfg_lightning.study.stages.Study`; the rows and figures are built
by :mod:`mfg_lightning.study.claims` and written by :mod:`mfg_lightning.study.report`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mfg_lightning.study import end_to_end as E
from mfg_lightning.study import plan
from mfg_lightning.study import settle as T
from mfg_lightning.study import stages as S
from mfg_lightning.study.measures import coverage_bins
from mfg_lightning.study.report import write_report
from mfg_lightning.study.rules import smallest_k


def run(study: S.Study, report: Path) -> Path:
    """Every selected stage result of the plan (:func:`mfg_lightning.study.plan.results`) in
    order, each computed by its stage's runner (``stage_table.<stage>.runner``), the report
    rewritten after each that ran (a reader follows a long study), and once at the start (a
    study whose stages are all cached writes it once).

    The stages that evaluate the main model (``table1`` … ``methods``) follow it at once,
    while its checkpoint is on this machine (a fresh clone resuming from the committed results
    trains it again only when one of them is not cached); then the other models, each trained
    and evaluated in its own stage.
    """
    written = -1
    for stage, name, arg in plan.results(study.cfg):
        study.stage(name, partial(plan.runner(study.cfg, stage), study, arg))
        if len(study.ran) != written:
            written = len(study.ran)
            write_report(study, report)
    return report


# --------------------------------------------------------------------------------------------
# The runners that conf/reproduce.yaml's stage_table names: ``runner(study, arg)`` computes one
# result of its stage from the argument :func:`mfg_lightning.study.plan.results` gives it. The
# stages that evaluate the main model compute nothing (None: not cached) until the main model's
# result exists.
# --------------------------------------------------------------------------------------------


def _main_extra(study: S.Study) -> list[str]:
    return list(study.cfg.main)


def stage_main(study: S.Study, _: Any = None) -> dict:
    """``main``: the main model, trained under the rule and the main caps."""
    b = study.cfg.budget
    return study.train("main", _main_extra(study), b.main_steps, b.get("main_max_time"))


def _of_main(study: S.Study, f: Callable[[dict, list[str]], dict | None]) -> dict | None:
    main = study.cached("main")
    return f(main, _main_extra(study)) if main is not None else None


def stage_table1(study: S.Study, _: Any = None) -> dict | None:
    """``table1``: the main model at every top-k (:func:`_table1`)."""
    return _of_main(study, lambda m, extra: _table1(study, m, extra))


def stage_basis(study: S.Study, _: Any = None) -> dict | None:
    """``basis``: claim 5's measurements of the main model (:func:`_basis`)."""
    return _of_main(study, lambda m, extra: _basis(study, m, extra))


def stage_object_motion(study: S.Study, _: Any = None) -> dict | None:
    """``object_motion``: the main model's object masks (:func:`_object_motion`)."""
    return _of_main(study, lambda m, extra: _object_motion(study, m, extra))


def stage_methods(study: S.Study, _: Any = None) -> dict | None:
    """``methods``: the main model against the classical methods (:func:`_methods`)."""
    t1 = study.cached("table1")
    return _of_main(study, lambda m, extra: _methods(study, m, extra, t1))


def stage_settle(study: S.Study, run: tuple[str, int]) -> dict:
    """``settle/<flow>_seed<n>`` and ``settle/strided_seed<n>``: one model of the 2 × 2."""
    kind, seed = run
    return T.stage_strided(study, seed) if kind == "strided" else T.stage_seed(study, kind, seed)


def stage_converge(study: S.Study, run: tuple[str, int]) -> dict:
    """``converge/<variant>_seed<n>``: one model under the rotation rule."""
    return T.stage_converge(study, *run)


def stage_end_to_end(study: S.Study, run: tuple[str, int | None]) -> dict | None:
    """``end_to_end/…``: one model of the end-to-end comparison."""
    return E.stage_end_to_end(study, *run)


def stage_size(study: S.Study, point: tuple[int, int | None] | None) -> dict:
    """``size/stride<N>[_seed<n>]`` (:func:`_size`), or ``size/classical`` (``point`` None)."""
    return _size_classical(study) if point is None else _size(study, *point)


def stage_data(study: S.Study, _: Any = None) -> dict:
    """``data``: the pairs of every split, and the seconds building each DataModule took."""
    cfg, main_extra = study.cfg, _main_extra(study)
    out = {}
    for name, extra in (("main", main_extra), ("table2", list(cfg.table2.overrides))):
        start = time.perf_counter()
        dm = study.datamodule(study.train_config(name, extra))
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


def stage_flow_error(study: S.Study, _: Any = None) -> dict | None:
    """``flow_error``: the estimated flow's error against the rendered worlds' exact flow, per
    frame offset, on the central test pairs and on validation (from the flow cache: no model).
    None when the study's flow is exact (there is no estimate to measure)."""
    main_extra = _main_extra(study)
    central = study.test_datamodule(main_extra)
    test = central.dataset("test")
    if not hasattr(test, "quality_by_offset"):
        return None
    dm = study.datamodule(study.train_config("main", main_extra), splits=("val",))
    return {"test": test.quality_by_offset(), "val": dm.dataset("val").quality_by_offset()}


def stage_seed(study: S.Study, seed: int) -> dict:
    """``seeds/seed<n>``: the main model's setting trained again at another ``seed`` (the same
    pairs, rule and step cap; the seed sets the initialisation and the data order, the worlds are
    ``dataset.scene_seed``'s), then every measurement the verdicts take from the main model:
    Table 1's scores (central test and validation at every k), MFG's errors by moving-object
    coverage, the basis and the object masks. With the main model (seed 0) these give the seed
    spread from which every verdict's tolerance is derived (:mod:`mfg_lightning.study.noise`).
    ``seeds.max_time`` caps its time: a machine without native bfloat16 trains at about half
    the rate of the one that trained the main model, and the rule, not the clock, should end a
    seed's run."""
    main_extra = _main_extra(study)
    extra = [*main_extra, f"seed={seed}"]
    trained = study.train(f"seed{seed}", extra, *_main_caps(study.cfg))
    t1 = _table1(study, trained, extra)
    return {
        **trained,
        "seed": seed,
        "table1": t1,
        "methods": _methods(study, trained, extra, t1, classical=False),
        "basis": _basis(study, trained, extra),
        "object_motion": _object_motion(study, trained, extra),
    }


def _main_caps(cfg: DictConfig) -> tuple[int, str | None]:
    """The step and time caps of a model of the main setting trained again (a seed, the twin):
    the main model's step cap and ``seeds.max_time`` (a safety net the rule should not meet on
    a machine slower than the one that trained the main model)."""
    return int(cfg.budget.main_steps), cfg.seeds.get("max_time") or cfg.budget.get("main_max_time")


def stage_twin(study: S.Study, _: Any = None) -> dict:
    """``twin``: the main model's exact-flow twin, the same worlds, pairs, seed, rule and caps
    with the model reading the exact flow (``twin.overrides``, ``dataset.input_flow=exact``),
    to separate the flow from the method (ATE * / ATE †) and to give the object masks the
    paper's protocol (a model trained on ground-truth flow). Scored on the exact central test
    (Table 1 at every k, validation too), on the DIS central test (all units), beside every
    classical method on the exact central test; its object masks on the exact and on the DIS
    test flow, the threshold and filters chosen on validation as for the main model."""
    main_extra = _main_extra(study)
    cfg = study.cfg
    extra = [*main_extra, *cfg.twin.overrides]
    trained = study.train("twin", extra, *_main_caps(cfg))
    t1 = _table1(study, trained, extra)
    dis = study.test_datamodule(main_extra)
    return {
        **trained,
        "table1": t1,
        "dis_test": S.mfg_scores(study.model(trained), study.loader(dis, "test"), [1.0])["1"],
        "methods": _methods(study, trained, extra, t1),
        # the DIS datamodule: its samples carry both flows (object_motion_by_flow scores each)
        "object_motion": _object_motion(study, trained, main_extra),
    }


def stage_learned(study: S.Study, _: Any = None) -> dict:
    """``learned``: the main model's setting on the framework's learned flow (``flow=learned``,
    the shipped weights, ``learned.overrides``): the paper's KITTI protocol feeds MFG a learned
    estimator's flow. The same worlds, pairs, seed, rule and caps as the main model; scored on
    the learned flow's central test (Table 1 at every k, validation too) and on DIS's (all
    units); the learned flow's error against the exact flow per offset on the central test
    pairs and on validation, as ``flow_error`` gives DIS's. A diagnostic beside the DIS model
    and the exact-flow twin: no verdict reads it."""
    main_extra = _main_extra(study)
    cfg = study.cfg
    extra = [*main_extra, *cfg.learned.overrides]
    trained = study.train("learned", extra, *_main_caps(cfg))
    t1 = _table1(study, trained, extra)
    dis = study.test_datamodule(main_extra)
    central = study.test_datamodule(extra)
    dm = study.datamodule(study.train_config("learned", extra))
    return {
        **trained,
        "table1": t1,
        "dis_test": S.mfg_scores(study.model(trained), study.loader(dis, "test"), [1.0])["1"],
        "flow_error": {
            "test": central.dataset("test").quality_by_offset(),
            "val": dm.dataset("val").quality_by_offset(),
        },
    }


def _size_extra(cfg: DictConfig, stride: int, seed: int | None) -> list[str]:
    extra = [*cfg.size.overrides, f"dataset.frame_stride={int(stride)}"]
    return extra + ([f"seed={seed}"] if seed is not None else [])


def _size(study: S.Study, stride: int, seed: int | None) -> dict:
    """``size/stride<N>[_seed<n>]``: the Table 2 setting (``size.overrides``: the +1 pairs, the
    exact flow) trained on every ``stride``-th source frame of the study's training split,
    under the other models' caps; its test scores with all units (the full 09 / 10 +1 pairs,
    whatever the stride: the stride thins training only)."""
    extra = _size_extra(study.cfg, stride, seed)
    name = f"size_{S.size_name(stride, seed)}"
    trained = _other(study, name, extra)
    dm = study.datamodule(study.train_config(name, extra))
    return {
        **trained,
        "stride": int(stride),
        "seed": int(study.cfg.seed) if seed is None else int(seed),
        "train_pairs": len(dm.dataset("train")),
        "test_pairs": len(dm.dataset("test")),
        "test": S.mfg_scores(study.model(trained), study.loader(dm, "test"), [1.0])["1"],
    }


def _size_classical(study: S.Study) -> dict:
    """``size/classical``: every classical method on the size curve's test pairs (they do not
    train, so one row each whatever the training set's size)."""
    from mfg_lightning.analysis.scoring import classical_methods, score_methods, scored_rows

    # the main model's stride: its training pairs are the ones the flow cache has (stride 1
    # would render every other frame of 00-08 in prepare_data, for a test split that is the same)
    extra = _size_extra(study.cfg, int(study.cfg.budget.main_frame_stride), None)
    dm = study.datamodule(study.train_config("size_classical", extra))
    ds = dm.dataset("test")
    rows = score_methods(classical_methods(ds.height, ds.width), study.loader(dm, "test"))
    return {"test_pairs": len(ds), "classical": scored_rows(rows)}


def _table1(study: S.Study, main: dict, main_extra: list[str]) -> dict | None:
    """``table1``: the main model's scores at every top-k, on the central test and on val."""
    cfg = study.cfg
    model = study.model(main)
    dm = study.datamodule(study.train_config("main", main_extra))
    ks = [float(k) for k in cfg.table1.top_k]
    central = study.test_datamodule(main_extra)
    return {
        "train_overrides": main_extra,
        "test": S.mfg_scores(model, study.loader(central, "test"), ks),
        "val": S.mfg_scores(model, study.loader(dm, "val"), ks),
    }


def _other(study: S.Study, name: str, extra: list[str], steps: int | None = None) -> dict:
    """Train one of the other models under the common rule and the other models' caps."""
    b = study.cfg.budget
    return study.train(name, extra, steps or int(b.other_steps), b.get("other_max_time"))


def stage_sparsity(study: S.Study, v: plan.SparsityVariant) -> dict:
    """``sparsity/<name>``: train one variant on the main model's data (±1, ±2); its smallest
    top-k within the val ATE tolerance (``k_star``), active fraction, whether it collapsed (no
    unit active on the average input), and test ATE with all units and at ``k_star``. The
    plain variant at the main model's w_s is the main model's run when that serves
    (:func:`main_run_serves`)."""
    main = study.cached("main")
    cfg = study.cfg
    extra, settings = list(cfg.main), v.settings()
    # the main model's recorded w_s, a number, against the variant's
    same = v.plain and main is not None and main["recipe"]["w_s"] == v.w_s
    if same and S.main_run_serves(study, main):
        trained, settings = {**main, "same_as": "main"}, {}
    else:
        b = cfg.budget
        trained = study.train(v.name, extra, int(b.other_steps), b.get("other_max_time"), settings)
    model = study.model(trained)
    dm = study.datamodule(study.train_config(trained["name"], extra, settings=settings))
    ks = [float(k) for k in cfg.table1.top_k]
    val = S.mfg_scores(model, study.loader(dm, "val"), ks)
    k_star = smallest_k(val, float(cfg.sparsity.ate_tolerance))
    test = S.mfg_scores(model, study.loader(dm, "test"), [1.0, k_star or 1.0])
    active = S.active_fraction(model, study.loader(dm, "val"))
    units = int(model.net.hidden_units)
    return {
        **trained,
        "w_s": v.w_s,
        "plain": v.plain,
        "val": val,
        "k_star": k_star,
        "active_fraction": active,
        "collapsed": active is None or active * units < 1.0,
        "test_full": test["1"].get("ate"),
        "test_k_star": test[f"{k_star or 1.0:g}"].get("ate"),
    }


def stage_table2(study: S.Study, exact: bool | None = None) -> dict:
    """``table2``: train on the Table 2 data; MFG and the classical methods on its test split.
    ``exact`` (``table2_exact``): every model and method reads the exact flow
    (``table2.exact``), the paper's Virtual KITTI protocol; ``table2`` (the study's flow) is
    the extension beside it."""
    from mfg_lightning.analysis.scoring import classical_methods, score_methods, scored_rows

    cfg = study.cfg
    name = "table2_exact" if exact else "table2"
    extra = [*cfg.table2.overrides, *(cfg.table2.exact if exact else [])]
    trained = _other(study, name, extra)
    model = study.model(trained)
    dm = study.datamodule(study.train_config(name, extra))
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


def _methods(
    study: S.Study, main: dict, main_extra: list[str], t1: dict | None, classical: bool = True
) -> dict:
    """``methods``: the main model (all units, and at Table 1's validation ``k_star``) against
    every classical baseline on every test frame of 09 and 10: ATE † (the +1 pairs), ATE *
    (±1, ±2), RPE; and the rotation and translation errors of the +1 pairs by the image
    fraction covered by moving objects (claim 4). ``classical=False``: MFG's rows only (a
    seed's)."""
    from mfg_lightning.analysis.scoring import (
        Method,
        classical_methods,
        mfg_top_k_methods,
        score_methods,
        scored_rows,
    )

    cfg = study.cfg
    model = study.model(main)
    central = study.test_datamodule(main_extra)
    ds = central.dataset("test")
    k_star = smallest_k(t1["val"], float(cfg.sparsity.ate_tolerance)) if t1 else None
    sparse = k_star is not None and k_star < 1
    predicts = mfg_top_k_methods(model, [1.0, k_star] if sparse else [1.0])
    rows = [Method("MFG (all units)", predicts[0])]
    if sparse:
        rows.append(Method(f"MFG k = {100 * k_star:g} % (val)", predicts[1]))
    if classical:
        rows += classical_methods(ds.height, ds.width)
    score_methods(rows, study.loader(central, "test"))
    edges = [float(e) for e in cfg.robustness.coverage_bins]
    bins = coverage_bins(rows, ds.samples, edges)
    return {
        "test_pairs": len(ds),
        "forward_pairs": sum(t == s + 1 for _, s, t in ds.samples),
        "rows": scored_rows(rows),
        "edges": edges,
        "counts": [b["n"] for b in bins[rows[0].name]["rot_bins"]],
        "bins": bins,
    }


def _basis(study: S.Study, main: dict, main_extra: list[str]) -> dict:
    """``basis``: claim 5's measurements of the main model (validation activations,
    intrinsics of the first test sample)."""
    from mfg_lightning.study.measures import basis_measurements

    model = study.model(main)
    dm = study.datamodule(study.train_config("main", main_extra))
    K = dm.dataset("test")[0]["intrinsics"]
    return basis_measurements(model, study.loader(dm, "val"), K, int(study.cfg.basis.units))


def _object_motion(study: S.Study, main: dict, main_extra: list[str]) -> dict:
    """``object_motion``: the main model's object masks on the test split (+1 pairs), the
    filters against the threshold chosen on validation, on exact and on estimated flow."""
    from hydra.utils import instantiate

    from mfg_lightning.study.measures import object_motion_by_flow

    cfg = study.cfg
    model = study.model(main)
    child = study.train_config("main", main_extra)
    dm = study.datamodule(child)
    return object_motion_by_flow(
        model,
        study.loader(dm, "val", forward_only=True),
        study.loader(dm, "test", forward_only=True),
        instantiate(child.object_motion),
        [float(x) for x in cfg.object_motion.thresholds],
        float(cfg.object_motion.slow_px),
        S.to_container(cfg.object_motion.get("filter_grid")),
    )


def stage_balance(study: S.Study, _: Any = None) -> dict:
    """``balance``: the paper's printed balancing reading (squared norm ratio) on the main
    model's data at the other models' budget: its test scores (claim 3's rotation) and claim
    5's measurements, beside the released code's reading (the main model)."""
    from mfg_lightning.study.measures import basis_measurements

    cfg = study.cfg
    extra = [*cfg.main, "model.loss.balance_squared=true"]
    trained = _other(study, "balance_squared", extra)
    model = study.model(trained)
    dm = study.datamodule(study.train_config("balance_squared", extra))
    K = dm.dataset("test")[0]["intrinsics"]
    return {
        **trained,
        "test": S.mfg_scores(model, study.loader(dm, "test"), [1.0])["1"],
        "basis": basis_measurements(model, study.loader(dm, "val"), K, int(cfg.basis.units)),
    }


def stage_recipe(study: S.Study, _: Any = None) -> dict:
    """``recipe``: row R, the CPU recipe against the paper's (batch 1, lr 1e-5), each under
    the common rule and trained for at least ``recipe.epochs`` epochs of the main model's
    training pairs (the rule's ``min_steps`` raised to that many steps); each run's curve and
    its val and test ATE †.

    The CPU recipe is the main model's own setting: its run is the main model's (the same
    overrides and seed would train the same model again), unless that is not cached or is
    shorter than ``recipe.epochs``. The paper's recipe has its own time cap,
    ``budget.recipe_max_time`` (an epoch at batch 1 is ~26 K steps), and the other models' step
    cap counted in samples (``budget.other_steps × budget.batch_size`` steps at batch 1).
    When the CPU recipe is the main model, its val and test ATE † are Table 1's at k = 100 %
    (the same model on the same splits), so a fresh clone does not train the main model again
    for them."""
    main = study.cached("main")
    cfg = study.cfg
    b = cfg.budget
    main_extra = list(cfg.main)
    dm = study.datamodule(study.train_config("recipe_cpu", main_extra))
    pairs = len(dm.dataset("train"))
    samples = math.ceil(float(cfg.recipe.epochs) * pairs)
    out = {}
    for name, extra, batch in (
        ("cpu", [], int(b.batch_size)),
        ("paper", list(cfg.recipe.paper), 1),
    ):
        epoch_steps = max(1, math.ceil(samples / batch))
        scores = None
        if name == "cpu" and S.main_run_serves(study, main) and main["samples_seen"] >= samples:
            trained = {**main, "same_as": "main"}
            if (t1 := study.cached("table1")) is not None:
                scores = (t1["val"]["1"].get("ate"), t1["test"]["1"].get("ate"))
        else:
            rule_min = max(int(cfg.convergence.min_steps), epoch_steps)
            extra = [*main_extra, *extra, f"callbacks.convergence.min_steps={rule_min}"]
            # the other models' step cap in samples (other_steps at budget.batch_size): at
            # batch 1 a step count meant for batch 16 would stop the run before its time cap
            steps = max(math.ceil(int(b.other_steps) * int(b.batch_size) / batch), epoch_steps)
            max_time = b.get("recipe_max_time") or b.get("other_max_time")
            trained = study.train(f"recipe_{name}", extra, steps, max_time)
        run_dm = study.datamodule(study.train_config(f"recipe_{name}", trained["overrides"]))
        if scores is None:
            model = study.model(trained)
            scores = tuple(
                S.mfg_scores(model, study.loader(run_dm, split), [1.0])["1"].get("ate")
                for split in ("val", "test")
            )
        out[name] = {
            **trained,
            "epochs": trained["samples_seen"] / max(len(run_dm.dataset("train")), 1),
            "val_ate": scores[0],
            "test_ate": scores[1],
        }
    return out
