"""The MFG training losses (paper section 4): L_t, L_ω, their balancing weights, and L_s.

Every function here runs in float32 whatever the autocast around it
(:func:`mfg_lightning.core.geometry.full_precision`): under ``bf16-mixed`` the sums over 6144
pixels, the balancing ratios and the sparsity count (42.42 comes out 42.5 in bfloat16) would
otherwise round to 8 significant bits.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from mfg_lightning.core.geometry import full_precision


class LossTerms(NamedTuple):
    """Every term of the loss, per batch.

    Attributes:
        total: scalar, the mean over the batch of ``w_t L_t + w_ω L_ω + w_s L_s``.
        l_t, l_omega, l_s: ``(B,)`` per-sample terms.
        w_t, w_omega: ``(B,)`` per-sample balancing weights (no gradient).
    """

    total: Tensor
    l_t: Tensor
    l_omega: Tensor
    l_s: Tensor
    w_t: Tensor
    w_omega: Tensor


@full_precision
def sparsity_count(hidden: Tensor, q: float = 25.0, b: float = 10.0) -> Tensor:
    """Differentiable count of active units, ``L_s = Σ_i 1 / (1 + Q e^(−B h_i))`` per sample.

    Args:
        hidden: ``(B, M)`` non-negative activations.
        q, b: the generalised logistic's Q and B (paper: 25 and 10).

    Returns:
        ``(B,)``.
    """
    # 1 / (1 + Q e^{-Bh}) = sigmoid(B h - ln Q), numerically stable for any h.
    return torch.sigmoid(b * hidden - torch.log(torch.tensor(q, dtype=hidden.dtype))).sum(dim=1)


@full_precision
def balancing_weights(
    v_t: Tensor, v_omega: Tensor, max_weight: float | None = 100.0, squared: bool = False
) -> tuple[Tensor, Tensor]:
    """Per-sample weights that equalise translation and rotation (paper eq. 8).

    ``w_t = max(‖v_ω‖ / ‖v_t‖, 1)``, ``w_ω = max(‖v_t‖ / ‖v_ω‖, 1)``, L2 norms over the whole
    ground-truth field, as the authors' released code computes them (the default);
    ``squared=True`` squares the ratio, the paper's formula with its superscript read as a
    power. The weights are clamped to ``max_weight`` (a sample with no rotation would
    otherwise get an infinite weight) and carry no gradient.

    Args:
        v_t, v_omega: ``(B, 2, H, W)`` ground-truth fields.

    Returns:
        ``(w_t, w_ω)``, ``(B,)`` each.
    """
    n_t = v_t.detach().flatten(1).norm(dim=1)
    n_w = v_omega.detach().flatten(1).norm(dim=1)
    if squared:
        n_t, n_w = n_t.square(), n_w.square()
    eps = torch.finfo(n_t.dtype).tiny
    w_t = (n_w / n_t.clamp_min(eps)).clamp_min(1.0)
    w_w = (n_t / n_w.clamp_min(eps)).clamp_min(1.0)
    if max_weight is not None:
        w_t, w_w = w_t.clamp_max(max_weight), w_w.clamp_max(max_weight)
    return w_t, w_w


class MFGLoss(nn.Module):
    """``L = w_t L_t + w_ω L_ω + w_s L_s`` (paper eq. 10), vectorised over the batch.

    Args:
        w_s: sparsity coefficient (paper: 100). Must be ≥ 0.
        w_t, w_omega: fixed weights; None (default) uses the per-sample balancing weights.
        balance_max: upper clamp of the balancing weights (None: no clamp).
        balance_squared: True: the paper's squared-norm ratio; False: the released code's ratio.
        sparsity_q, sparsity_b: Q and B of the generalised logistic (paper: 25, 10).
        reduction: ``"sum"`` sums |error| over pixels as the paper does; ``"mean"`` averages.
    """

    def __init__(
        self,
        w_s: float = 100.0,
        w_t: float | None = None,
        w_omega: float | None = None,
        balance_max: float | None = 100.0,
        balance_squared: bool = False,
        sparsity_q: float = 25.0,
        sparsity_b: float = 10.0,
        reduction: str = "sum",
    ) -> None:
        super().__init__()
        for name, value in (("w_s", w_s), ("w_t", w_t), ("w_omega", w_omega)):
            if value is not None and not value >= 0:
                raise ValueError(f"model.loss.{name} must be non-negative, got {value}")
        if balance_max is not None and balance_max < 1:
            raise ValueError(f"model.loss.balance_max must be ≥ 1 (or null), got {balance_max}")
        if reduction not in ("sum", "mean"):
            raise ValueError(f"model.loss.reduction must be 'sum' or 'mean', got {reduction!r}")
        self.w_s, self.w_t, self.w_omega = w_s, w_t, w_omega
        self.balance_max, self.balance_squared = balance_max, balance_squared
        self.q, self.b = sparsity_q, sparsity_b
        self.reduction = reduction

    @full_precision
    def forward(
        self, pred_t: Tensor, pred_omega: Tensor, gt_t: Tensor, gt_omega: Tensor, hidden: Tensor
    ) -> LossTerms:
        """All tensors batched: fields ``(B, 2, H, W)`` in pixels, hidden ``(B, M)``; every term
        in float32 (float64 inputs: float64)."""
        reduce = torch.sum if self.reduction == "sum" else torch.mean
        l_t = reduce((pred_t - gt_t).abs().flatten(1), dim=1)
        l_w = reduce((pred_omega - gt_omega).abs().flatten(1), dim=1)
        l_s = sparsity_count(hidden, self.q, self.b)
        w_t, w_w = balancing_weights(gt_t, gt_omega, self.balance_max, self.balance_squared)
        if self.w_t is not None:
            w_t = torch.full_like(w_t, self.w_t)
        if self.w_omega is not None:
            w_w = torch.full_like(w_w, self.w_omega)
        total = (w_t * l_t + w_w * l_w + self.w_s * l_s).mean()
        return LossTerms(total, l_t, l_w, l_s, w_t, w_w)
