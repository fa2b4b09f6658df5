"""Object motion: compensate the predicted egomotion field, then mask the residual (paper §4).

The definitions come from the paper's section 4 ("Object motion extraction", Filters 1 and 2) and
section 5.4 (parameter values), as restated in ``docs/protocols.md`` ("Object motion"):

* egomotion field ``ṽ = ρ ṽ_t + ṽ_ω`` with ``ρ = 1/depth`` (:func:`egomotion_field`);
* residual ``r = v̂ − ṽ`` (:func:`residual`);
* Filter 1, average thresholding: ``‖r‖² > θ_d · mean(tanh(‖r‖²))``
  (:func:`filter_average_threshold`);
* Filter 2, multistage divisive max-pooling normalisation on depth ``d`` normalised to [0, 1]:
  ``r' = ‖r‖²/max‖r‖²``, ``r'' = r' ∘ tanh(d)²``, ``r'' = r''/max r''``,
  ``r_s = r'' ∘ (1 + (max r'' − r'')²)⁻¹``, keep ``r_s > θ_p · mean(r_s)`` and ``d < Threshold_D``
  (:func:`filter_divisive_normalisation`);
* object mask ``F_obj = F1 ∧ F2`` and object field ``ṽ_obj = r ∘ F_obj``
  (:func:`extract_object_motion`).

Conventions
-----------
* Fields are ``(B, 2, H, W)`` in pixels per frame, as in :mod:`mfg_lightning.core.geometry`:
``ṽ_t`` is
  the translational field at unit inverse depth (ρ = 1 m⁻¹), ``ṽ_ω`` the rotational field.
* Depth is ``(B, H, W)`` along the camera z axis in metres; 0 marks unknown depth (the sample
  schema of :mod:`mfg_lightning.data.sample`). Zero, negative, infinite and NaN depths are
  *invalid*: they are never divided by, their egomotion field and residual are set to 0 and they
  never enter a mask, a mean or a max.
* "mean" and "max" in the filters are taken per sample over the valid pixels (flow valid and depth
  valid), so the whole batch is processed at once and one frame never influences another.
* Every function runs in float32 whatever the autocast around it
  (:func:`mfg_lightning.core.geometry.full_precision`): residuals and the thresholds they are
  compared with are never rounded to bfloat16 under ``trainer.precision=bf16-mixed``.

Depth normalisation (Filter 2)
------------------------------
The paper normalises depth "to range 0-1" and then reads Threshold_D = 0.2 as "objects closer than
20% of the maximum depth (655 meters)". 655.35 m is Virtual KITTI's far plane (16-bit depth in
centimetres saturates at 65535), so every VKITTI frame with sky has exactly that maximum and the
two readings "divide by the far plane" and "divide by the frame's own maximum" coincide there. They
differ on data without a far plane (LiDAR or synthetic frames without sky), where a per-frame
maximum would move the Threshold_D cut from frame to frame. We therefore default to the fixed far
plane (``depth_normalisation="fixed"``, ``d = min(depth / max_depth, 1)``) — which makes the
0.2 cut mean 131 m everywhere, as the paper states it — and offer the per-frame reading as
``depth_normalisation="per_frame"`` (``d = depth / the largest valid depth of the frame``, whether
or not the flow there is valid).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from mfg_lightning.core.geometry import full_precision

__all__ = [
    "DATASETS_WITH_DEPTH",
    "ObjectMotionConfig",
    "ObjectMotionError",
    "ObjectMotionResult",
    "depth_validity",
    "egomotion_field",
    "extract_object_motion",
    "filter_average_threshold",
    "filter_divisive_normalisation",
    "normalise_depth",
    "require_ground_truth",
    "residual",
    "squared_norm",
    "threshold_baseline",
]

#: Datasets of this project whose samples carry a ``depth`` key (named in error messages).
DATASETS_WITH_DEPTH = (
    "Virtual KITTI 1.3.1 / 2.0.3 (rendered dense depth)",
    "the synthetic driving dataset (exact depth)",
)

DepthNormalisation = Literal["fixed", "per_frame"]


class ObjectMotionError(ValueError):
    """Object-motion extraction cannot run on the given inputs (e.g. a sample without depth)."""


def _missing_depth_message() -> str:
    return (
        "object motion extraction needs depth: the predicted egomotion field is "
        "ṽ = ρ·ṽ_t + ṽ_ω with ρ = 1/depth (paper §4), so it cannot be compensated from the flow "
        "without a depth map, but depth is None. Datasets with depth: "
        + "; ".join(DATASETS_WITH_DEPTH)
        + ". KITTI odometry has no depth ground truth, so object motion is not evaluated on it."
    )


def require_ground_truth(sample: Mapping[str, Any]) -> None:
    """Refuse a dataset whose samples lack the ``depth`` and ``object_mask`` that object-motion
    extraction and its scores need (raises :class:`ObjectMotionError`, naming the datasets
    that have them)."""
    if "depth" not in sample or "object_mask" not in sample:
        raise ObjectMotionError(_missing_depth_message())


@dataclass
class ObjectMotionConfig:
    """Parameters of the object-mask pipeline (paper §4; values from §5.4).

    Attributes:
        theta_d: Filter 1 factor θ_d (paper: 1.5).
        theta_p: Filter 2 factor θ_p (paper: 0.5).
        threshold_d: Filter 2 depth cut Threshold_D on normalised depth (paper: 0.2, "objects
            closer than 20% of the maximum depth").
        max_depth: the far plane in metres used to normalise depth to [0, 1] (paper: "655
            meters", Virtual KITTI's 655.35 m far plane). Used when
            ``depth_normalisation == "fixed"``.
        depth_normalisation: ``"fixed"`` divides depth by ``max_depth`` (default, see the module
            docstring) and ``"per_frame"`` by the largest valid depth of each frame.
        baseline_threshold: the plain ``‖r‖ > threshold`` baseline's threshold in pixels per frame
            (this project's choice; the paper names the baseline but gives no value).
    """

    theta_d: float = 1.5
    theta_p: float = 0.5
    threshold_d: float = 0.2
    max_depth: float = 655.35
    depth_normalisation: DepthNormalisation = "fixed"
    baseline_threshold: float = 1.0

    def __post_init__(self) -> None:
        if self.depth_normalisation not in ("fixed", "per_frame"):
            raise ValueError(
                f"depth_normalisation must be 'fixed' or 'per_frame', got "
                f"{self.depth_normalisation!r}"
            )
        if self.max_depth <= 0:
            raise ValueError(f"max_depth must be positive (metres), got {self.max_depth}")


@dataclass
class ObjectMotionResult:
    """Everything :func:`extract_object_motion` computes for a batch.

    Attributes:
        ego_field: ``(B, 2, H, W)`` predicted egomotion field ``ṽ = ρ ṽ_t + ṽ_ω`` (px/frame);
            0 where depth is invalid.
        residual: ``(B, 2, H, W)`` ``r = v̂ − ṽ`` (px/frame); 0 on invalid pixels.
        mask: ``(B, H, W)`` bool object mask ``F1 ∧ F2``.
        object_flow: ``(B, 2, H, W)`` object motion field ``r ∘ mask`` (px/frame).
        f1: ``(B, H, W)`` bool Filter 1 (average thresholding).
        f2: ``(B, H, W)`` bool Filter 2 (divisive normalisation and depth cut).
        valid: ``(B, H, W)`` bool pixels that entered the filters (flow and depth valid).
        depth_norm: ``(B, H, W)`` depth normalised to [0, 1] (0 where depth is invalid).
    """

    ego_field: Tensor
    residual: Tensor
    mask: Tensor
    object_flow: Tensor
    f1: Tensor
    f2: Tensor
    valid: Tensor
    depth_norm: Tensor


# --------------------------------------------------------------------------------------------
# Masked per-sample reductions
# --------------------------------------------------------------------------------------------


def _all_valid(x: Tensor) -> Tensor:
    return torch.ones(x.shape[0], *x.shape[-2:], dtype=torch.bool, device=x.device)


def _masked_mean(x: Tensor, valid: Tensor) -> Tensor:
    """``(B, H, W)`` → ``(B, 1, 1)`` mean over valid pixels; 0 for a frame with none."""
    total = torch.where(valid, x, torch.zeros_like(x)).sum(dim=(-2, -1), keepdim=True)
    count = valid.sum(dim=(-2, -1), keepdim=True).clamp_min(1)
    return total / count


def _masked_max(x: Tensor, valid: Tensor) -> Tensor:
    """``(B, H, W)`` non-negative values → ``(B, 1, 1)`` max over valid pixels (0 if none)."""
    return torch.where(valid, x, torch.zeros_like(x)).amax(dim=(-2, -1), keepdim=True)


def _safe_divide(x: Tensor, denom: Tensor) -> Tensor:
    """``x / denom`` where ``denom > 0``, else 0: an all-zero frame stays all zero, not NaN."""
    positive = denom > 0
    return torch.where(positive, x / torch.where(positive, denom, torch.ones_like(denom)), 0.0)


# --------------------------------------------------------------------------------------------
# Fields
# --------------------------------------------------------------------------------------------


@full_precision
def depth_validity(depth: Tensor) -> Tensor:
    """Pixels whose depth can be inverted: finite and strictly positive.

    Args:
        depth: ``(B, H, W)`` metres (0 marks unknown depth).

    Returns:
        ``(B, H, W)`` bool.
    """
    return torch.isfinite(depth) & (depth > 0)


@full_precision
def squared_norm(field: Tensor) -> Tensor:
    """``(B, 2, H, W)`` field → ``(B, H, W)`` ``‖·‖²`` per pixel (px²)."""
    return (field * field).sum(dim=1)


@full_precision
def egomotion_field(v_t_pred: Tensor, v_w_pred: Tensor, depth: Tensor | None) -> Tensor:
    """The predicted egomotion field scaled by depth, ``ṽ = ρ ṽ_t + ṽ_ω`` (paper §4).

    Args:
        v_t_pred: ``(B, 2, H, W)`` predicted translational field at unit inverse depth (px/frame
            at ρ = 1 m⁻¹).
        v_w_pred: ``(B, 2, H, W)`` predicted rotational field (px/frame).
        depth: ``(B, H, W)`` depth in metres.

    Returns:
        ``(B, 2, H, W)`` in px/frame; 0 where the depth is invalid (see :func:`depth_validity`):
        the field is undefined there, and those pixels never enter a mask.

    Raises:
        ObjectMotionError: ``depth`` is None.
    """
    if depth is None:
        raise ObjectMotionError(_missing_depth_message())
    if depth.dim() != 3 or depth.shape[-2:] != v_t_pred.shape[-2:]:
        raise ObjectMotionError(
            f"depth must be (B, H, W) matching the fields {tuple(v_t_pred.shape)}, got "
            f"{tuple(depth.shape)}"
        )
    valid = depth_validity(depth)
    # Substitute 1 before inverting so invalid depths are never divided by (no inf/NaN gradients).
    inv_depth = torch.where(valid, 1.0 / torch.where(valid, depth, torch.ones_like(depth)), 0.0)
    field = inv_depth[:, None].to(v_t_pred) * v_t_pred + v_w_pred
    return torch.where(valid[:, None], field, torch.zeros_like(field))


@full_precision
def residual(flow: Tensor, ego_field: Tensor) -> Tensor:
    """Residual image velocity ``r = v̂ − ṽ`` (paper §4).

    Args:
        flow: ``(B, 2, H, W)`` input optical flow v̂ (px/frame).
        ego_field: ``(B, 2, H, W)`` predicted egomotion field ṽ (px/frame).

    Returns:
        ``(B, 2, H, W)`` px/frame.
    """
    return flow - ego_field


@full_precision
def normalise_depth(
    depth: Tensor,
    valid: Tensor | None = None,
    max_depth: float = 655.35,
    mode: DepthNormalisation = "fixed",
) -> Tensor:
    """Depth normalised to [0, 1] for Filter 2 (see the module docstring for the two modes).

    Args:
        depth: ``(B, H, W)`` metres.
        valid: ``(B, H, W)`` bool pixels to use (default: :func:`depth_validity`).
        max_depth: far plane in metres for ``mode="fixed"``; depths beyond it are clipped to 1
            (they are sky or beyond the cut either way).
        mode: ``"fixed"`` or ``"per_frame"``.

    Returns:
        ``(B, H, W)`` in [0, 1]; 0 on invalid pixels.
    """
    if valid is None:
        valid = depth_validity(depth)
    safe = torch.where(valid, depth, torch.zeros_like(depth))
    if mode == "fixed":
        d = safe / max_depth
    elif mode == "per_frame":
        d = _safe_divide(safe, _masked_max(safe, valid))
    else:
        raise ValueError(f"mode must be 'fixed' or 'per_frame', got {mode!r}")
    return d.clamp(0.0, 1.0)


# --------------------------------------------------------------------------------------------
# Filters
# --------------------------------------------------------------------------------------------


@full_precision
def filter_average_threshold(r: Tensor, theta_d: float, valid: Tensor | None = None) -> Tensor:
    """Filter 1, average thresholding: ``‖r‖² > θ_d · mean(tanh(‖r‖²))`` (paper §4).

    The tanh saturates large residues, so a few huge residues (near static structure) do not raise
    the threshold much: slow objects survive this filter, together with large static residue that
    Filter 2 removes.

    Args:
        r: ``(B, 2, H, W)`` residual (px/frame).
        theta_d: θ_d (paper: 1.5).
        valid: ``(B, H, W)`` bool pixels to consider (default: all); the mean is per sample over
            them and invalid pixels are never kept.

    Returns:
        ``(B, H, W)`` bool.
    """
    if valid is None:
        valid = _all_valid(r)
    r2 = squared_norm(r)
    threshold = theta_d * _masked_mean(torch.tanh(r2), valid)
    return (r2 > threshold) & valid


@full_precision
def filter_divisive_normalisation(
    r: Tensor,
    depth_norm: Tensor,
    theta_p: float,
    threshold_d: float,
    valid: Tensor | None = None,
) -> Tensor:
    """Filter 2, multistage divisive max-pooling normalisation (paper §4).

    With per-sample max and mean over the valid pixels::

        r'  = ‖r‖² / max ‖r‖²
        r'' = r' ∘ tanh(d)²            (depth weighting: near static residue is suppressed)
        r'' = r'' / max r''
        r_s = r'' ∘ (1 + (max r'' − r'')²)⁻¹
        F2  = (r_s > θ_p · mean(r_s)) ∧ (d < Threshold_D)

    Every division by a max is guarded: a frame whose residual is all zero gives r' = r'' = r_s = 0
    and an empty mask.

    Args:
        r: ``(B, 2, H, W)`` residual (px/frame).
        depth_norm: ``(B, H, W)`` depth normalised to [0, 1] (:func:`normalise_depth`).
        theta_p: θ_p (paper: 0.5).
        threshold_d: Threshold_D on normalised depth (paper: 0.2).
        valid: ``(B, H, W)`` bool pixels to consider (default: all).

    Returns:
        ``(B, H, W)`` bool.
    """
    if valid is None:
        valid = _all_valid(r)
    r2 = torch.where(valid, squared_norm(r), torch.zeros_like(depth_norm).to(r))
    r1 = _safe_divide(r2, _masked_max(r2, valid))
    r_dd = r1 * torch.tanh(depth_norm.to(r1)) ** 2
    r_dd = _safe_divide(r_dd, _masked_max(r_dd, valid))
    peak = _masked_max(r_dd, valid)
    r_s = r_dd / (1.0 + (peak - r_dd) ** 2)
    keep = r_s > theta_p * _masked_mean(r_s, valid)
    return keep & (depth_norm < threshold_d) & valid


@full_precision
def threshold_baseline(r: Tensor, threshold: float, valid: Tensor | None = None) -> Tensor:
    """The plain thresholding baseline: ``‖r‖ > threshold`` (px/frame).

    The paper (§4) notes that this fails: a threshold high enough to reject the large residue of
    near static structure also rejects slow (or distant) moving objects.

    Args:
        r: ``(B, 2, H, W)`` residual (px/frame).
        threshold: pixels per frame.
        valid: ``(B, H, W)`` bool pixels to consider (default: all).

    Returns:
        ``(B, H, W)`` bool.
    """
    keep = squared_norm(r) > threshold * threshold
    return keep if valid is None else keep & valid


# --------------------------------------------------------------------------------------------
# The pipeline
# --------------------------------------------------------------------------------------------


@full_precision
def extract_object_motion(
    flow: Tensor,
    v_t_pred: Tensor,
    v_w_pred: Tensor,
    depth: Tensor | None,
    config: ObjectMotionConfig | None = None,
    valid: Tensor | None = None,
) -> ObjectMotionResult:
    """Object mask and object motion field from flow, predicted egomotion fields and depth.

    Args:
        flow: ``(B, 2, H, W)`` input optical flow v̂ (px/frame).
        v_t_pred: ``(B, 2, H, W)`` predicted translational field at unit inverse depth.
        v_w_pred: ``(B, 2, H, W)`` predicted rotational field.
        depth: ``(B, H, W)`` depth in metres (0 where unknown).
        config: filter parameters (default: the paper's, :class:`ObjectMotionConfig`).
        valid: ``(B, H, W)`` bool flow validity (``flow_valid`` of the sample); default all.
            Combined with depth validity; non-finite flow pixels are also excluded.

    Returns:
        :class:`ObjectMotionResult`.

    Raises:
        ObjectMotionError: ``depth`` is None.
    """
    if depth is None:
        raise ObjectMotionError(_missing_depth_message())
    config = config or ObjectMotionConfig()
    px_valid = depth_validity(depth) & torch.isfinite(flow).all(dim=1)
    if valid is not None:
        px_valid = px_valid & valid.to(torch.bool)
    ego = egomotion_field(v_t_pred, v_w_pred, depth)
    finite_flow = torch.where(px_valid[:, None], flow, torch.zeros_like(flow))
    r = torch.where(px_valid[:, None], residual(finite_flow, ego), torch.zeros_like(ego))
    # Depth is normalised over every pixel with a depth, flow-valid or not: on Virtual KITTI the
    # sky has invalid flow but keeps its 655.35 m far plane, which is the frame's maximum.
    d = normalise_depth(depth, None, config.max_depth, config.depth_normalisation)
    f1 = filter_average_threshold(r, config.theta_d, px_valid)
    f2 = filter_divisive_normalisation(r, d, config.theta_p, config.threshold_d, px_valid)
    mask = f1 & f2
    return ObjectMotionResult(
        ego_field=ego,
        residual=r,
        mask=mask,
        object_flow=r * mask[:, None].to(r),
        f1=f1,
        f2=f2,
        valid=px_valid,
        depth_norm=d,
    )
