"""Scoring egomotion methods over a dataloader: MFG at any k and the classical baselines, on the
very same flows, with the published trajectory metrics and per-sample errors.

A :class:`Method` is a name and a function of a batch returning ``(t, ω)`` ``(B, 3)`` (metres and
radians per frame). :func:`score_methods` runs every method on every batch, feeds each one's
:class:`~mfg_lightning.metrics.evaluator.TrajectoryEvaluator` (ATE †/*, RPE, drift) and keeps
per-sample errors (:func:`~mfg_lightning.metrics.frame_errors.frame_errors`) beside the fraction
of the image covered by independently moving objects (``object_mask``, when the batch has one).
Used by ``bench/accuracy.py`` and ``python -m mfg_lightning.reproduce``.

The classical methods see one pair of frames and cannot know the translation's scale: they are
given the ground-truth length (:mod:`mfg_lightning.motion.baselines`), as monocular methods are
scored.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from mfg_lightning.core import geometry
from mfg_lightning.data.sample import model_inputs
from mfg_lightning.metrics.evaluator import TrajectoryEvaluator
from mfg_lightning.metrics.frame_errors import frame_errors
from mfg_lightning.models.mfg import validate_top_k
from mfg_lightning.motion import baselines

__all__ = [
    "Method",
    "classical_methods",
    "mfg_method",
    "mfg_top_k_methods",
    "object_coverage",
    "score_methods",
    "scored_rows",
]

Predict = Callable[[dict], tuple[Tensor, Tensor]]


@dataclass
class Method:
    """One row: a name, what it computes, and what it measured.

    Attributes:
        name: the row's label.
        predict: batch → ``(t, ω)``, ``(B, 3)`` each.
        note: shown beside the row (e.g. ``scale from GT``).
        paper: reference values shown beside the row.
        seconds, frames: the time spent predicting and the frames predicted.
        evaluator: the trajectory metrics fed with this method's predictions.
        trans_err, rot_err: per-sample errors (m, rad) of the samples scored, in order.
        coverage: per-sample fraction of the valid pixels on moving objects (NaN without a mask).
    """

    name: str
    predict: Predict
    note: str = ""
    paper: tuple[str, ...] = ("–", "–")
    seconds: float = 0.0
    frames: int = 0
    evaluator: TrajectoryEvaluator = field(default_factory=TrajectoryEvaluator)
    trans_err: list[float] = field(default_factory=list)
    rot_err: list[float] = field(default_factory=list)
    coverage: list[float] = field(default_factory=list)


def mfg_method(model: Any, top_k: float) -> Predict:
    """MFG (a :class:`~mfg_lightning.models.mfg_module.MFGLitModule` in evaluation mode) keeping
    the ``top_k`` fraction of its most active hidden units (1.0: all), in inference mode: the
    motion of ``model.predict_motion(flow, K, top_k=top_k)``."""
    return mfg_top_k_methods(model, [top_k])[0]


def mfg_top_k_methods(model: Any, top_ks: Iterable[float]) -> list[Predict]:
    """:func:`mfg_method` at every ``top_k`` of ``top_ks`` (fractions in (0, 1], validated
    here): the first of them to see a batch computes the fields of every k from one pass of the
    encoder (``model.fields``), the others take theirs. The encoder's and every decoder's time is
    counted in the first method's seconds."""
    ks = tuple(validate_top_k(k, "top_k") for k in top_ks)
    last: dict[str, Any] = {"batch": None, "motions": None}

    def motions_of(batch: dict) -> list[tuple[Tensor, Tensor]]:
        if model.training:
            raise ValueError("MFG scoring: put the model in evaluation mode (model.eval())")
        if last["batch"] is not batch:
            with torch.inference_mode():
                outs = model.fields(model_inputs(batch).flow, ks)
                motions = [geometry.recover_motion(o.v_t, o.v_omega, batch["intrinsics"])
                           for o in outs]  # fmt: skip
            last["batch"], last["motions"] = batch, motions
        return last["motions"]

    def at(i: int) -> Predict:
        return lambda batch: motions_of(batch)[i]

    return [at(i) for i in range(len(ks))]


def _gt_norm(batch: dict) -> Tensor:
    return geometry.pose_to_motion(batch["pose"].double())[0].norm(dim=-1)


def classical_methods(height: int, width: int, oracle: bool = True) -> list[Method]:
    """The classical rows: essential matrix (RANSAC, MAGSAC++), continuous least squares (plain,
    IRLS), and (``oracle``) the recovery from the exact fields of the true motion, whose input is
    ``height × width``."""

    def essential(method: str) -> Predict:
        return lambda b: baselines.essential_matrix_motion(
            b["flow"], b["intrinsics"], b["flow_valid"], _gt_norm(b), method=method
        )

    def continuous(robust: bool) -> Predict:
        return lambda b: baselines.continuous_least_squares(
            b["flow"], b["intrinsics"], b["flow_valid"], _gt_norm(b), robust=robust
        )

    rows = [
        Method("essential matrix + RANSAC (OpenCV)", essential("RANSAC"), "scale from GT"),
        Method("essential matrix + MAGSAC++ (OpenCV)", essential("USAC_MAGSAC"), "scale from GT"),
        Method("continuous least squares (§3, Bruss–Horn)", continuous(False), "scale from GT"),
        Method("continuous LS + IRLS (Cauchy)", continuous(True), "scale from GT"),
    ]
    if oracle:
        rows.append(
            Method(
                "oracle: exact fields → recover_motion",
                lambda b: baselines.oracle_motion(b["pose"], b["intrinsics"], height, width),
                "floor (float32)",
            )
        )
    return rows


def object_coverage(batch: dict) -> Tensor:
    """``(B,)`` fraction of each sample's valid pixels on independently moving objects (NaN
    when the batch carries no ``object_mask``)."""
    valid = batch["flow_valid"].bool()
    if "object_mask" not in batch:
        return torch.full((valid.shape[0],), float("nan"))
    on = (batch["object_mask"].bool() & valid).flatten(1).sum(1).double()
    return on / valid.flatten(1).sum(1).clamp_min(1).double()


def score_methods(
    rows: list[Method], batches: Iterable[dict | None], warm_up: bool = True
) -> list[Method]:
    """Run every method on every batch and feed its evaluator and per-sample errors.

    Args:
        rows: the methods (their evaluators and errors are added to).
        batches: collated batches (None entries, fully unreadable batches, are skipped).
        warm_up: one untimed pass of every method on the first batch first: one-off costs
            (kernel selection, cached pseudo-inverses) are not per-frame costs.

    Returns:
        ``rows``.
    """
    first = True
    for batch in batches:
        if batch is None:
            continue
        if first and warm_up:
            for m in rows:
                m.predict(batch)
        first = False
        coverage = object_coverage(batch).tolist()
        for m in rows:
            start = time.perf_counter()
            t, w = m.predict(batch)
            m.seconds += time.perf_counter() - start
            m.frames += t.shape[0]
            m.evaluator.update(
                batch["sequence"],
                batch["frame"],
                batch["target"],
                geometry.motion_to_pose(t.double(), w.double()),
                batch["pose"],
            )
            te, re = frame_errors(t, w, batch["pose"])
            m.trans_err += te.tolist()
            m.rot_err += re.tolist()
            m.coverage += coverage
    return rows


def scored_rows(rows: list[Method], per_sample: bool = False) -> list[dict]:
    """Every row's metrics as JSON-able dicts (what a cached stage stores); ``per_sample`` adds
    the per-sample errors and coverage."""
    out = []
    for m in rows:
        res = m.evaluator.compute().metrics
        row = {
            "name": m.name,
            "metrics": {k: float(v) for k, v in res.items()},
            "ms_per_frame": 1e3 * m.seconds / max(m.frames, 1),
            "paper": list(m.paper),
            "note": m.note,
        }
        if per_sample:
            row.update(trans_err=m.trans_err, rot_err=m.rot_err, coverage=m.coverage)
        out.append(row)
    return out
