"""Object-motion extraction (paper §4, Filters 1 and 2): hand-computed filters, batching,
invalid depth, errors, config and pictures."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

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
from object_scenes import REPO, SKY, iou, make_frame

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
