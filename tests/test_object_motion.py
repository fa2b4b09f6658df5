"""Object-motion extraction (paper §4, Filters 1 and 2) on oracle scenes: every mover found at
urban speed, against the threshold baseline and the first-order field."""

from __future__ import annotations

import pytest
import torch

from mfg_lightning.core import geometry
from mfg_lightning.motion.object_motion import (
    extract_object_motion,
    threshold_baseline,
)
from object_scenes import iou, make_frame

# --------------------------------------------------------------------------------------------
# Oracle scenes
# --------------------------------------------------------------------------------------------


def test_oracle_fields_recover_every_moving_object_at_urban_speed() -> None:
    """v_t = A t_true, v_ω = B ω_true on exact flow at 0.5 m/frame: measured IoU 1.000."""
    frame = make_frame(speed=0.5)
    result = extract_object_motion(frame.flow, frame.v_t, frame.v_w, frame.depth)
    assert iou(result.mask, frame.gt_mask) >= 0.9
    for i, name in enumerate(frame.names):
        if name != "static":
            on = frame.surface == i
            assert on.sum() >= 10, name  # the object is visible at this resolution
            assert result.mask[on].float().mean() >= 0.9, name
    # The object field is the residual on the mask and zero elsewhere.
    assert torch.equal(
        result.object_flow[:, :, ~result.mask[0]],
        torch.zeros_like(result.object_flow[:, :, ~result.mask[0]]),
    )


def test_threshold_baseline_loses_the_slow_object_that_the_filters_keep() -> None:
    """Paper §4: a plain threshold high enough to reject near static residue drops slow objects."""
    frame = make_frame(speed=0.5)
    result = extract_object_motion(frame.flow, frame.v_t, frame.v_w, frame.depth)
    norm = result.residual.norm(dim=1)
    static_peak = float(norm[~frame.gt_mask & result.valid].max())
    slow = frame.surface == frame.names.index("slow pedestrian")
    # The slow object's residue is below that of near static structure ...
    assert float(norm[slow].max()) < static_peak
    # ... so the lowest threshold without false alarms misses it; the filters keep it.
    baseline = threshold_baseline(result.residual, static_peak, result.valid)
    assert not (baseline & ~frame.gt_mask).any()
    assert not baseline[slow].any()
    assert result.mask[slow].all()
    best_baseline = max(
        iou(threshold_baseline(result.residual, float(th), result.valid), frame.gt_mask)
        for th in torch.linspace(0.05, 6.0, 120)
    )
    assert best_baseline < iou(result.mask, frame.gt_mask)


def test_exact_rigid_compensation_recovers_objects_at_1m_per_frame() -> None:
    """An ego field equal to the exact static-scene flow leaves only object motion in r."""
    frame = make_frame(speed=1.0)
    # ρ ṽ_t + ṽ_ω = rigid flow  ⇔  ṽ_t = (rigid − ṽ_ω) · depth.
    v_t_exact = (frame.rigid_flow - frame.v_w) * frame.depth[:, None]
    result = extract_object_motion(frame.flow, v_t_exact, frame.v_w, frame.depth)
    assert iou(result.mask, frame.gt_mask) >= 0.9  # measured 1.000
    gt_object_flow = (frame.flow - frame.rigid_flow) * frame.gt_mask[:, None]
    assert torch.allclose(result.object_flow, gt_object_flow, atol=1e-4)


def test_first_order_field_at_1m_per_frame_leaves_near_static_residue_in_the_mask() -> None:
    """A limit of the paper's method, measured: at 1 m/frame the linear motion field misses the
    exact flow of near static structure by several pixels (second order in t_z / Z), which both
    filters keep. Oracle IoU drops to 0.14 here; every false alarm is static and near."""
    frame = make_frame(speed=1.0)
    result = extract_object_motion(frame.flow, frame.v_t, frame.v_w, frame.depth)
    false_alarm = result.mask & ~frame.gt_mask
    assert iou(result.mask, frame.gt_mask) < 0.5
    assert false_alarm.sum() > frame.gt_mask.sum()
    assert float(frame.depth[false_alarm].max()) < 45.0
    assert float(frame.depth[false_alarm].median()) < 20.0
    # The moving objects themselves are still found.
    assert result.mask[frame.gt_mask].float().mean() > 0.9


def test_oracle_on_synthetic_driving_dataset() -> None:
    """The lead's SyntheticDrivingDataset (exact flow, no noise), oracle fields from the pose.

    Measured on these 8 test samples at 48×128: IoU 0.049, precision 0.051, recall 0.60, far
    (≥ 20 m) precision 1.00; on all 59 samples of the sequence IoU 0.083, recall 0.61 (the 1 px
    threshold baseline: IoU 0.17). The dataset drives at 0.55–1.05 m/frame past facades 5–15 m
    away, so the second-order residue of near static structure (see the 1 m/frame test above)
    and frames without any moving object (both filters are relative to the frame's mean, so they
    always select something) make the false alarms — all of them nearer than 20 m. The
    thresholds below guard these measurements; they are not a claim of good performance.
    """
    synthetic = pytest.importorskip("mfg_lightning.data.synthetic")
    from mfg_lightning.data.base import collate_samples
    from mfg_lightning.metrics.object_motion import ObjectMotionScores

    dm = synthetic.SyntheticDataModule(
        height=48,
        width=128,
        sequence_length=60,
        test_sequences=1,
        flow={"source": "exact", "noise_std": 0.0, "outlier_fraction": 0.0},
    )
    dataset = dm.dataset("test")
    batch = collate_samples([dataset[i] for i in range(0, 59, 8)])
    t, w = geometry.pose_to_motion(batch["pose"].double())
    K = batch["intrinsics"].double()
    v_t = geometry.translational_field(t, K, 48, 128).float()
    v_w = geometry.rotational_field(w, K, 48, 128).float()
    result = extract_object_motion(
        batch["flow"], v_t, v_w, batch["depth"], valid=batch["flow_valid"]
    )
    scores = ObjectMotionScores()
    scores.update(
        result.mask,
        result.object_flow,
        batch["object_mask"],
        batch["object_flow"],
        batch["depth"],
        batch["flow_valid"],
    )
    s = {k: float(v) for k, v in scores.compute().items()}
    assert s["gt_pixels"] > 0
    assert s["iou"] >= 0.04
    assert s["recall"] >= 0.5
    assert s["far/precision"] >= 0.9
    false_alarm = result.mask & ~batch["object_mask"]
    assert false_alarm.any() and (batch["depth"][false_alarm] < 20.0).all()


# --------------------------------------------------------------------------------------------
# Filters against hand-computed values
# --------------------------------------------------------------------------------------------

# A 2×3 frame. Residual vectors (px) and normalised depth, row-major.
