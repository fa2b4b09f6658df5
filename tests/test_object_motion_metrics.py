"""ObjectMotionScores: hand-computed IoU / precision / recall / EPE, near/far split, pooling."""

from __future__ import annotations

import math

import pytest
import torch

from mfg_lightning.metrics.object_motion import ObjectMotionScores

# A 2×4 frame. Left half near (5 m), right half far (40 m); one pixel without depth.
#   pred  [[1 1 0 0]      gt  [[1 0 1 0]      depth [[ 5  5 40 40]
#          [1 0 1 0]]          [1 0 1 1]]           [ 5  0 40 40]]
PRED = torch.tensor([[[1, 1, 0, 0], [1, 0, 1, 0]]], dtype=torch.bool)
GT = torch.tensor([[[1, 0, 1, 0], [1, 0, 1, 1]]], dtype=torch.bool)
DEPTH = torch.tensor([[[5.0, 5.0, 40.0, 40.0], [5.0, 0.0, 40.0, 40.0]]])


def flows() -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted and ground-truth object flow (1, 2, 2, 4) with known per-pixel errors."""
    gt = torch.zeros(1, 2, 2, 4)
    pred = torch.zeros(1, 2, 2, 4)
    gt[0, :, 0, 0] = torch.tensor([1.0, 0.0])
    pred[0, :, 0, 0] = torch.tensor([4.0, 4.0])  # error 5
    gt[0, :, 1, 0] = torch.tensor([2.0, 2.0])
    pred[0, :, 1, 0] = torch.tensor([2.0, 2.0])  # error 0
    gt[0, :, 0, 2] = torch.tensor([0.0, 1.0])  # missed: predicted 0, error 1
    gt[0, :, 1, 2] = torch.tensor([1.0, 1.0])
    pred[0, :, 1, 2] = torch.tensor([1.0, 3.0])  # error 2
    gt[0, :, 1, 3] = torch.tensor([3.0, 4.0])  # missed: error 5
    pred[0, :, 0, 1] = torch.tensor([9.0, 9.0])  # false alarm: not on a GT pixel, not scored
    return pred, gt


def scores_of(*updates: tuple) -> dict[str, float]:
    metric = ObjectMotionScores(near_far_depth=20.0)
    for args in updates:
        metric.update(*args)
    return {k: float(v) for k, v in metric.compute().items()}


def test_hand_computed_scores() -> None:
    pred_flow, gt_flow = flows()
    s = scores_of((PRED, pred_flow, GT, gt_flow, DEPTH))
    # tp: (0,0) (1,0) (1,2) = 3; fp: (0,1) = 1; fn: (0,2) (1,3) = 2.
    assert s["iou"] == pytest.approx(3 / 6)
    assert s["precision"] == pytest.approx(3 / 4)
    assert s["recall"] == pytest.approx(3 / 5)
    assert s["epe"] == pytest.approx((5 + 0 + 1 + 2 + 5) / 5)
    assert s["gt_pixels"] == 5
    # near (depth < 20 m and valid): (0,0) (0,1) (1,0); (1,1) has no depth.
    # tp 2, fp 1, fn 0.
    assert s["near/iou"] == pytest.approx(2 / 3)
    assert s["near/precision"] == pytest.approx(2 / 3)
    assert s["near/recall"] == pytest.approx(1.0)
    assert s["near/epe"] == pytest.approx((5 + 0) / 2)
    assert s["near/gt_pixels"] == 2
    # far: (0,2) (0,3) (1,2) (1,3): tp 1, fp 0, fn 2.
    assert s["far/iou"] == pytest.approx(1 / 3)
    assert s["far/precision"] == pytest.approx(1.0)
    assert s["far/recall"] == pytest.approx(1 / 3)
    assert s["far/epe"] == pytest.approx((1 + 2 + 5) / 3)
    assert s["far/gt_pixels"] == 3


def test_near_far_threshold_is_configurable() -> None:
    pred_flow, gt_flow = flows()
    metric = ObjectMotionScores(near_far_depth=50.0)
    metric.update(PRED, pred_flow, GT, gt_flow, DEPTH)
    s = {k: float(v) for k, v in metric.compute().items()}
    # Every pixel with depth is near now; the pixel without depth is in neither split.
    assert s["near/gt_pixels"] == 5 and s["far/gt_pixels"] == 0
    assert s["near/iou"] == pytest.approx(3 / 6)
    with pytest.raises(ValueError, match="near_far_depth"):
        ObjectMotionScores(near_far_depth=0.0)


def test_valid_mask_excludes_pixels() -> None:
    pred_flow, gt_flow = flows()
    valid = torch.ones_like(GT)
    valid[0, 0, 1] = False  # drop the false alarm
    valid[0, 1, 3] = False  # drop a miss
    s = scores_of((PRED, pred_flow, GT, gt_flow, DEPTH, valid))
    assert s["iou"] == pytest.approx(3 / 4)
    assert s["precision"] == pytest.approx(1.0)
    assert s["recall"] == pytest.approx(3 / 4)
    assert s["epe"] == pytest.approx((5 + 0 + 1 + 2) / 4)


def test_one_batch_equals_many_identical_updates_and_pools_pixels() -> None:
    pred_flow, gt_flow = flows()
    once = scores_of((PRED, pred_flow, GT, gt_flow, DEPTH))
    batch = scores_of(
        (
            PRED.repeat(3, 1, 1),
            pred_flow.repeat(3, 1, 1, 1),
            GT.repeat(3, 1, 1),
            gt_flow.repeat(3, 1, 1, 1),
            DEPTH.repeat(3, 1, 1),
        )
    )
    many = scores_of(*[(PRED, pred_flow, GT, gt_flow, DEPTH)] * 3)
    for key, value in once.items():
        factor = 3 if key.endswith("gt_pixels") else 1
        assert batch[key] == pytest.approx(value * factor), key
        assert many[key] == pytest.approx(value * factor), key

    # Pooled, not averaged per frame: a perfect frame with 1 object pixel and a frame with
    # IoU 0 over 3 pixels give 1/4, not (1 + 0)/2.
    empty = torch.zeros(1, 2, 4, dtype=torch.bool)
    one = empty.clone()
    one[0, 0, 0] = True
    three = empty.clone()
    three[0, 1, :3] = True
    zero_flow = torch.zeros(1, 2, 2, 4)
    s = scores_of(
        (one, zero_flow, one, zero_flow, DEPTH), (empty, zero_flow, three, zero_flow, DEPTH)
    )
    assert s["iou"] == pytest.approx(1 / 4)


def test_empty_denominators_are_documented_values_not_nan() -> None:
    empty = torch.zeros(1, 2, 4, dtype=torch.bool)
    zero_flow = torch.zeros(1, 2, 2, 4)
    # Nothing predicted, nothing there.
    s = scores_of((empty, zero_flow, empty, zero_flow, DEPTH))
    assert all(math.isfinite(v) for v in s.values())
    assert s["iou"] == s["precision"] == s["recall"] == 1.0
    assert s["epe"] == 0.0 and s["gt_pixels"] == 0
    # Objects there, nothing predicted: IoU and recall 0, precision vacuous (1).
    s = scores_of((empty, zero_flow, GT, None, DEPTH))
    assert s["iou"] == 0.0 and s["recall"] == 0.0 and s["precision"] == 1.0
    # No ground-truth flow given: EPE is not measured and reported as 0.
    assert s["epe"] == 0.0
    # A metric that saw no update at all (torchmetrics warns about that; the values stay finite).
    with pytest.warns(UserWarning, match="before the ``update``"):
        s = {k: float(v) for k, v in ObjectMotionScores().compute().items()}
    assert all(math.isfinite(v) for v in s.values())


def test_non_finite_ground_truth_flow_is_not_pooled() -> None:
    pred_flow, gt_flow = flows()
    gt_flow[0, 0, 1, 2] = math.nan
    s = scores_of((PRED, pred_flow, GT, gt_flow, DEPTH))
    assert s["epe"] == pytest.approx((5 + 0 + 1 + 5) / 4)


def test_states_reduce_by_sum() -> None:
    metric = ObjectMotionScores()
    for name, reduce in metric._reductions.items():
        assert reduce is not None and reduce.__name__ == "dim_zero_sum", name
    # Merging two metrics (what DDP's sync does with the states) equals one metric on both.
    pred_flow, gt_flow = flows()
    a, b = ObjectMotionScores(), ObjectMotionScores()
    a.update(PRED, pred_flow, GT, gt_flow, DEPTH)
    b.update(~PRED, pred_flow, GT, gt_flow, DEPTH)
    a.merge_state(b)
    both = scores_of((PRED, pred_flow, GT, gt_flow, DEPTH), (~PRED, pred_flow, GT, gt_flow, DEPTH))
    assert {k: float(v) for k, v in a.compute().items()} == pytest.approx(both)


def test_shape_mismatch_is_an_error() -> None:
    pred_flow, gt_flow = flows()
    with pytest.raises(ValueError, match="must all be"):
        ObjectMotionScores().update(PRED, pred_flow, GT[:, :1], gt_flow, DEPTH)
