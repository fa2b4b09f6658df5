"""Object-motion extraction (paper §4, Filters 1 and 2): oracle scenes, hand-computed filters,
batching, invalid depth, errors, config and pictures."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from mfg_lightning.core import geometry
from mfg_lightning.motion.object_motion import (
    ObjectMotionConfig,
    ObjectMotionError,
    egomotion_field,
    extract_object_motion,
    filter_average_threshold,
    filter_divisive_normalisation,
    normalise_depth,
    residual,
    threshold_baseline,
)
from mfg_lightning.pictures.grids import save_png
from mfg_lightning.pictures.object_motion import (
    object_motion_grid,
    object_motion_grid_batch,
    object_motion_panels,
)

REPO = Path(__file__).resolve().parents[1]
KITTI_K = torch.tensor([718.856, 718.856, 607.1928, 185.2157], dtype=torch.float64)
KITTI_SIZE = (376, 1241)
FAR_PLANE = 655.35
CAMERA_HEIGHT = 1.65
SKY, GROUND = -1, -2

# Axis-aligned boxes (x0, x1, y0, y1, z0, z1) in camera-k coordinates (m; x right, y down,
# z forward; the ground is y = +1.65).
STATIC_BOXES = [
    (-14.0, -8.0, -8.0, CAMERA_HEIGHT, 8.0, 45.0),  # facades on the left
    (7.0, 10.0, -6.0, CAMERA_HEIGHT, 5.0, 18.0),  # a near facade on the right
    (3.0, 4.8, 0.15, CAMERA_HEIGHT, 6.5, 10.5),  # a parked car close by
    (-4.0, -2.2, 0.2, CAMERA_HEIGHT, 25.0, 29.0),  # a parked car ahead
]
# (box, displacement over one frame in m): the paper's claim is about all of these at once.
MOVING = {
    "oncoming car": ((-3.6, -1.8, 0.2, CAMERA_HEIGHT, 12.0, 16.0), (0.0, 0.0, -1.2)),
    "crossing car": ((1.0, 2.8, 0.2, CAMERA_HEIGHT, 22.0, 26.0), (-0.6, 0.0, 0.8)),
    "small distant car": ((-1.0, 0.8, 0.3, CAMERA_HEIGHT, 60.0, 64.0), (0.7, 0.0, 0.3)),
    "slow pedestrian": ((3.0, 3.6, -0.05, CAMERA_HEIGHT, 19.0, 19.5), (-0.1, 0.0, 0.0)),
}


@dataclass
class Frame:
    """A synthetic frame: inputs of the pipeline plus ground truth (batch of 1)."""

    flow: torch.Tensor  # (1, 2, H, W) exact reprojection flow with moving objects
    rigid_flow: torch.Tensor  # (1, 2, H, W) exact flow of the static scene
    v_t: torch.Tensor  # (1, 2, H, W) oracle translational field at unit inverse depth
    v_w: torch.Tensor  # (1, 2, H, W) oracle rotational field
    depth: torch.Tensor  # (1, H, W) metres
    gt_mask: torch.Tensor  # (1, H, W) moving-object pixels
    surface: torch.Tensor  # (1, H, W) SKY, GROUND or the index into the box list
    names: list[str]  # box index → name ("static" for static boxes)


def kitti_intrinsics(height: int, width: int) -> torch.Tensor:
    return geometry.scale_intrinsics(KITTI_K, width / KITTI_SIZE[1], height / KITTI_SIZE[0])


def ray_cast(boxes: list[tuple], K: torch.Tensor, height: int, width: int):
    """Depth and surface index of the first hit of every pixel ray (ground, boxes, far plane).

    A ray through normalised coordinates (x, y) is (x, y, 1)·z, so the slab parameter is depth.
    """
    xy = geometry.normalized_grid(K[None], height, width)[0]
    direction = torch.stack([xy[0], xy[1], torch.ones_like(xy[0])])  # (3, H, W)
    depth = torch.full((height, width), FAR_PLANE, dtype=torch.float64)
    surface = torch.full((height, width), SKY, dtype=torch.long)
    ground = torch.where(xy[1] > 0, CAMERA_HEIGHT / xy[1].clamp_min(1e-12), math.inf)
    hit = ground < depth
    depth, surface = torch.where(hit, ground, depth), torch.where(hit, GROUND, surface)
    safe = torch.where(direction.abs() > 1e-12, direction, torch.full_like(direction, 1e-12))
    for i, box in enumerate(boxes):
        lo = torch.tensor(box[0::2], dtype=torch.float64)[:, None, None] / safe
        hi = torch.tensor(box[1::2], dtype=torch.float64)[:, None, None] / safe
        enter = torch.minimum(lo, hi).amax(0)
        leave = torch.maximum(lo, hi).amin(0)
        hit = (enter <= leave) & (enter > 0) & (enter < depth)
        depth, surface = torch.where(hit, enter, depth), torch.where(hit, i, surface)
    return depth, surface


def make_frame(speed: float, height: int = 96, width: int = 256, yaw: float = 0.01) -> Frame:
    """A KITTI-like driving frame: camera driving forward ``speed`` m/frame with a small yaw."""
    K = kitti_intrinsics(height, width)
    boxes = STATIC_BOXES + [box for box, _ in MOVING.values()]
    names = ["static"] * len(STATIC_BOXES) + list(MOVING)
    depth, surface = ray_cast(boxes, K, height, width)
    t = torch.tensor([[0.05 * speed, 0.0, speed]], dtype=torch.float64)
    w = torch.tensor([[0.0, yaw, 0.0]], dtype=torch.float64)
    pose = geometry.motion_to_pose(t, w)
    displacement = torch.zeros(1, height, width, 3, dtype=torch.float64)
    gt = torch.zeros(1, height, width, dtype=torch.bool)
    for i, (_, motion) in enumerate(MOVING.values(), start=len(STATIC_BOXES)):
        on = surface[None] == i
        displacement[on] = torch.tensor(motion, dtype=torch.float64)
        gt |= on
    flow = geometry.reprojection_flow(depth[None], pose, K[None], point_motion=displacement)
    rigid = geometry.reprojection_flow(depth[None], pose, K[None])
    return Frame(
        flow=flow.float(),
        rigid_flow=rigid.float(),
        v_t=geometry.translational_field(t, K, height, width).float(),
        v_w=geometry.rotational_field(w, K, height, width).float(),
        depth=depth[None].float(),
        gt_mask=gt,
        surface=surface[None],
        names=names,
    )


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum()) / max(float((a | b).sum()), 1.0)


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
R_TINY = [(3.0, 4.0), (1.0, 0.0), (0.0, 0.0), (0.5, 0.5), (2.0, 0.0), (0.0, -3.0)]
D_TINY = [0.1, 0.05, 0.15, 0.3, 0.12, 0.02]


def tiny_residual() -> torch.Tensor:
    r = torch.tensor(R_TINY, dtype=torch.float64).T.reshape(1, 2, 2, 3)
    return r


def tiny_depth_norm() -> torch.Tensor:
    return torch.tensor(D_TINY, dtype=torch.float64).reshape(1, 2, 3)


def test_filter_1_matches_hand_computation() -> None:
    sq = [u * u + v * v for u, v in R_TINY]  # 25, 1, 0, 0.5, 4, 9
    threshold = 1.5 * sum(math.tanh(s) for s in sq) / 6  # 1.5 · 0.7038 = 1.0557
    expected = [s > threshold for s in sq]
    assert expected == [True, False, False, False, True, True]  # 1 px² sits just below
    f1 = filter_average_threshold(tiny_residual(), theta_d=1.5)
    assert f1.flatten().tolist() == expected

    # Means over valid pixels only: without the 25 px² pixel the threshold is 1.5·0.5446 = 0.817,
    # and the 1 px² pixel now passes.
    valid = torch.ones(1, 2, 3, dtype=torch.bool)
    valid[0, 0, 0] = False
    threshold = 1.5 * sum(math.tanh(s) for s in sq[1:]) / 5
    expected = [False] + [s > threshold for s in sq[1:]]
    assert expected == [False, True, False, False, True, True]
    f1 = filter_average_threshold(tiny_residual(), theta_d=1.5, valid=valid)
    assert f1.flatten().tolist() == expected


def test_filter_2_matches_hand_computation() -> None:
    sq = [u * u + v * v for u, v in R_TINY]
    r1 = [s / max(sq) for s in sq]
    r2 = [a * math.tanh(d) ** 2 for a, d in zip(r1, D_TINY, strict=True)]
    r2 = [a / max(r2) for a in r2]
    rs = [a / (1 + (max(r2) - a) ** 2) for a in r2]
    cut = 0.5 * sum(rs) / 6
    expected = [s > cut and d < 0.2 for s, d in zip(rs, D_TINY, strict=True)]
    # Worked by hand: r_s ≈ [1, 0.0051, 0, 0.1025, 0.144, 0.0074], cut ≈ 0.1049: pixel 3 fails
    # the cut (and the depth test), pixel 5 (9 px² but 2% of the far plane) is suppressed.
    assert rs[0] == pytest.approx(1.0)
    assert rs[4] == pytest.approx(0.144, abs=1e-3)
    assert cut == pytest.approx(0.1049, abs=1e-3)
    assert expected == [True, False, False, False, True, False]
    f2 = filter_divisive_normalisation(tiny_residual(), tiny_depth_norm(), 0.5, 0.2)
    assert f2.flatten().tolist() == expected

    # The depth cut alone: with Threshold_D = 0.11 pixel 4 (d = 0.12) drops out.
    f2 = filter_divisive_normalisation(tiny_residual(), tiny_depth_norm(), 0.5, 0.11)
    assert f2.flatten().tolist() == [True, False, False, False, False, False]


def test_pipeline_on_tiny_frame_is_the_conjunction_and_masks_the_residual() -> None:
    # flow = r + ego with ego from ρ = 1/depth; depth = d · 655.35 gives the normalised depths.
    r = tiny_residual().float()
    depth = (tiny_depth_norm() * 655.35).float()
    v_t = torch.randn(1, 2, 2, 3, generator=torch.Generator().manual_seed(0))
    v_w = torch.randn(1, 2, 2, 3, generator=torch.Generator().manual_seed(1))
    ego = v_t / depth[:, None] + v_w
    result = extract_object_motion(r + ego, v_t, v_w, depth)
    assert torch.allclose(result.ego_field, ego)
    assert torch.allclose(result.residual, r, atol=1e-5)
    assert torch.allclose(result.depth_norm, tiny_depth_norm().float(), atol=1e-6)
    assert result.f1.flatten().tolist() == [True, False, False, False, True, True]
    assert result.f2.flatten().tolist() == [True, False, False, False, True, False]
    assert result.mask.flatten().tolist() == [True, False, False, False, True, False]
    expected_flow = r * result.mask[:, None]
    assert torch.allclose(result.object_flow, expected_flow, atol=1e-5)


def test_egomotion_field_and_residual_by_hand() -> None:
    v_t = torch.tensor([[[[2.0, -4.0]], [[6.0, 1.0]]]])  # (1, 2, 1, 2)
    v_w = torch.tensor([[[[0.5, 0.5]], [[-1.0, 0.0]]]])
    depth = torch.tensor([[[2.0, 4.0]]])
    ego = egomotion_field(v_t, v_w, depth)
    assert torch.allclose(ego, torch.tensor([[[[1.5, -0.5]], [[2.0, 0.25]]]]))
    flow = torch.tensor([[[[1.0, 1.0]], [[1.0, 1.0]]]])
    assert torch.allclose(residual(flow, ego), torch.tensor([[[[-0.5, 1.5]], [[-1.0, 0.75]]]]))


def test_baseline_thresholds_the_residual_norm() -> None:
    baseline = threshold_baseline(tiny_residual(), 2.0)
    # norms 5, 1, 0, 0.707, 2, 3: strictly above 2
    assert baseline.flatten().tolist() == [True, False, False, False, False, True]


# --------------------------------------------------------------------------------------------
# Batching, invalid depth, degenerate frames, errors
# --------------------------------------------------------------------------------------------


def test_batch_and_single_sample_agree() -> None:
    frames = [make_frame(speed=0.5, height=48, width=128), make_frame(1.0, 48, 128, yaw=-0.02)]
    depth_b = torch.cat([f.depth for f in frames])
    depth_b[1, :4] = 0.0  # invalid depth in one sample must not touch the other
    batched = extract_object_motion(
        torch.cat([f.flow for f in frames]),
        torch.cat([f.v_t for f in frames]),
        torch.cat([f.v_w for f in frames]),
        depth_b,
    )
    for i, f in enumerate(frames):
        single = extract_object_motion(f.flow, f.v_t, f.v_w, depth_b[i : i + 1])
        for field in ("mask", "f1", "f2", "valid"):
            assert torch.equal(getattr(batched, field)[i], getattr(single, field)[0]), field
        for field in ("ego_field", "residual", "object_flow", "depth_norm"):
            assert torch.allclose(getattr(batched, field)[i], getattr(single, field)[0]), field


def test_invalid_depth_is_masked_not_divided() -> None:
    frame = make_frame(speed=0.5, height=48, width=128)
    depth = frame.depth.clone()
    bad = torch.zeros_like(depth, dtype=torch.bool)
    depth[0, 30, 10:14] = torch.tensor([0.0, -3.0, math.inf, math.nan])
    bad[0, 30, 10:14] = True
    # Also on a moving object, where the mask would otherwise be set.
    on_object = frame.gt_mask[0].nonzero()[0]
    depth[0, on_object[0], on_object[1]] = 0.0
    bad[0, on_object[0], on_object[1]] = True
    v_t = frame.v_t.clone().requires_grad_(True)
    result = extract_object_motion(frame.flow, v_t, frame.v_w, depth)
    for name in ("ego_field", "residual", "object_flow", "depth_norm"):
        assert torch.isfinite(getattr(result, name)).all(), name
    assert not result.valid[bad].any()
    assert not (result.mask | result.f1 | result.f2)[bad].any()
    assert (result.ego_field[:, :, bad[0]] == 0).all()
    result.object_flow.sum().backward()
    assert torch.isfinite(v_t.grad).all()
    # The rest of the frame is still solved.
    assert iou(result.mask, frame.gt_mask & ~bad) >= 0.9


def test_zero_residual_gives_empty_masks_without_nan() -> None:
    frame = make_frame(speed=0.5, height=48, width=128)
    flow = egomotion_field(frame.v_t, frame.v_w, frame.depth)  # r = 0 exactly
    result = extract_object_motion(flow, frame.v_t, frame.v_w, frame.depth)
    assert not result.mask.any() and not result.f1.any() and not result.f2.any()
    assert torch.isfinite(result.object_flow).all()
    # Frames with no valid pixel at all are empty too.
    result = extract_object_motion(
        frame.flow, frame.v_t, frame.v_w, frame.depth, valid=torch.zeros_like(frame.gt_mask)
    )
    assert not result.mask.any() and torch.isfinite(result.residual).all()


def test_non_finite_flow_is_excluded() -> None:
    frame = make_frame(speed=0.5, height=48, width=128)
    flow = frame.flow.clone()
    flow[0, 0, 5, 5] = math.nan
    flow[0, 1, 6, 6] = math.inf
    result = extract_object_motion(flow, frame.v_t, frame.v_w, frame.depth)
    assert not result.valid[0, 5, 5] and not result.valid[0, 6, 6]
    assert torch.isfinite(result.residual).all() and torch.isfinite(result.object_flow).all()


def test_missing_depth_raises_a_clear_error() -> None:
    frame = make_frame(speed=0.5, height=48, width=128)
    with pytest.raises(ObjectMotionError, match="needs depth") as info:
        extract_object_motion(frame.flow, frame.v_t, frame.v_w, None)
    assert isinstance(info.value, ValueError)
    assert "Virtual KITTI" in str(info.value) and "synthetic" in str(info.value)
    assert "KITTI odometry has no depth" in str(info.value)
    with pytest.raises(ObjectMotionError, match="needs depth"):
        egomotion_field(frame.v_t, frame.v_w, None)


# --------------------------------------------------------------------------------------------
# Depth normalisation and config
# --------------------------------------------------------------------------------------------


def test_depth_normalisation_modes() -> None:
    depth = torch.tensor([[[10.0, 50.0], [0.0, 1000.0]], [[10.0, 50.0], [0.0, 25.0]]])
    fixed = normalise_depth(depth, max_depth=655.35, mode="fixed")
    assert torch.allclose(fixed[0], torch.tensor([[10 / 655.35, 50 / 655.35], [0.0, 1.0]]))
    per_frame = normalise_depth(depth, mode="per_frame")
    assert torch.allclose(per_frame[0], torch.tensor([[0.01, 0.05], [0.0, 1.0]]))
    assert torch.allclose(per_frame[1], torch.tensor([[0.2, 1.0], [0.0, 0.5]]))
    # On a frame whose far plane is 655.35 m (VKITTI sky), the two readings coincide.
    vkitti = torch.tensor([[[10.0, 655.35]]])
    assert torch.allclose(
        normalise_depth(vkitti, mode="fixed"), normalise_depth(vkitti, mode="per_frame")
    )


def test_config_defaults_and_validation() -> None:
    cfg = ObjectMotionConfig()
    assert (cfg.theta_d, cfg.theta_p, cfg.threshold_d, cfg.max_depth) == (1.5, 0.5, 0.2, 655.35)
    with pytest.raises(ValueError, match="depth_normalisation"):
        ObjectMotionConfig(depth_normalisation="median")
    with pytest.raises(ValueError, match="max_depth"):
        ObjectMotionConfig(max_depth=0.0)
    hydra_cfg = instantiate(OmegaConf.load(REPO / "conf" / "object_motion" / "default.yaml"))
    assert hydra_cfg == cfg


def test_per_frame_normalisation_changes_the_depth_cut_only_without_a_far_plane() -> None:
    frame = make_frame(speed=0.5, height=48, width=128)
    extract = functools.partial(
        extract_object_motion, frame.flow, frame.v_t, frame.v_w, frame.depth
    )
    fixed = extract()
    per_frame = extract(ObjectMotionConfig(depth_normalisation="per_frame"))
    assert torch.equal(fixed.mask, per_frame.mask)  # the frame has sky at 655.35 m
    # Without a far plane (sky depth unknown, as with LiDAR), "per_frame" divides by the frame's
    # farthest ground pixel, 191 m: Threshold_D = 0.2 then means 38 m and the distant car (60 m)
    # falls outside the cut.
    # Invalid flow alone does not change the normalisation (VKITTI's sky: invalid flow, 655.35 m).
    sky = frame.surface == SKY
    per_frame_sky_flow_invalid = extract(
        ObjectMotionConfig(depth_normalisation="per_frame"), valid=~sky
    )
    assert torch.equal(per_frame_sky_flow_invalid.depth_norm, fixed.depth_norm)
    per_frame = extract_object_motion(
        frame.flow,
        frame.v_t,
        frame.v_w,
        torch.where(sky, 0.0, frame.depth),
        ObjectMotionConfig(depth_normalisation="per_frame"),
    )
    assert float(per_frame.depth_norm.amax()) == 1.0
    farthest = frame.depth[0][per_frame.depth_norm[0] == 1.0]
    assert float(farthest[0]) == pytest.approx(191.28, abs=0.01)
    distant = frame.surface == frame.names.index("small distant car")
    assert fixed.mask[distant].all()
    assert not per_frame.mask[distant].any()


# --------------------------------------------------------------------------------------------
# Pictures
# --------------------------------------------------------------------------------------------


def test_picture_grid_single_and_batch(tmp_path: Path) -> None:
    import cv2

    frame = make_frame(speed=0.5, height=48, width=128)
    flow = torch.cat([frame.flow, frame.flow])
    result = extract_object_motion(
        flow, torch.cat([frame.v_t] * 2), torch.cat([frame.v_w] * 2), torch.cat([frame.depth] * 2)
    )
    panels = object_motion_panels(result, flow, 0, gt_mask=torch.cat([frame.gt_mask] * 2))
    assert [title.split(" (")[0] for title, _ in panels] == [
        "inverse depth",
        "input flow",
        "predicted egomotion field",
        "residual",
        "object mask",
        "object motion field",
    ]
    for _, image in panels:
        assert image.shape == (48, 128, 3) and image.dtype == np.uint8
    # Mask panel: every ground-truth object pixel is a hit (white) here.
    mask_panel = panels[4][1]
    assert (mask_panel[frame.gt_mask[0].numpy()] == 255).all()

    rgb = torch.randint(0, 256, (2, 3, 48, 128), dtype=torch.uint8)
    single = object_motion_grid(result, flow, 0, rgb=rgb, header="frame 0")
    batch = object_motion_grid_batch(result, flow, rgb=rgb, headers=["a", "b"])
    assert single.dtype == np.uint8 and single.ndim == 3 and single.shape[-1] == 3
    assert batch.shape[1] > 1.5 * single.shape[1]
    assert single.std() > 10  # drawn, not blank
    path = save_png(batch, tmp_path / "grids" / "object_motion.png")
    back = cv2.imread(str(path))[..., ::-1]
    assert np.array_equal(back, batch)
