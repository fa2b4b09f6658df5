"""Object-motion scores: mask IoU, precision, recall and object-field end-point error.

The paper reports object motion qualitatively only (§5.4, Figure 4); these scores are this
project's addition (``docs/protocols.md``, "Object motion"). They compare a predicted object
mask and object motion field (:func:`mfg_lightning.motion.object_motion.extract_object_motion`)
with a
sample's ground-truth ``object_mask`` and ``object_flow`` (:mod:`mfg_lightning.data.sample`).

Pooling
-------
Every score is **pooled over all pixels of all frames** seen since the last reset: the true/false
positive and false negative counts and the end-point-error sums are accumulated, and the ratios are
formed once in :meth:`ObjectMotionScores.compute`. Large objects therefore weigh more than small
ones and frames with many object pixels more than frames with few; a per-frame mean would differ.
The states are sums declared with ``dist_reduce_fx="sum"``, so the scores reduce exactly under DDP;
``update`` uses tensor operations only (no device synchronisation per batch).

Near / far split
----------------
A pixel is *near* when its depth is valid (finite, > 0) and below ``near_far_depth`` metres and
*far* when its depth is valid and at least ``near_far_depth``; pixels without valid depth count in
the overall scores only. ``near/iou`` is the IoU restricted to near pixels,
``|P ∩ G ∩ N| / |(P ∪ G) ∩ N|``; ``near/recall`` and ``near/epe`` are over the near ground-truth
object pixels ``G ∩ N`` (likewise for far).

Empty denominators
------------------
Scores never come out NaN. A ratio whose denominator is empty is a vacuous statement and is
reported as its best value: IoU of two empty masks = 1 (nothing to find, nothing found);
precision with no predicted pixel = 1 (no false alarm was raised); recall with no ground-truth
pixel = 1 (nothing was missed). ``epe`` with no ground-truth object pixel (or when no ground-truth
object flow was given) is 0. Check the ``*gt_pixels`` counts returned beside the scores to tell
such vacuous values from measured ones.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from mfg_lightning.core.geometry import float32_math
from mfg_lightning.motion.object_motion import depth_validity

__all__ = ["ObjectMotionScores"]

_REGIONS = ("all", "near", "far")


class ObjectMotionScores(Metric):
    """Pooled object-mask IoU / precision / recall and object-field EPE, with a near/far split.

    Args:
        near_far_depth: depth in metres separating near from far pixels (default 20 m).

    ``compute()`` returns a dict of scalar tensors: ``iou``, ``precision``, ``recall``, ``epe``
    (pixels per frame), ``gt_pixels``; and ``near/iou``, ``near/precision``, ``near/recall``,
    ``near/epe``, ``near/gt_pixels`` and the same for ``far/``. See the module docstring for pooling
    and for the values reported when a denominator is empty.
    """

    is_differentiable = False
    higher_is_better = None
    full_state_update = False

    def __init__(self, near_far_depth: float = 20.0, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if near_far_depth <= 0:
            raise ValueError(f"near_far_depth must be positive (metres), got {near_far_depth}")
        self.near_far_depth = float(near_far_depth)
        for region in _REGIONS:
            for name in ("tp", "fp", "fn", "epe_count"):
                self.add_state(
                    f"{region}_{name}",
                    default=torch.tensor(0, dtype=torch.long),
                    dist_reduce_fx="sum",
                )
            # float32, not float64, so the metric also runs on devices without float64 (MPS).
            self.add_state(f"{region}_epe_sum", default=torch.tensor(0.0), dist_reduce_fx="sum")

    def update(
        self,
        pred_mask: Tensor,
        pred_object_flow: Tensor,
        gt_mask: Tensor,
        gt_object_flow: Tensor | None,
        depth: Tensor,
        valid: Tensor | None = None,
    ) -> None:
        """Accumulate one batch.

        Args:
            pred_mask: ``(B, H, W)`` bool predicted object mask.
            pred_object_flow: ``(B, 2, H, W)`` predicted object motion field (px/frame).
            gt_mask: ``(B, H, W)`` bool ground-truth moving-object mask.
            gt_object_flow: ``(B, 2, H, W)`` ground-truth object flow (px/frame), or None to
                skip the end-point error.
            depth: ``(B, H, W)`` metres (0 where unknown), for the near/far split.
            valid: ``(B, H, W)`` bool pixels to score (default: all).
        """
        pred_mask = pred_mask.to(torch.bool)
        gt_mask = gt_mask.to(torch.bool)
        if pred_mask.shape != gt_mask.shape or depth.shape != gt_mask.shape:
            raise ValueError(
                f"pred_mask {tuple(pred_mask.shape)}, gt_mask {tuple(gt_mask.shape)} and depth "
                f"{tuple(depth.shape)} must all be (B, H, W)"
            )
        if valid is None:
            valid = torch.ones_like(gt_mask)
        valid = valid.to(torch.bool)
        has_depth = depth_validity(depth)
        regions = {
            "all": valid,
            "near": valid & has_depth & (depth < self.near_far_depth),
            "far": valid & has_depth & (depth >= self.near_far_depth),
        }
        epe = None
        if gt_object_flow is not None:
            # Non-finite ground truth (should not happen) must not poison the pooled sum.
            with float32_math():  # the norms in float32 under any autocast
                err = (pred_object_flow.float() - gt_object_flow.float()).norm(dim=1)
            epe_ok = torch.isfinite(err)
            epe = torch.where(epe_ok, err, torch.zeros_like(err))
        for region, sel in regions.items():
            gt_here = gt_mask & sel
            pred_here = pred_mask & sel
            self._add(f"{region}_tp", (pred_here & gt_here).sum())
            self._add(f"{region}_fp", (pred_here & ~gt_here).sum())
            self._add(f"{region}_fn", (~pred_here & gt_here).sum())
            if epe is not None:
                scored = gt_here & epe_ok
                self._add(f"{region}_epe_count", scored.sum())
                # where, not epe[scored]: boolean indexing waits for the device (nonzero).
                self._add(f"{region}_epe_sum", torch.where(scored, epe, 0.0).sum())

    def _add(self, name: str, value: Tensor) -> None:
        state = getattr(self, name)
        setattr(self, name, state + value.to(state.dtype))

    def compute(self) -> dict[str, Tensor]:
        """Pooled scores (see the class and module docstrings for keys and conventions)."""
        out: dict[str, Tensor] = {}
        for region in _REGIONS:
            tp = getattr(self, f"{region}_tp").float()
            fp = getattr(self, f"{region}_fp").float()
            fn = getattr(self, f"{region}_fn").float()
            n = getattr(self, f"{region}_epe_count").float()
            epe_sum = getattr(self, f"{region}_epe_sum")
            prefix = "" if region == "all" else f"{region}/"
            out[f"{prefix}iou"] = _ratio(tp, tp + fp + fn, empty=1.0)
            out[f"{prefix}precision"] = _ratio(tp, tp + fp, empty=1.0)
            out[f"{prefix}recall"] = _ratio(tp, tp + fn, empty=1.0)
            out[f"{prefix}epe"] = _ratio(epe_sum, n, empty=0.0)
            out[f"{prefix}gt_pixels"] = (tp + fn).float()
        return out


def _ratio(num: Tensor, den: Tensor, empty: float) -> Tensor:
    """``num / den``, or ``empty`` when ``den == 0`` (no NaN)."""
    safe = torch.where(den > 0, den, torch.ones_like(den))
    return torch.where(den > 0, num / safe, torch.full_like(num, empty))
