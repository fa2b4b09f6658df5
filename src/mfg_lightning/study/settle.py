"""The experiments that settle the Table-2 sentences (S4–S6) and the object sentences (S9, S10).

Table 2's setting (the VKITTI-sized set: 1,696 training and 446 test +1 pairs, ``table2``) is
trained at ``settle.seeds`` on each of ``settle.flows`` (the exact flow, the paper's protocol,
and DIS): a 2 × 2 of flow × method (MFG, the robust continuous method IRLS) on the very same
test pairs, with MFG's spread over seeds measured at this data size rather than borrowed from
the main model. Every model trains for the same ``settle.steps`` (an equal budget stated before
training: :class:`mfg_lightning.run.convergence.ConvergenceStop` with ``budget_steps``; its
last checkpoint is evaluated), in ``trainer.precision=32-true`` whatever the CPU, so that seeds
trained on different machines differ by their seed only.

Each stage keeps **per-pair** values (rotation and translation errors of every test pair at
every k; the object masks' pixel counts and the object-velocity error by object size × speed
bin), so that the verdicts (:mod:`mfg_lightning.study.intervals`) can resample the test pairs
(a paired bootstrap) as well as the seeds. The stages:

* ``settle/<flow>_seed<n>``: one model of the 2 × 2 (:func:`stage_seed`);
* ``settle_classical/<flow>``: every classical method on the same test pairs
  (:func:`stage_classical`; they do not train, so one stage per flow);
* ``settle/strided_seed<n>``: Table 2's size drawn as every ``settle.strided.stride``-th source
  frame of the whole training split instead of 224 contiguous frames of 00–07, on the exact flow
  and tested on the same pairs (:func:`stage_strided`): contiguous against strided at a matched
  size separates the training set's diversity from its size.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch.utils.data import DataLoader

from mfg_lightning.study import stages as S

__all__ = [
    "converge_runs",
    "evaluated",
    "object_velocity_pairs",
    "seed_runs",
    "stage_classical",
    "stage_converge",
    "stage_objects",
    "stage_seed",
    "stage_strided",
    "strided_runs",
    "table2_extra",
    "test_loader",
    "train_settled",
]


def seed_runs(cfg: DictConfig) -> list[tuple[str, int]]:
    """The 2 × 2's models, ``(flow, seed)``, seed by seed (each seed on every flow before the
    next seed: a study stopped half-way has both flows at as many seeds)."""
    return [(str(f), int(s)) for s in cfg.settle.seeds for f in cfg.settle.flows]


#: The variants of stage ``converge``: the 2 × 2's flows, the unclamped weights, the largest set.
VARIANTS = ("exact", "dis", "unclamped", "largest")


def converge_runs(cfg: DictConfig) -> list[tuple[str, int]]:
    """The converged models, ``(variant, seed)``: each group of ``converge.variants`` seed by
    seed as :func:`seed_runs`, then the next group."""
    groups = cfg.converge.variants
    return [(str(v), int(s)) for g in groups for s in cfg.converge.seeds for v in g]


def strided_runs(cfg: DictConfig) -> list[int]:
    """The seeds of the strided training set (``settle.strided.seeds``)."""
    return [int(s) for s in cfg.settle.strided.seeds]


def _flow_overrides(cfg: DictConfig, flow: str) -> list[str]:
    if flow == "exact":
        return list(cfg.table2.exact)
    if flow == "dis":
        return []
    if flow == "learned":  # stage end_to_end's two-stage models
        return list(cfg.learned.overrides)
    raise ValueError(f"settle.flows: {flow!r} is not a flow of the study (exact, dis, learned)")


def table2_extra(cfg: DictConfig, flow: str) -> list[str]:
    """Table 2's data on ``flow`` with the 2 × 2's training settings."""
    return [*cfg.table2.overrides, *_flow_overrides(cfg, flow), *cfg.settle.overrides]


def train_settled(study: S.Study, name: str, extra: list[str], converge: bool = False) -> dict:
    """Train (or resume) ``name`` for the equal budget ``settle.steps``, or (``converge``) under
    ``converge.rule`` capped at ``converge.steps`` and ``converge.max_time``."""
    c = study.cfg.converge
    if converge:
        return study.train(name, [*extra, *c.rule], int(c.steps), c.max_time)
    steps = int(study.cfg.settle.steps)
    budget = [f"callbacks.convergence.budget_steps={steps}"]
    return study.train(name, [*extra, *budget], steps, study.cfg.budget.get("other_max_time"))


def test_loader(study: S.Study, flow: str, more: tuple = ()) -> tuple[Any, DataLoader]:
    """Table 2's test pairs (+1 only) on ``flow`` (``more``: overrides of its estimator): the
    same pairs for every model and method."""
    extra = [*table2_extra(study.cfg, flow), *more]
    dm = study.datamodule(study.train_config(f"settle_{flow}", extra), ("val", "test"))
    return dm, study.loader(dm, "test", forward_only=True)


def _rounded(xs: list[float], digits: int = 7) -> list[float]:
    # per-pair values in the committed JSON: 7 significant digits are far below any spread
    return [float(f"{x:.{digits}g}") for x in xs]


def mfg_pairs(model: Any, loader: DataLoader, ks: list[float]) -> dict[str, dict[str, Any]]:
    """MFG at every k (``"1"``: all units): the trajectory metrics and the per-pair rotation
    (rad) and translation (m) errors, in the loader's order."""
    from mfg_lightning.analysis.scoring import Method, mfg_top_k_methods, score_methods

    predicts = mfg_top_k_methods(model, [float(k) for k in ks])
    rows = [Method(f"k={k:g}", p) for k, p in zip(ks, predicts, strict=True)]
    score_methods(rows, loader, warm_up=False)
    return {
        f"{k:g}": {
            "metrics": {key: float(v) for key, v in m.evaluator.compute().metrics.items()},
            "rot_err": _rounded(m.rot_err),
            "trans_err": _rounded(m.trans_err),
        }
        for k, m in zip(ks, rows, strict=True)
    }


def stage_seed(study: S.Study, flow: str, seed: int) -> dict:
    """``settle/<flow>_seed<n>``: Table 2's model on ``flow`` at ``seed`` for the equal budget;
    MFG's per-pair errors at every ``table2.top_k`` on the test pairs; on the exact flow also
    the object masks and the object velocity (:func:`object_velocity_pairs`), the threshold and
    the filters' constants chosen on validation."""
    extra = [*table2_extra(study.cfg, flow), f"seed={seed}"]
    return evaluated(study, train_settled(study, f"settle_{flow}_seed{seed}", extra), flow, seed)


def stage_converge(study: S.Study, variant: str, seed: int) -> dict:
    """``converge/<variant>_seed<n>``: one model of ``converge.variants`` trained under the
    rotation rule (``converge.rule``), evaluated as :func:`stage_seed` on the 2 × 2's test pairs
    of its flow (``largest``: the exact ones, all units only, as :func:`stage_strided`)."""
    cfg = study.cfg
    if variant not in VARIANTS:
        raise ValueError(f"converge.variants: unknown {variant!r}; known: {', '.join(VARIANTS)}")
    flow = "dis" if variant == "dis" else "exact"
    extra = {
        "unclamped": [*table2_extra(cfg, flow), *cfg.converge.unclamped],
        "largest": [
            *cfg.size.overrides, *cfg.settle.overrides,
            f"dataset.frame_stride={int(cfg.size.strides[-1])}",
        ],
    }.get(variant, table2_extra(cfg, flow))  # fmt: skip
    trained = train_settled(study, f"converge_{variant}_seed{seed}", [*extra, f"seed={seed}"], True)
    return {**evaluated(study, trained, flow, seed, variant != "largest"), "variant": variant}


def evaluated(
    study: S.Study, trained: dict, flow: str, seed: int, full: bool = True, more: tuple = ()
) -> dict:
    """A trained model's result on the 2 × 2's test pairs of ``flow`` (``more``: overrides of
    its estimator): MFG's per-pair errors at every ``table2.top_k`` and, on the exact flow, the
    objects (:func:`object_velocity_pairs`); all units only when not ``full``."""
    model = study.model(trained)
    dm, test = test_loader(study, flow, more)
    train_cfg = study.train_config(
        trained["name"], list(trained["overrides"]), settings=trained.get("settings")
    )
    ks = [float(k) for k in study.cfg.table2.top_k] if full else [1.0]
    out = {
        **trained,
        "flow": flow,
        "seed": seed,
        "train_pairs": len(study.datamodule(train_cfg, ("train",)).dataset("train")),
        "test_pairs": len(test.dataset),
        "mfg": mfg_pairs(model, test, ks),
    }
    if flow == "exact" and full:
        out["objects"] = object_velocity_pairs(study, model, study.loader(dm, "val", True), test)
    return out


def stage_objects(study: S.Study, seed: int) -> dict | None:
    """``objects/seed<n>``: the converged exact-flow model of ``seed`` (``converge/exact_seed<n>``;
    None until it exists) on the object test set (``objects.world``: Table 2's test pairs in
    worlds with more movers), the threshold and the filters' constants chosen on Table 2's
    validation over ``objects.filter_grid`` (:func:`object_velocity_pairs`)."""
    cfg = study.cfg
    if (trained := study.cached(f"converge/exact_seed{seed}")) is None:
        return None
    extra = [*table2_extra(cfg, "exact"), *cfg.objects.world]
    dm, _ = test_loader(study, "exact")
    objects_dm = study.datamodule(study.train_config("objects", extra), ("test",))
    if getattr(objects_dm.dataset("test"), "crossing", None) is None:
        raise ValueError(
            f"objects.world: {list(cfg.objects.world)} renders no object crossing the road "
            "(it needs rendered worlds, flow=dis, and dataset.world.crossing_per_100m > 0)"
        )
    test = study.loader(objects_dm, "test", forward_only=True)
    val = study.loader(dm, "val", forward_only=True)
    grid = S.to_container(cfg.objects.filter_grid)
    objects = object_velocity_pairs(study, study.model(trained), val, test, grid)
    return {"model": trained["name"], "seed": seed, "world": list(cfg.objects.world),
            "test_pairs": len(test.dataset), "objects": objects}  # fmt: skip


def stage_classical(study: S.Study, flow: str) -> dict:
    """``settle_classical/<flow>``: every classical method on the 2 × 2's test pairs of
    ``flow``, with per-pair errors."""
    from mfg_lightning.analysis.scoring import classical_methods, score_methods, scored_rows

    _, test = test_loader(study, flow)
    ds = test.dataset.dataset
    rows = score_methods(classical_methods(ds.height, ds.width), list(test))
    scored = scored_rows(rows, per_sample=True)
    for r in scored:
        r["rot_err"], r["trans_err"] = _rounded(r["rot_err"]), _rounded(r["trans_err"])
        r.pop("coverage", None)
    return {"flow": flow, "test_pairs": len(test.dataset), "classical": scored}


def stage_strided(study: S.Study, seed: int) -> dict:
    """``settle/strided_seed<n>``: Table 2's setting on the exact flow trained on every
    ``settle.strided.stride``-th source frame of the study's training split (00–08, about Table
    2's size) for the same budget; MFG's per-pair errors (all units) on the 2 × 2's exact test
    pairs, so that it compares pair by pair with the contiguous seeds."""
    cfg = study.cfg
    stride = int(cfg.settle.strided.stride)
    extra = [
        *cfg.size.overrides, *cfg.settle.overrides, f"dataset.frame_stride={stride}",
        f"seed={seed}",
    ]  # fmt: skip
    trained = train_settled(study, f"settle_strided_seed{seed}", extra)
    return {**evaluated(study, trained, "exact", seed, full=False), "stride": stride}


# --------------------------------------------------------------------------------------------
# Object masks and velocity, per test pair
# --------------------------------------------------------------------------------------------


def _components(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 8-connected components of a boolean ``(H, W)`` mask: ``(labels, areas)``, label 0
    the background (area 0)."""
    import cv2

    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    areas = stats[:, cv2.CC_STAT_AREA].astype(np.int64)
    areas[0] = 0
    return labels, areas


def _bin_of(x: np.ndarray, edges: list[float]) -> np.ndarray:
    """Index of the bin ``[edges[i], edges[i+1])`` holding each ``x`` (the last bin open)."""
    return np.clip(np.searchsorted(np.asarray(edges[1:-1]), x, side="right"), 0, len(edges) - 2)


@torch.no_grad()
def object_velocity_pairs(
    study: S.Study, model: Any, val: DataLoader, test: DataLoader, grid: Any = None
) -> dict[str, Any]:
    """The object masks and the object velocity of the paper's filters and of the plain
    threshold, per test pair, both chosen on validation
    (:func:`mfg_lightning.study.measures.choose_threshold` and ``choose_filters``).

    Per pair and method: the mask's true positive, false positive and false negative pixels
    (S9's IoU and precision, pooled over resampled pairs), and per object size × speed bin the
    sum of the object-velocity error over the true objects' pixels and their count (S10), and
    per bin the sum of the true speed over the same pixels (``speed``: the error of reporting
    no motion, the bound of S10's absolute reading). An
    object is an 8-connected component of the true moving-object mask; its size is its area as
    a fraction of the image, its speed the mean length of its true object flow (px/frame at the
    model input); ``object_motion.size_bins`` and ``speed_bins`` give the edges. The velocity
    error of a pixel is the length of (extracted object flow − true object flow), the extracted
    flow being 0 where the method's mask is off: a missed object costs its whole speed.
    """
    from hydra.utils import instantiate

    from mfg_lightning.data.sample import model_inputs
    from mfg_lightning.motion.object_motion import extract_object_motion, threshold_baseline
    from mfg_lightning.study.measures import FILTER_GRID, choose_filters, choose_threshold

    cfg = study.cfg
    om = cfg.object_motion
    child = study.train_config("settle_objects", list(cfg.table2.overrides))
    base = instantiate(child.object_motion)
    grid = grid or S.to_container(om.get("filter_grid")) or FILTER_GRID
    chosen = choose_threshold(model, val, base, [float(x) for x in om.thresholds], "flow")
    filters = choose_filters(model, val, base, grid, "flow")
    tuned = dataclasses.replace(
        base, baseline_threshold=chosen["threshold"], theta_d=filters["theta_d"],
        theta_p=filters["theta_p"],
    )  # fmt: skip
    size_edges = [float(x) for x in om.size_bins]
    speed_edges = [float(x) for x in om.speed_bins]
    n_bins = (len(size_edges) - 1) * (len(speed_edges) - 1)
    methods = ("filters", "threshold")
    per: dict[str, Any] = {
        m: {"tp": [], "fp": [], "fn": [], "err": [], "pixels": []} for m in methods
    }
    per["speed"] = []
    for batch in test:
        if batch is None:
            continue
        flow, valid, _ = model_inputs(batch)
        out = model(flow)
        res = extract_object_motion(flow, out.v_t, out.v_omega, batch["depth"], tuned, valid=valid)
        thr = threshold_baseline(res.residual, tuned.baseline_threshold, res.valid)
        gt = batch["object_mask"].bool() & res.valid
        gt_flow = batch["object_flow"].double()
        fields = {
            "filters": (res.mask, res.object_flow),
            "threshold": (thr, res.residual * thr[:, None]),
        }
        pix = res.valid.shape[-2] * res.valid.shape[-1]
        for b in range(gt.shape[0]):
            g = gt[b].numpy()
            labels, areas = _components(g)
            speed_sum = np.bincount(
                labels.ravel(), weights=gt_flow[b].norm(dim=0).numpy().ravel(),
                minlength=len(areas),
            )  # fmt: skip
            speed = speed_sum / np.maximum(areas, 1)
            bins = _bin_of(areas / pix, size_edges) * (len(speed_edges) - 1) + _bin_of(
                speed, speed_edges
            )
            pixel_bin = bins[labels[g]]
            # the error of reporting no motion at all: the true objects' own speed
            still = gt_flow[b].norm(dim=0).numpy()[g]
            per["speed"].append(_rounded(np.bincount(pixel_bin, still, n_bins).tolist()))
            for m in methods:
                mask, field = fields[m]
                p = mask[b].numpy() & res.valid[b].numpy()
                per[m]["tp"].append(int((p & g).sum()))
                per[m]["fp"].append(int((p & ~g).sum()))
                per[m]["fn"].append(int((~p & g).sum()))
                err = (field[b].double() - gt_flow[b]).norm(dim=0).numpy()[g]
                per[m]["err"].append(_rounded(np.bincount(pixel_bin, err, n_bins).tolist()))
                per[m]["pixels"].append(np.bincount(pixel_bin, minlength=n_bins).tolist())
    return {
        "threshold": chosen,
        "filters_choice": filters,
        "size_bins": size_edges,
        "speed_bins": speed_edges,
        "pairs": per,
    }
