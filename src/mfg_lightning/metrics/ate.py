"""Absolute trajectory error over short snippets (Zhou et al. 2017; the paper's Table 1).

Definition (``docs/protocols.md``, "ATE over 5-frame snippets"), for one snippet of
``L`` frames with ground-truth positions ``g_k`` and predicted positions ``p_k``, both expressed in
the camera of the snippet's first frame (so the first position is the origin):

1. translate the prediction so that its first position equals the ground truth's first position;
2. scale it by the least-squares factor ``s = Σ (g · p) / Σ (p · p)`` (sums over all coordinates of
   the L points); no rotation alignment;
3. ``ate = sqrt( Σ_k ‖s·p_k − g_k‖² ) / L``: the root of the summed squares divided by the number of
   frames, the definition of Zhou et al.'s ``compute_ate`` behind every number of Table 1;
   ``ate_rmse = sqrt( Σ_k ‖s·p_k − g_k‖² / L )`` is the conventional RMSE, reported beside it.

Over a set of snippets: the mean and the population standard deviation (``np.std``, as Zhou et
al.) of ``ate``, and the mean of ``ate_rmse``. Units: those of the poses (metres for KITTI).

Degenerate prediction: when every predicted position equals the first one (a method predicting no
motion, or all-zero translations), ``Σ p·p = 0`` and ``s`` is undefined. Any ``s`` then gives the
same aligned prediction (all points at the origin), so ``s = 0`` is used and the error is that of
predicting no motion, ``sqrt(Σ ‖g_k‖²) / L`` — finite, never NaN.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from mfg_lightning.core import geometry
from mfg_lightning.metrics.stats import cat_state, summary
from mfg_lightning.trajectory.trajectories import evaluation_poses

__all__ = [
    "ATE_NAMES",
    "SnippetATE",
    "snippet_ate",
    "snippet_ate_errors",
    "snippet_ate_from_errors",
]

#: The published names of :func:`snippet_ate` and :class:`SnippetATE`.
ATE_NAMES: tuple[str, ...] = ("ate", "ate_std", "ate_rmse")


def _check_snippets(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape or pred.dim() != 4 or tuple(pred.shape[-2:]) != (4, 4):
        raise ValueError(
            "pred and target must both be snippets of poses shaped (B, L, 4, 4), got "
            f"{tuple(pred.shape)} and {tuple(target.shape)}"
        )


def snippet_ate_errors(pred: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Per-snippet ATE after translation and scale alignment (Zhou et al. 2017).

    Args:
        pred: ``(B, L, 4, 4)`` predicted camera-to-world poses of B snippets of L frames, in any
            reference frame (each snippet is re-expressed relative to its first frame here).
        target: ``(B, L, 4, 4)`` ground-truth camera-to-world poses, any reference frame.

    Returns:
        ``(ate, ate_rmse)``, ``(B,)`` float64 each, in the unit of the poses' translations:
        ``sqrt(Σ_k ‖s·p_k − g_k‖²) / L`` and ``sqrt(Σ_k ‖s·p_k − g_k‖² / L)`` (module docstring).
    """
    _check_snippets(pred, target)
    P = evaluation_poses(pred)
    Q = evaluation_poses(target).to(P.device)
    # Positions of every frame in the camera of its snippet's first frame: (B, L, 3).
    p = geometry.relative_pose(P[:, :1], P)[..., :3, 3]
    g = geometry.relative_pose(Q[:, :1], Q)[..., :3, 3]
    # Both first positions are the origin up to rounding; the offset step is kept as published.
    p = p - p[:, :1] + g[:, :1]
    num = (g * p).sum(dim=(1, 2))
    den = (p * p).sum(dim=(1, 2))
    positive = den > 0
    scale = torch.where(positive, num / torch.where(positive, den, torch.ones_like(den)), 0.0)
    squared = ((scale[:, None, None] * p - g) ** 2).sum(dim=(1, 2))
    length = pred.shape[1]
    return squared.sqrt() / length, (squared / length).sqrt()


def _summary(ate: Tensor, ate_rmse: Tensor) -> dict[str, Tensor]:
    """Mean and population std over snippets; NaN when there are none."""
    stats = summary(ate)
    # ate_rmse is the mean of the per-snippet RMSEs (not the RMSE of ate): Table 1's layout.
    return {"ate": stats["mean"], "ate_std": stats["std"], "ate_rmse": summary(ate_rmse)["mean"]}


def snippet_ate_from_errors(ate: Tensor, ate_rmse: Tensor) -> dict[str, Tensor]:
    """ATE over a set of snippets from their per-snippet errors (of one sequence or several).

    Args:
        ate, ate_rmse: ``(B,)`` as :func:`snippet_ate_errors` returns them.

    Returns:
        The dict of :func:`snippet_ate` (NaN when ``B == 0``).
    """
    return _summary(ate, ate_rmse)


def snippet_ate(pred: Tensor, target: Tensor) -> dict[str, Tensor]:
    """ATE over a set of snippets: the functional twin of :class:`SnippetATE`.

    Args:
        pred, target: ``(B, L, 4, 4)`` camera-to-world poses of B snippets (see
            :func:`snippet_ate_errors`).

    Returns:
        ``{"ate", "ate_std", "ate_rmse"}``: float64 scalars, the mean of the per-snippet ATE, its
        population standard deviation, and the mean per-snippet RMSE. NaN when ``B == 0``.
    """
    return _summary(*snippet_ate_errors(pred, target))


class SnippetATE(Metric):
    """Accumulated snippet ATE (Zhou et al. 2017; the paper's Table 1), DDP-safe.

    Each ``update`` adds a batch of snippets; per-snippet errors are stored in list states
    reduced by concatenation, so the result is the same whether the snippets arrive in one batch,
    in many, or spread over processes. Use one instance per sequence to report per-sequence
    numbers (``test/09/ate``) and one over all sequences for the pooled value.

    Args:
        snippet_length: the L every update must have (5 in Table 1); ``None`` accepts any. The
            ATE divides by L, so mixing lengths in one metric would mix definitions.
        kwargs: passed to :class:`torchmetrics.Metric`.

    ``compute()`` returns ``{"ate", "ate_std", "ate_rmse"}`` (float64 scalars, pose units).
    """

    names = ATE_NAMES
    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, snippet_length: int | None = 5, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if snippet_length is not None and snippet_length < 1:
            raise ValueError(f"snippet_length must be >= 1 or None, got {snippet_length}")
        self.snippet_length = snippet_length
        self.add_state("ate_values", default=[], dist_reduce_fx="cat")
        self.add_state("rmse_values", default=[], dist_reduce_fx="cat")

    def update(self, pred: Tensor, target: Tensor) -> None:
        """Add B snippets.

        Args:
            pred: ``(B, L, 4, 4)`` predicted camera-to-world poses, any reference frame.
            target: ``(B, L, 4, 4)`` ground-truth camera-to-world poses, any reference frame.
        """
        _check_snippets(pred, target)
        if self.snippet_length is not None and pred.shape[1] != self.snippet_length:
            raise ValueError(
                f"expected snippets of {self.snippet_length} frames, got {pred.shape[1]}"
            )
        ate, rmse = snippet_ate_errors(pred, target)
        self.ate_values.append(ate)
        self.rmse_values.append(rmse)

    def compute(self) -> dict[str, Tensor]:
        """``{"ate", "ate_std", "ate_rmse"}`` over every snippet seen (NaN if none)."""
        return _summary(cat_state(self.ate_values), cat_state(self.rmse_values))
