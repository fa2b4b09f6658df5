"""Titled panels laid out in a grid, and PNG files of pictures: what every picture grid of the
project (object motion, rendered frames, flow quality) is drawn with."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def panel_grid(
    columns: Sequence[Sequence[tuple[str, np.ndarray]]], headers: Sequence[str]
) -> np.ndarray:
    """Draw panel columns side by side with titles; return ``(H', W', 3)`` uint8."""
    n_rows = len(columns[0])
    n_cols = len(columns)
    height, width = columns[0][0][1].shape[:2]
    # Panels at least 3.2 in wide so titles fit; keep the image aspect ratio.
    panel_w = max(3.2, width / 100.0)
    panel_h = panel_w * height / width + 0.35
    fig = Figure(figsize=(panel_w * n_cols, panel_h * n_rows), dpi=100)
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(n_rows, n_cols, squeeze=False)
    for c, column in enumerate(columns):
        for r, (title, image) in enumerate(column):
            ax = axes[r][c]
            ax.imshow(image, interpolation="nearest")
            label = f"{headers[c]}: {title}" if r == 0 and headers[c] else title
            ax.set_title(f"{chr(ord('a') + r)}) {label}", fontsize=8)
            ax.set_axis_off()
    fig.tight_layout(pad=0.3)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an ``(H, W, 3)`` uint8 RGB image as PNG (parent folders are created)."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"expected (H, W, 3) uint8, got {image.dtype} {image.shape}")
    if not cv2.imwrite(str(path), np.ascontiguousarray(image[..., ::-1])):
        raise OSError(f"could not write PNG to {path}")
    return path
