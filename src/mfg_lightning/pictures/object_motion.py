"""Picture grids of object-motion extraction in the layout of the paper's supplementary Figure 1.

Each sample is one column of six panels, top to bottom (the paper's a–f): the RGB frame (or the
inverse depth when there is no RGB), the input optical flow, the predicted egomotion field
``ṽ = ρ ṽ_t + ṽ_ω``, the residual ``r = v̂ − ṽ``, the object mask and the object motion field
``r ∘ mask``. A batch puts samples side by side. Flow-like panels use the Middlebury colour wheel
of :mod:`mfg_lightning.pictures.colours`; within a column, the input flow and the egomotion field
share one normalisation (they are the same kind of quantity, so equal colours mean equal
velocities), and so do the residual and the object field. Each panel's title gives the magnitude
that maps to full saturation.

Rendering uses matplotlib's Agg canvas directly (no pyplot state, no display needed); images are
returned as ``(H', W', 3)`` uint8 arrays for PNG files (:func:`save_png`) or TensorBoard
(``add_image(tag, image, dataformats="HWC")``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mfg_lightning.motion.object_motion import ObjectMotionConfig, ObjectMotionResult
from mfg_lightning.pictures.colours import flow_to_rgb, scalar_to_rgb
from mfg_lightning.pictures.grids import panel_grid

__all__ = [
    "PANEL_TITLES",
    "object_motion_grid",
    "object_motion_grid_batch",
    "object_motion_panels",
    "object_motion_pictures",
]

#: The six panels of one column (the paper's supplementary Figure 1, a–f).
PANEL_TITLES = (
    "RGB",
    "input flow",
    "predicted egomotion field",
    "residual",
    "object mask",
    "object motion field",
)

# Mask colours when a ground-truth mask is given: hits, false alarms, misses.
_HIT = np.array([255, 255, 255], dtype=np.uint8)
_FALSE_ALARM = np.array([230, 40, 40], dtype=np.uint8)
_MISS = np.array([40, 90, 230], dtype=np.uint8)


def _np(x: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _max_norm(field: np.ndarray, valid: np.ndarray) -> float:
    """Largest ``‖·‖`` of a ``(2, H, W)`` field over valid pixels (0 when none)."""
    norm = np.sqrt((np.nan_to_num(field.astype(np.float64)) ** 2).sum(0))
    return float(norm[valid].max()) if valid.any() else 0.0


def _mask_rgb(mask: np.ndarray, gt_mask: np.ndarray | None) -> np.ndarray:
    """``(H, W)`` bool → ``(H, W, 3)`` uint8: white mask, or hit/false-alarm/miss colours."""
    image = np.zeros((*mask.shape, 3), dtype=np.uint8)
    if gt_mask is None:
        image[mask] = _HIT
        return image
    image[mask & gt_mask] = _HIT
    image[mask & ~gt_mask] = _FALSE_ALARM
    image[~mask & gt_mask] = _MISS
    return image


def object_motion_panels(
    result: ObjectMotionResult,
    flow: Tensor,
    index: int = 0,
    rgb: Tensor | None = None,
    depth: Tensor | None = None,
    gt_mask: Tensor | None = None,
) -> list[tuple[str, np.ndarray]]:
    """The six panels of one sample as ``(title, (H, W, 3) uint8)`` pairs, top to bottom.

    Args:
        result: output of :func:`mfg_lightning.motion.object_motion.extract_object_motion` for a
        batch.
        flow: ``(B, 2, H, W)`` input flow (px/frame) that produced ``result``.
        index: which sample of the batch.
        rgb: optional ``(B, 3, H, W)`` uint8 source frames.
        depth: optional ``(B, H, W)`` depth (m) for the first panel when there is no RGB; without
            it the normalised depth held in ``result`` is used.
        gt_mask: optional ``(B, H, W)`` bool ground-truth object mask; when given the mask panel
            shows hits white, false alarms red and misses blue.

    Returns:
        Six ``(title, image)`` pairs in the order of :data:`PANEL_TITLES`.
    """
    valid = _np(result.valid[index]).astype(bool)
    if rgb is not None:
        first = ("RGB", _np(rgb[index]).transpose(1, 2, 0).astype(np.uint8))
    else:
        d = _np(depth[index] if depth is not None else result.depth_norm[index]).astype(np.float64)
        has = np.isfinite(d) & (d > 0)
        # Inverse depth: near structure, where object motion is found, gets the contrast.
        inv = np.where(has, 1.0 / np.where(has, d, 1.0), 0.0)
        first = ("inverse depth", scalar_to_rgb(inv))

    flow_i = _np(flow[index]).astype(np.float32)
    ego = _np(result.ego_field[index]).astype(np.float32)
    res = _np(result.residual[index]).astype(np.float32)
    obj = _np(result.object_flow[index]).astype(np.float32)
    flow_scale = max(_max_norm(flow_i, valid), _max_norm(ego, valid))
    res_scale = _max_norm(res, valid)
    mask = _np(result.mask[index]).astype(bool)
    gt = None if gt_mask is None else _np(gt_mask[index]).astype(bool)
    mask_title = "object mask" if gt is None else "object mask (hit / false alarm / miss)"
    return [
        first,
        (f"input flow (max {flow_scale:.2f} px)", flow_to_rgb(flow_i, flow_scale)),
        (f"predicted egomotion field (max {flow_scale:.2f} px)", flow_to_rgb(ego, flow_scale)),
        (f"residual (max {res_scale:.2f} px)", flow_to_rgb(res, res_scale)),
        (mask_title, _mask_rgb(mask, gt)),
        (f"object motion field (max {res_scale:.2f} px)", flow_to_rgb(obj, res_scale)),
    ]


def object_motion_grid(
    result: ObjectMotionResult,
    flow: Tensor,
    index: int = 0,
    header: str = "",
    **images: Tensor | None,
) -> np.ndarray:
    """One sample's column of six titled panels (paper supplementary Figure 1, a–f).

    Arguments as in :func:`object_motion_panels` (``images``: its ``rgb``, ``depth`` and
    ``gt_mask``); ``header`` (e.g. the sample id) prefixes the first title.

    Returns:
        ``(H', W', 3)`` uint8 RGB image.
    """
    return panel_grid([object_motion_panels(result, flow, index, **images)], [header])


def object_motion_grid_batch(
    result: ObjectMotionResult,
    flow: Tensor,
    rgb: Tensor | None = None,
    depth: Tensor | None = None,
    gt_mask: Tensor | None = None,
    max_samples: int = 4,
    headers: Sequence[str] | None = None,
) -> np.ndarray:
    """The first ``max_samples`` samples of a batch, one column each, side by side.

    Arguments as in :func:`object_motion_panels`, for the whole batch; ``headers`` optionally
    names each column (e.g. the batch's ``sample_id`` list).

    Returns:
        ``(H', W', 3)`` uint8 RGB image.
    """
    n = min(int(flow.shape[0]), max_samples)
    if n < 1:
        raise ValueError("object_motion_grid_batch needs a non-empty batch")
    columns = [object_motion_panels(result, flow, i, rgb, depth, gt_mask) for i in range(n)]
    names = list(headers[:n]) if headers is not None else [""] * n
    return panel_grid(columns, names)


@torch.no_grad()
def object_motion_pictures(
    model: Callable[[Tensor], Any],
    batch: Mapping[str, Any],
    config: ObjectMotionConfig,
    max_samples: int = 4,
) -> np.ndarray:
    """Extract object motion (paper §4) from the first ``max_samples`` samples of a batch with
    depth and ground-truth masks, and draw them side by side (:func:`object_motion_grid_batch`).

    Args:
        model: the MFG module in eval mode; ``model(flow)`` returns ``v_t`` and ``v_omega``.
        batch: a collated batch with ``flow``, ``flow_valid``, ``depth``, ``object_mask``,
            ``sample_id`` and optionally ``rgb``.
        config: the object-motion filters.
        max_samples: columns drawn.

    Returns:
        ``(H', W', 3)`` uint8 RGB image.
    """
    from mfg_lightning.motion.object_motion import extract_object_motion

    n = max_samples
    flow, depth = batch["flow"][:n], batch["depth"][:n]
    pred = model(flow)
    result = extract_object_motion(
        flow, pred.v_t, pred.v_omega, depth, config, valid=batch["flow_valid"][:n]
    )
    return object_motion_grid_batch(
        result, flow, rgb=batch["rgb"][:n] if "rgb" in batch else None, depth=depth,
        gt_mask=batch["object_mask"][:n], max_samples=n, headers=list(batch["sample_id"][:n]),
    )  # fmt: skip
