"""Resizing a sample's arrays to the model's input resolution (used by every real dataset).

All functions take numpy arrays as the readers of :mod:`.flow_io` return them (``(H, W, 2)``
flow, ``(H, W)`` masks and depth, ``(H, W, 3)`` RGB) and return the resized arrays; the
datasets convert to tensors once at the end (:func:`flow_to_tensor`).

Choices, and why:

* **Flow** is an area average *over valid pixels only*: each output pixel is the mean of the
  valid input flow vectors it covers (``cv2.INTER_AREA`` of ``flow · valid`` divided by that of
  ``valid``), so an invalid pixel (sky, no match, NaN) never drags a valid one towards 0. An output
  pixel is valid when at least ``min_valid_fraction`` (default one half) of the area it covers is
  valid. Values are then multiplied by the width and height ratios (``u' = u · W'/W``,
  ``v' = v · H'/H``), since a displacement of ``u`` input pixels is ``u · W'/W`` output pixels.
* **Depth** is averaged as *inverse* depth over the pixels with known depth, i.e. each output pixel
  gets the harmonic mean of the depths it covers. The motion field is linear in inverse depth
  (``v = ρ A t + B ω``), so the rigid flow of the averaged ``ρ`` equals the area average of the
  rigid flow, the same operator applied to the flow above: residuals ``flow − rigid flow`` at the
  input resolution stay near 0 on static surfaces, also at depth edges, where nearest sampling
  (one arbitrary side of the edge) or min-pooling (always the near side) would create spurious
  "moving" pixels. Pixels with no known depth stay 0 ("unknown", as in the sample schema).
* **Masks** (object masks) keep an output pixel when at least half of the input pixels it
  covers, among those where the mask is defined, are set.
* **RGB** uses ``cv2.INTER_AREA`` (anti-aliased shrinking).
* **Intrinsics** go through :func:`mfg_lightning.core.geometry.scale_intrinsics` (pixel centres map
  as ``u' = (u + 0.5) · s − 0.5``).

When the output is larger than the input, bilinear interpolation replaces the area average, with
the same masking.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from mfg_lightning.core import geometry

__all__ = [
    "flow_to_tensor",
    "resize_depth",
    "resize_flow",
    "resize_intrinsics",
    "resize_mask",
    "resize_rgb",
]


def _interpolation(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> int:
    # INTER_AREA is an exact area average when shrinking; when enlarging it degenerates to a
    # blocky nearest/linear mix, so use bilinear instead.
    shrinking = dst_hw[0] <= src_hw[0] and dst_hw[1] <= src_hw[1]
    return cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR


def _masked_mean(
    values: np.ndarray, weight: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted mean of ``values`` ``(H, W[, C])`` over ``weight`` ``(H, W)`` in [0, 1].

    Returns ``(mean, coverage)``: the resized mean (0 where nothing was covered) and the fraction
    of each output pixel's area with weight, both at ``(height, width)``.
    """
    interp = _interpolation(values.shape[:2], (height, width))
    w = weight.astype(np.float32)
    weighted = values.astype(np.float32) * (w[..., None] if values.ndim == 3 else w)
    num = cv2.resize(weighted, (width, height), interpolation=interp)
    den = cv2.resize(w, (width, height), interpolation=interp)
    if num.ndim == 2 and values.ndim == 3:  # cv2 drops a trailing channel axis of size 1
        num = num[..., None]
    safe = np.where(den > 1e-6, den, 1.0)
    mean = num / (safe[..., None] if num.ndim == 3 else safe)
    mean[den <= 1e-6] = 0.0
    return mean.astype(np.float32), den


def resize_flow(
    flow: np.ndarray,
    valid: np.ndarray,
    height: int,
    width: int,
    min_valid_fraction: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Resize flow to ``height × width`` and rescale its values.

    Args:
        flow: ``(H, W, 2)`` pixels at the input resolution, ``(u, v)``.
        valid: ``(H, W)`` bool.
        height, width: output size in pixels.
        min_valid_fraction: an output pixel is valid when at least this fraction of the area it
            covers is valid.

    Returns:
        ``(flow, valid)``: ``(height, width, 2)`` float32 pixels at the output resolution (0 where
        invalid) and ``(height, width)`` bool.
    """
    in_h, in_w = flow.shape[:2]
    valid = np.asarray(valid, bool) & np.isfinite(flow).all(axis=2)
    flow = np.where(valid[..., None], flow, 0.0).astype(np.float32)
    if (in_h, in_w) == (height, width):
        return flow, valid
    mean, coverage = _masked_mean(flow, valid, height, width)
    out_valid = coverage >= min_valid_fraction - 1e-6
    mean *= np.array([width / in_w, height / in_h], np.float32)
    mean[~out_valid] = 0.0
    return mean, out_valid


def resize_depth(
    depth: np.ndarray, height: int, width: int, known: np.ndarray | None = None
) -> np.ndarray:
    """Resize depth by averaging inverse depth (harmonic mean of the covered depths).

    Args:
        depth: ``(H, W)`` metres along z; values ``<= 0`` or non-finite are unknown.
        height, width: output size.
        known: optional ``(H, W)`` bool restricting which pixels count as known.

    Returns:
        ``(height, width)`` float32 metres, 0 where no covered pixel had a known depth.
    """
    depth = np.asarray(depth, np.float32)
    ok = np.isfinite(depth) & (depth > 0)
    if known is not None:
        ok &= np.asarray(known, bool)
    if depth.shape == (height, width):
        return np.where(ok, depth, 0.0).astype(np.float32)
    inv = np.where(ok, 1.0 / np.where(ok, depth, 1.0), 0.0).astype(np.float32)
    inv_mean, coverage = _masked_mean(inv, ok, height, width)
    out = np.zeros((height, width), np.float32)
    has = (coverage > 1e-6) & (inv_mean > 0)
    out[has] = 1.0 / inv_mean[has]
    return out


def resize_mask(
    mask: np.ndarray, height: int, width: int, defined: np.ndarray | None = None
) -> np.ndarray:
    """Resize a bool mask: an output pixel is set when at least half of the input pixels it covers
    (among ``defined`` ones, if given) are set.

    Args:
        mask: ``(H, W)`` bool.
        defined: optional ``(H, W)`` bool, where the mask means something (e.g. valid flow).

    Returns:
        ``(height, width)`` bool.
    """
    mask = np.asarray(mask, bool)
    if mask.shape == (height, width):
        return mask if defined is None else mask & np.asarray(defined, bool)
    weight = np.ones(mask.shape, bool) if defined is None else np.asarray(defined, bool)
    frac, coverage = _masked_mean(mask.astype(np.float32), weight, height, width)
    return (frac >= 0.5) & (coverage > 1e-6)


def resize_rgb(rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize an ``(H, W, 3)`` uint8 image to ``(height, width, 3)`` uint8 (area averaging)."""
    if rgb.shape[:2] == (height, width):
        return rgb
    return cv2.resize(
        rgb, (width, height), interpolation=_interpolation(rgb.shape[:2], (height, width))
    )


def resize_intrinsics(
    intrinsics: torch.Tensor | np.ndarray | list[float],
    src_hw: tuple[int, int],
    dst_hw: tuple[int, int],
) -> torch.Tensor:
    """``(fx, fy, cx, cy)`` of an ``src_hw`` image → the same camera at ``dst_hw``.

    Returns:
        ``(4,)`` float32 tensor in pixels of the ``dst_hw`` image.
    """
    K = torch.as_tensor(np.asarray(intrinsics, np.float64))
    scaled = geometry.scale_intrinsics(K, dst_hw[1] / src_hw[1], dst_hw[0] / src_hw[0])
    return scaled.float()


def flow_to_tensor(flow: np.ndarray) -> torch.Tensor:
    """``(H, W, 2)`` numpy flow → ``(2, H, W)`` float32 tensor (the sample layout)."""
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(flow, 2, 0), dtype=np.float32))


# --------------------------------------------------------------------------------------------
# Frame selection shared by the real datasets
# --------------------------------------------------------------------------------------------


def holdout_ranges(n_frames: int, val_fraction: float, span: int = 1) -> tuple[range, range]:
    """Split one training sequence into a training head and a validation tail.

    The validation frames are a contiguous tail of the sequence: ``ceil(val_fraction · n)``
    frames, but at least ``span + 1`` so that the tail holds at least one pair (``span`` is the
    largest ``|offset|`` between a source and a target frame) and never the whole sequence.
    A sample belongs to a part only when both its frames do, so no frame is seen by both.

    Args:
        n_frames: frames in the sequence.
        val_fraction: fraction of the frames held out, in ``[0, 1)``; 0 holds out nothing.
        span: the largest frame offset of a sample.

    Returns:
        ``(train, val)`` frame-index ranges.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    if val_fraction == 0.0 or n_frames <= 2 * (span + 1):
        # Too short to split: keep it whole for training rather than leave two useless halves.
        return range(0, n_frames), range(n_frames, n_frames)
    n_val = max(int(np.ceil(val_fraction * n_frames)), span + 1)
    n_val = min(n_val, n_frames - (span + 1))
    return range(0, n_frames - n_val), range(n_frames - n_val, n_frames)
