"""Pictures: optical-flow colour coding and image grids (no geometry here).

Flow fields are drawn with the standard Middlebury colour wheel (Baker et al. 2011) via the
``flow_vis`` package; this module only adds a fixed, shared normalisation so that fields drawn
side by side are comparable.
"""

from __future__ import annotations

import math

import flow_vis
import numpy as np
import torch


def flow_to_rgb(flow: torch.Tensor | np.ndarray, max_norm: float | None = None) -> np.ndarray:
    """Colour-code one flow field.

    Args:
        flow: ``(2, H, W)`` (u, v) in pixels.
        max_norm: magnitude mapped to full saturation; None uses the field's own maximum.

    Returns:
        ``(H, W, 3)`` uint8 RGB.
    """
    if isinstance(flow, torch.Tensor):
        flow = flow.detach().float().cpu().numpy()
    uv = np.nan_to_num(np.asarray(flow, dtype=np.float64)).transpose(1, 2, 0)
    if max_norm is None:
        max_norm = float(np.sqrt((uv**2).sum(-1)).max())
    uv = uv / max(max_norm, 1e-9)
    # Saturate at the rim instead of flow_vis's dimmed "out of range" colours; and call its
    # wheel directly: flow_vis.flow_to_color normalises every field by its own maximum again,
    # which would undo a shared max_norm (ground truth and prediction drawn alike).
    uv = uv / np.maximum(np.sqrt((uv**2).sum(-1, keepdims=True)), 1.0)
    return flow_vis.flow_uv_to_colors(uv[..., 0], uv[..., 1], convert_to_bgr=False)


def colour_wheel(size: int = 65) -> np.ndarray:
    """The colour key of :func:`flow_to_rgb`: ``(size, size, 4)`` uint8 RGBA, a disc whose
    centre is no motion and whose rim is a motion of ``max_norm`` in the direction from the
    centre (image axes: x right, y down, as the fields are drawn); transparent outside."""
    c = (size - 1) / 2
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    uv = np.stack([(x - c) / c, (y - c) / c])
    inside = (uv**2).sum(0) <= 1.0
    rgba = np.zeros((size, size, 4), dtype=np.uint8)
    rgba[..., :3] = flow_to_rgb(uv, max_norm=1.0)
    rgba[..., 3] = np.where(inside, 255, 0)
    return rgba


def flows_to_rgb(flows: torch.Tensor, shared_norm: bool = True) -> torch.Tensor:
    """Colour-code a batch of flows for TensorBoard.

    Args:
        flows: ``(N, 2, H, W)`` pixels.
        shared_norm: normalise all fields by the largest magnitude among them (comparable colours).

    Returns:
        ``(N, 3, H, W)`` uint8.
    """
    max_norm = float(flows.detach().norm(dim=1).max()) if shared_norm else None
    images = [flow_to_rgb(f, max_norm) for f in flows]
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2)


def scalar_to_rgb(values: torch.Tensor | np.ndarray, cmap: str = "magma") -> np.ndarray:
    """Map a ``(H, W)`` scalar image to ``(H, W, 3)`` uint8 (matplotlib colour map, min–max)."""
    from matplotlib import colormaps

    if isinstance(values, torch.Tensor):
        values = values.detach().float().cpu().numpy()
    v = np.nan_to_num(np.asarray(values, dtype=np.float64))
    lo, hi = float(v.min()), float(v.max())
    v = (v - lo) / max(hi - lo, 1e-12)
    return (colormaps[cmap](v)[..., :3] * 255).astype(np.uint8)


def activation_map(hidden: torch.Tensor) -> np.ndarray:
    """``(M,)`` hidden activations of one input as a near-square heat map (the paper's activation
    pictures; brighter: more active): ``ceil(√M)`` columns, as many rows as needed, zero-padded.

    Returns:
        ``(rows, cols, 3)`` uint8 RGB.
    """
    m = hidden.numel()
    side = max(1, math.ceil(math.sqrt(m)))
    rows = math.ceil(m / side)
    pad = torch.zeros(rows * side)
    pad[:m] = hidden.detach().float().cpu().reshape(-1)
    return scalar_to_rgb(pad.view(rows, side))
