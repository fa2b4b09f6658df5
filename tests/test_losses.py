"""Loss terms against values worked out by hand."""

from __future__ import annotations

import math

import pytest
import torch

from mfg_lightning.models.losses import MFGLoss, balancing_weights, sparsity_count


def test_sparsity_count_matches_the_generalised_logistic() -> None:
    h = torch.tensor([[0.0, 0.5, 2.0]])
    expected = sum(1 / (1 + 25 * math.exp(-10 * x)) for x in (0.0, 0.5, 2.0))
    assert sparsity_count(h).item() == pytest.approx(expected, rel=1e-6)
    # g(0) = 1/26: an inactive unit costs almost nothing; a unit at h = 1 is counted as ~1.
    assert sparsity_count(torch.zeros(1, 1)).item() == pytest.approx(1 / 26)
    assert sparsity_count(torch.ones(1, 1)).item() > 0.99


def test_balancing_weights_by_hand() -> None:
    v_t = torch.zeros(2, 2, 1, 2)
    v_w = torch.zeros(2, 2, 1, 2)
    v_t[0, 0, 0, 0], v_w[0, 0, 0, 0] = 3.0, 1.0  # ‖v_t‖² = 9, ‖v_ω‖² = 1
    v_t[1, 0, 0, 0], v_w[1, 1, 0, 1] = 1.0, 2.0  # ‖v_t‖² = 1, ‖v_ω‖² = 4
    # The squared ratio (the paper's superscript read as a power).
    w_t, w_w = balancing_weights(v_t, v_w, max_weight=None, squared=True)
    assert w_t.tolist() == pytest.approx([1.0, 4.0])
    assert w_w.tolist() == pytest.approx([9.0, 1.0])
    # The released code's un-squared ratio: the default.
    for w_t, w_w in (
        balancing_weights(v_t, v_w, max_weight=None, squared=False),
        balancing_weights(v_t, v_w, max_weight=None),
    ):
        assert w_t.tolist() == pytest.approx([1.0, 2.0])
        assert w_w.tolist() == pytest.approx([3.0, 1.0])
    # Clamp: no rotation at all gives the clamp, not infinity.
    w_t, w_w = balancing_weights(v_t, torch.zeros_like(v_w), max_weight=100.0)
    assert w_w.tolist() == [100.0, 100.0]


def test_total_loss_by_hand() -> None:
    gt_t = torch.zeros(1, 2, 1, 2)
    gt_w = torch.zeros(1, 2, 1, 2)
    gt_t[0, 0, 0, 0] = 2.0  # ‖v_t‖² = 4
    gt_w[0, 1, 0, 1] = 1.0  # ‖v_ω‖ = 1  → w_t = 1, w_ω = 2 (released code), 4 (squared)
    pred_t = gt_t + torch.tensor([0.5, -0.5, 0.0, 0.0]).view(1, 2, 1, 2)  # L_t = 1.0
    pred_w = gt_w + 0.25  # L_ω = 4 × 0.25 = 1.0
    hidden = torch.tensor([[0.0, 1.0]])
    l_s = 1 / 26 + 1 / (1 + 25 * math.exp(-10))
    loss = MFGLoss(w_s=2.0)
    terms = loss(pred_t, pred_w, gt_t, gt_w, hidden)
    assert terms.l_t.item() == pytest.approx(1.0)
    assert terms.l_omega.item() == pytest.approx(1.0)
    assert terms.total.item() == pytest.approx(1 * 1.0 + 2 * 1.0 + 2.0 * l_s, rel=1e-6)
    squared = MFGLoss(w_s=2.0, balance_squared=True)(pred_t, pred_w, gt_t, gt_w, hidden)
    assert squared.total.item() == pytest.approx(1 * 1.0 + 4 * 1.0 + 2.0 * l_s, rel=1e-6)
    fixed = MFGLoss(w_s=0.0, w_t=3.0, w_omega=0.5)(pred_t, pred_w, gt_t, gt_w, hidden)
    assert fixed.total.item() == pytest.approx(3.0 + 0.5)
    mean = MFGLoss(w_s=0.0, reduction="mean")(pred_t, pred_w, gt_t, gt_w, hidden)
    assert mean.l_t.item() == pytest.approx(1.0 / 4)


def test_loss_is_vectorised_over_the_batch() -> None:
    gen = torch.Generator().manual_seed(0)
    args = [torch.randn(3, 2, 4, 5, generator=gen) for _ in range(4)] + [
        torch.rand(3, 7, generator=gen)
    ]
    loss = MFGLoss(w_s=10.0)
    batch = loss(*args)
    singles = [loss(*(a[i : i + 1] for a in args)) for i in range(3)]
    torch.testing.assert_close(batch.l_t, torch.cat([s.l_t for s in singles]))
    torch.testing.assert_close(batch.total, torch.stack([s.total for s in singles]).mean())


@pytest.mark.parametrize(
    "kwargs", [{"w_s": -1.0}, {"w_t": -0.1}, {"balance_max": 0.5}, {"reduction": "max"}]
)
def test_bad_loss_settings_are_refused(kwargs) -> None:
    with pytest.raises(ValueError, match="model.loss"):
        MFGLoss(**kwargs)


@pytest.mark.parametrize(
    ("tz", "wy", "squared", "w_omega"),
    [(1.0, 0.01, True, 100.0), (1.0, 0.01, False, 41.87), (0.5, 0.03, True, 48.70),
     (0.5, 0.03, False, 6.979)],
)  # fmt: skip
def test_balancing_weights_of_real_fields_for_both_readings(
    tz: float, wy: float, squared: bool, w_omega: float
) -> None:
    """The two readings of w = max(‖v_ω‖ / ‖v_t‖, 1) at 48 × 128 with KITTI intrinsics: the
    paper's squared ratio reaches the clamp where the released code's is 42."""
    from mfg_lightning.core import geometry
    from mfg_lightning.scene.camera import kitti_like_intrinsics

    K = kitti_like_intrinsics(48, 128).float()[None]
    v_t = geometry.translational_field(torch.tensor([[0.0, 0.0, tz]]), K, 48, 128)
    v_w = geometry.rotational_field(torch.tensor([[0.0, wy, 0.0]]), K, 48, 128)
    w_t, w_w = balancing_weights(v_t, v_w, max_weight=100.0, squared=squared)
    assert w_t.item() == 1.0
    assert w_w.item() == pytest.approx(w_omega, rel=1e-3)
