"""Snippet ATE (Zhou et al. 2017): hand-computed values, invariances and accumulation."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mfg_lightning.metrics import SnippetATE, snippet_ate, snippet_ate_errors


def _poses(rotations: np.ndarray, positions: np.ndarray) -> torch.Tensor:
    """``(..., 4, 4)`` from ``(..., 3, 3)`` rotations and ``(..., 3)`` positions."""
    T = np.zeros((*positions.shape[:-1], 4, 4))
    T[..., :3, :3] = rotations
    T[..., :3, 3] = positions
    T[..., 3, 3] = 1.0
    return torch.from_numpy(T)


def _line_snippet() -> torch.Tensor:
    """Five frames 1 m apart along z, no rotation: positions (0, 0, k)."""
    positions = np.array([[0.0, 0.0, k] for k in range(5)])
    return _poses(np.tile(np.eye(3), (5, 1, 1)), positions)[None]


def _random_snippets(count: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    rotations = Rotation.from_rotvec(rng.normal(0, 0.3, (count * 5, 3))).as_matrix()
    positions = np.cumsum(rng.normal(0, 1.0, (count, 5, 3)), axis=1) + rng.normal(
        0, 5, (count, 1, 3)
    )
    return _poses(rotations.reshape(count, 5, 3, 3), positions)


def _rigid(seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return _poses(Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 10, 3))


def _reference_ate(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """The protocol step by step for one snippet (numpy, matrix inverses, loops)."""
    g = np.array([(np.linalg.inv(gt[0]) @ gt[k])[:3, 3] for k in range(len(gt))])
    p = np.array([(np.linalg.inv(pred[0]) @ pred[k])[:3, 3] for k in range(len(pred))])
    p = p + (g[0] - p[0])
    s = np.sum(g * p) / np.sum(p * p)
    squared = np.sum((s * p - g) ** 2)
    return math.sqrt(squared) / len(gt), math.sqrt(squared / len(gt))


def test_known_perturbation_has_its_hand_computed_value() -> None:
    gt = _line_snippet()
    pred = gt.clone()
    pred[0, 4, 0, 3] = 1.0  # the last frame 1 m to the side: (1, 0, 4)
    # By hand: Σ g·p = 0 + 1 + 4 + 9 + 16 = 30, Σ p·p = 30 + 1 = 31, s = 30/31.
    # Residuals: k(s − 1) along z for k = 0…3, and (s, 0, 4s − 4) for k = 4, so
    # Σ‖·‖² = 30 (1/31)² + (30/31)² = 930/961 = 30/31.
    ate, rmse = snippet_ate_errors(pred, gt)
    assert ate.item() == pytest.approx(math.sqrt(30 / 31) / 5, abs=1e-12)
    assert rmse.item() == pytest.approx(math.sqrt(6 / 31), abs=1e-12)
    # The same snippets placed anywhere in the world give the same error.
    W = _rigid(0)
    ate_w, rmse_w = snippet_ate_errors(W @ pred, W @ gt)
    assert ate_w.item() == pytest.approx(ate.item(), abs=1e-12)
    assert rmse_w.item() == pytest.approx(rmse.item(), abs=1e-12)


def test_pure_scale_error_is_zero() -> None:
    gt = _random_snippets(20, 1)
    pred = gt.clone()
    pred[..., :3, 3] *= 3.7  # every position scaled about the world origin, rotations kept
    ate, rmse = snippet_ate_errors(pred, gt)
    assert ate.abs().max().item() < 1e-12 and rmse.abs().max().item() < 1e-12


def test_pure_offset_and_other_world_frame_are_zero() -> None:
    gt = _random_snippets(20, 2)
    shifted = gt.clone()
    shifted[..., :3, 3] += torch.tensor([100.0, -20.0, 3.0], dtype=torch.float64)
    assert snippet_ate_errors(shifted, gt)[0].abs().max().item() < 1e-12
    moved = _rigid(3) @ gt  # the whole prediction in another world frame
    assert snippet_ate_errors(moved, gt)[0].abs().max().item() < 1e-12


def test_matches_the_protocol_step_by_step() -> None:
    gt = _random_snippets(30, 4)
    pred = _random_snippets(30, 5)
    ate, rmse = snippet_ate_errors(pred, gt)
    for i in range(30):
        ref_ate, ref_rmse = _reference_ate(pred[i].numpy(), gt[i].numpy())
        assert ate[i].item() == pytest.approx(ref_ate, rel=1e-10)
        assert rmse[i].item() == pytest.approx(ref_rmse, rel=1e-10)
    summary = snippet_ate(pred, gt)
    assert summary["ate"].item() == pytest.approx(float(np.mean(ate.numpy())), rel=1e-12)
    # Population standard deviation (np.std, ddof 0), as Zhou et al.
    assert summary["ate_std"].item() == pytest.approx(float(np.std(ate.numpy())), rel=1e-10)
    assert summary["ate_rmse"].item() == pytest.approx(float(np.mean(rmse.numpy())), rel=1e-12)


def test_prediction_without_motion_is_finite() -> None:
    gt = _line_snippet()
    still = torch.eye(4, dtype=torch.float64).expand(1, 5, 4, 4)
    zeros = torch.zeros(1, 5, 4, 4, dtype=torch.float64)
    for pred in (still, zeros):
        ate, rmse = snippet_ate_errors(pred, gt)
        # Scale 0: the error of predicting no motion, ‖g‖ = sqrt(0 + 1 + 4 + 9 + 16).
        assert ate.item() == pytest.approx(math.sqrt(30) / 5, abs=1e-12)
        assert rmse.item() == pytest.approx(math.sqrt(30 / 5), abs=1e-12)


def test_float32_input_is_evaluated_in_float64() -> None:
    gt = _random_snippets(10, 6)
    pred = _random_snippets(10, 7)
    ate64, _ = snippet_ate_errors(pred, gt)
    ate32, _ = snippet_ate_errors(pred.float(), gt.float())
    assert ate32.dtype == torch.float64
    torch.testing.assert_close(ate32, ate64, atol=1e-5, rtol=1e-5)


def test_metric_is_the_same_in_one_batch_many_batches_or_merged() -> None:
    gt = _random_snippets(23, 8)
    pred = _random_snippets(23, 9)
    whole = SnippetATE()
    whole.update(pred, gt)
    split = SnippetATE()
    for chunk in (slice(0, 1), slice(1, 10), slice(10, 23)):
        split.update(pred[chunk], gt[chunk])
    # merge_state applies the same reductions (dist_reduce_fx) as a DDP sync.
    left, right = SnippetATE(), SnippetATE()
    left.update(pred[:11], gt[:11])
    right.update(pred[11:], gt[11:])
    left.merge_state(right)
    expected = snippet_ate(pred, gt)
    for result in (whole.compute(), split.compute(), left.compute()):
        assert set(result) == {"ate", "ate_std", "ate_rmse"}
        for key, value in expected.items():
            assert result[key].item() == pytest.approx(value.item(), rel=1e-12)


def test_metric_checks_shapes_and_handles_no_data() -> None:
    metric = SnippetATE(snippet_length=5)
    with pytest.raises(ValueError, match="5 frames"):
        metric.update(_random_snippets(2, 10)[:, :4], _random_snippets(2, 11)[:, :4])
    with pytest.raises(ValueError, match=r"\(B, L, 4, 4\)"):
        metric.update(_random_snippets(2, 10), _random_snippets(3, 11))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torchmetrics warns about compute before update
        result = metric.compute()
    assert all(math.isnan(v.item()) for v in result.values())
