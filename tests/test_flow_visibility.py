"""The exact flow's visibility marks (occluded, out of frame) on real renders, and flow scored as
KITTI scores it: on the non-occluded pixels (noc) and on all pixels, numpy and torch alike."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import quiet_trainer
from mfg_lightning.core import geometry
from mfg_lightning.data.flow_pairs import FlowPairsDataModule
from mfg_lightning.flow.pwc import PWCConfig
from mfg_lightning.metrics.flow_quality import (
    OCCLUDED,
    OUT_OF_FRAME,
    QUALITY_REGIONS,
    UNKNOWN,
    VISIBLE,
    PooledFlowQuality,
    flow_quality,
    pair_stats,
    pooled_quality,
    pooled_quality_by_offset,
    visibility_codes,
)
from mfg_lightning.models.flow_module import (
    FlowLitModule,
    flow_quality_metrics,
    quality_names,
    score_flow,
)
from mfg_lightning.scene import camera, render
from mfg_lightning.scene.worlds import World, WorldConfig
from street_worlds import rendered_frames, street_world

H, W = 48, 128


@pytest.fixture(scope="module")
def static_world() -> World:
    """A world without moving objects (every point's motion is the camera's: its depth in the
    second camera follows from the geometry module alone) and with many parked cars (occluders
    in front of the facades)."""
    config = WorldConfig(cars_per_100m=0.0, pedestrians_per_100m=0.0, parked_per_100m=20.0)
    return street_world(40, config)


@pytest.fixture(scope="module")
def K() -> torch.Tensor:
    return camera.kitti_like_intrinsics(H, W).double()


@pytest.fixture(scope="module")
def frames(static_world: World, K: torch.Tensor) -> dict[int, render.RenderedFrame]:
    return rendered_frames(static_world, K, (20, 21, 23), H, W)


def _landing(flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Where every pixel lands in the second image, ``(u, v)`` float64 ``(H, W)`` each."""
    u = torch.arange(W, dtype=torch.float64)[None] + flow[0].double()
    v = torch.arange(H, dtype=torch.float64)[:, None] + flow[1].double()
    return u, v


def test_moving_forward_the_border_pixels_leave_the_frame_and_nothing_else(
    static_world: World, K: torch.Tensor, frames: dict
) -> None:
    e = render.exact_flow(static_world, 20, 21, K, H, W, source=frames[20], target=frames[21])
    u, v = _landing(e["flow"])
    outside = (u < -0.5) | (u > W - 0.5) | (v < -0.5) | (v > H - 0.5)
    # exactly the valid pixels whose flow lands outside the image
    assert torch.equal(e["out_of_frame"], e["flow_valid"] & outside)
    share = float(e["out_of_frame"].float().mean())
    assert 0.03 < share < 0.4, share  # about a metre forward: a band along the borders
    # the view expands from the focus of expansion near the centre: the middle stays in frame
    assert not e["out_of_frame"][H // 3 : H // 2, W // 3 : 2 * W // 3].any()
    assert e["out_of_frame"][-1].float().mean() > 0.5  # the near road under the camera
    # backwards, the view contracts: (almost) nothing leaves it
    back = render.exact_flow(static_world, 21, 20, K, H, W, source=frames[21], target=frames[20])
    assert float(back["out_of_frame"].float().mean()) < 0.01
    # the marks partition the valid pixels, and change no flow
    parts = e["out_of_frame"].int() + e["occluded"].int() + e["visible"].int()
    assert torch.equal(parts, e["flow_valid"].int())
    plain = render.exact_flow(static_world, 20, 21, K, H, W, source=frames[20])
    assert "occluded" not in plain and torch.equal(plain["out_of_frame"], e["out_of_frame"])
    for key in ("flow", "flow_valid"):
        assert torch.equal(plain[key], e[key])


def test_occluded_pixels_are_those_a_nearer_point_lands_on(
    static_world: World, K: torch.Tensor, frames: dict
) -> None:
    """Checked against a z-buffer of the source frame's own points splatted into the second
    camera (independent of the second frame's ray casts, which the renderer compares with)."""
    e = render.exact_flow(static_world, 20, 23, K, H, W, source=frames[20], target=frames[23])
    occluded, visible = e["occluded"], e["visible"]
    share = float(occluded.float().mean())
    assert occluded.sum() >= 10 and share < 0.1, share  # parked cars in front of facades
    # every point's depth in the second camera (no moving object: the camera's motion alone)
    points = geometry.backproject(frames[20].depth.double()[None], K[None])[0]
    to_second = geometry.invert_pose(geometry.relative_pose(static_world.poses[20],
                                                            static_world.poses[23]))  # fmt: skip
    z = (points @ to_second[:3, :3].T + to_second[:3, 3])[..., 2]
    u, v = _landing(e["flow"])
    ui, vi = u.round().long(), v.round().long()
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    zbuf = torch.full((H * W,), float("inf"), dtype=torch.float64)
    zbuf.scatter_reduce_(0, (vi * W + ui)[inside], z[inside], reduce="amin")
    zbuf = zbuf.view(H, W)
    # the nearest splatted point within a pixel of where each point lands
    padded = torch.nn.functional.pad(zbuf[None, None], (1, 1, 1, 1), value=float("inf"))
    near3 = -torch.nn.functional.max_pool2d(-padded, 3, 1)[0, 0]
    uc, vc = ui.clamp(0, W - 1), vi.clamp(0, H - 1)
    assert bool((near3[vc, uc] < 0.98 * z)[occluded].all())  # something nearer lands there
    # and a visible point is (almost always) the nearest to land on its own pixel
    hidden_by_splat = (zbuf[vc, uc] < 0.98 * z)[visible]
    assert float(hidden_by_splat.float().mean()) < 0.02


def test_visibility_codes_mark_each_pixel_once() -> None:
    valid = np.array([[True, True, True, False]])
    out = np.array([[False, True, True, True]])  # (a marked unknown pixel stays unknown)
    occ = np.array([[False, False, True, True]])
    codes = visibility_codes(valid, out, occ)
    assert codes.dtype == np.uint8
    np.testing.assert_array_equal(codes, [[VISIBLE, OUT_OF_FRAME, OUT_OF_FRAME, UNKNOWN]])
    np.testing.assert_array_equal(visibility_codes(valid, ~out, occ)[0, :3], [OUT_OF_FRAME,
                                  VISIBLE, OCCLUDED])  # fmt: skip


def _hand_made() -> dict[str, np.ndarray]:
    """A 2 × 4 pair with known errors: road on top, far field below, one unknown pixel."""
    exact = np.zeros((2, 4, 2))
    exact[..., 0] = [[1.0, 100.0, 100.0, 10.0], [1.0, 1.0, 1.0, 1.0]]
    est = exact.copy()
    est[0, 0, 0] += 3.5  # > 3 px and > 5 % of 1 px: outlier (occluded)
    est[0, 1, 0] += 4.0  # > 3 px but < 5 % of 100 px: not an outlier
    est[0, 2, 0] += 6.0  # > 3 px and > 5 % of 100 px: outlier (out of frame)
    est[0, 3, 0] += 2.0  # < 3 px: not an outlier
    est[1, 1, 0] += 1.0  # visible, 1 px
    region = np.array([[render.REGION_ROAD] * 4, [render.REGION_FAR] * 4], np.uint8)
    valid = np.ones((2, 4), bool)
    valid[1, 3] = False
    codes = np.full((2, 4), VISIBLE, np.uint8)
    codes[0, 0], codes[0, 2], codes[1, 3] = OCCLUDED, OUT_OF_FRAME, UNKNOWN
    return {"est": est, "exact": exact, "region": region, "valid": valid, "codes": codes}


def test_noc_and_all_pool_the_known_errors_and_outliers() -> None:
    p = _hand_made()
    q = flow_quality(p["est"], p["exact"], p["valid"], p["region"], noc=p["codes"] == VISIBLE)
    road, far, every = (QUALITY_REGIONS.index(r) for r in ("road", "far", "all"))
    noc, all_ = 0, 1
    np.testing.assert_allclose(q[all_, road], [3.5 + 4.0 + 6.0 + 2.0, 2, 4])
    np.testing.assert_allclose(q[all_, far], [1.0, 0, 3])
    np.testing.assert_allclose(q[all_, every], [16.5, 2, 7])
    np.testing.assert_allclose(q[noc, road], [4.0 + 2.0, 0, 2])  # both outliers were hidden
    np.testing.assert_allclose(q[noc, far], [1.0, 0, 3])
    np.testing.assert_allclose(q[noc, every], [7.0, 0, 5])
    # two pairs pooled pixel by pixel: the second exact everywhere (errors 0, same pixels)
    perfect = flow_quality(p["exact"], p["exact"], p["valid"], p["region"], p["codes"] == VISIBLE)
    pairs = [pair_stats(q, 1, occluded=1, out_of_frame=1), pair_stats(perfect, 0, 1, 1)]
    pooled = pooled_quality(pairs)
    assert pooled["regions"]["road"] == {"epe": 15.5 / 8, "fl": 100 * 2 / 8, "pixels": 8.0}
    assert pooled["regions"]["all"] == {"epe": 16.5 / 14, "fl": 100 * 2 / 14, "pixels": 14.0}
    assert pooled["regions_noc"]["road"] == {"epe": 6.0 / 4, "fl": 0.0, "pixels": 4.0}
    assert pooled["regions_noc"]["all"] == {"epe": 7.0 / 10, "fl": 0.0, "pixels": 10.0}
    assert pooled["regions_noc"]["moving"] == {"epe": None, "fl": None, "pixels": 0.0}
    assert (pooled["occluded_pixels"], pooled["out_of_frame_pixels"]) == (2, 2)
    assert pooled["nonfinite_pixels"] == 1
    by = pooled_quality_by_offset([(1, pairs[0]), (-1, pairs[1])])
    assert list(by) == ["-1", "1"] and by["1"]["pairs"] == 1
    assert by["1"]["regions_noc"]["all"]["epe"] == pytest.approx(7.0 / 5)
    assert by["-1"]["regions"]["all"]["fl"] == 0.0
    with pytest.raises(ValueError, match="older version"):
        pooled_quality([np.zeros(16)])  # the layout before noc: refused, not misread


def test_the_learned_flow_validation_scores_noc_and_all_as_the_numpy_sums() -> None:
    p = _hand_made()
    target = torch.from_numpy(np.where(p["valid"][..., None], p["exact"], np.nan))
    quality = PooledFlowQuality(quality_names())
    score_flow(
        quality,
        torch.from_numpy(p["est"]).permute(2, 0, 1)[None],
        target.permute(2, 0, 1)[None],
        torch.from_numpy(p["region"])[None],
        torch.tensor([1]),
        visibility=torch.from_numpy(p["codes"])[None],
    )
    metrics = {k: float(v) for k, v in flow_quality_metrics(quality, "val/").items()}
    assert metrics["val/epe"] == pytest.approx(16.5 / 7)
    assert metrics["val/fl"] == pytest.approx(100 * 2 / 7)
    assert metrics["val/epe_noc"] == pytest.approx(7.0 / 5)
    assert metrics["val/fl_noc"] == 0.0
    assert metrics["val/epe/road"] == pytest.approx(15.5 / 4)
    assert metrics["val/fl/road"] == pytest.approx(50.0)
    assert metrics["val/epe_noc/road"] == pytest.approx(3.0)
    assert metrics["val/epe_+1"] == pytest.approx(16.5 / 7)
    assert "val/epe_noc/moving" not in metrics  # no pixel of it
    # without visibility codes (a batch that has none) no noc score is made up
    plain = PooledFlowQuality(quality_names())
    score_flow(plain, torch.from_numpy(p["est"]).permute(2, 0, 1)[None],
               target.permute(2, 0, 1)[None], torch.from_numpy(p["region"])[None],
               torch.tensor([1]))  # fmt: skip
    assert not any("noc" in k for k in flow_quality_metrics(plain, "val/"))


def test_flow_pairs_carry_the_marks_and_the_learned_flow_validates_on_noc_and_all(
    tmp_path: Path,
) -> None:
    """``dataset=flow_pairs``: every pair keeps its exact flow where the point is hidden (the
    training target is unchanged) with the visibility codes beside it, and ``train_flow``'s
    validation scores both sets."""
    data = FlowPairsDataModule(
        train_sequences=1, sequence_length=10, val_fraction=0.3, frame_stride=1, val_every=1,
        image_hw=(64, 128), batch_size=2, eval_batch_size=4, num_workers=0, prepare_workers=0,
        cache_dir=str(tmp_path / "cache"), offsets=(1, 2),
    )  # fmt: skip
    data.prepare_data()
    ds = data.dataset("val")
    s = ds[len(ds) - 1]
    codes = s["visibility"]
    assert codes.shape == (64, 128) and codes.dtype == torch.uint8
    known = torch.isfinite(s["flow"]).all(0)
    assert torch.equal(known, codes != UNKNOWN)  # hidden pixels keep their flow
    hidden = float((codes != VISIBLE).float().mean())
    assert (codes == OUT_OF_FRAME).any() and 0.02 < hidden < 0.6, hidden
    config = PWCConfig(pyramid=(8, 8, 12, 16), decoder=(16, 16), context=(8, 8), dilations=(1, 2))
    torch.manual_seed(0)
    module = FlowLitModule(net=config.to_dict(), level_weights=(1.0, 1.0, 1.0))
    scores = quiet_trainer().validate(module, datamodule=data, verbose=False)[0]
    for key in ("val/epe", "val/fl", "val/epe_noc", "val/fl_noc", "val/epe_noc/road",
                "val/fl/road", "val/epe_+1", "val/epe_+2"):  # fmt: skip
        assert np.isfinite(scores[key]), key
    assert scores["val/epe_noc"] != scores["val/epe"]  # two sets of pixels, two scores
