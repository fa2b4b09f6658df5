"""Pictures of rendered frames (:mod:`mfg_lightning.scene.render`): titled panels of the RGB
image, the exact flow, the regions and the moving-object mask, side by side."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from mfg_lightning.scene.render import RenderedFrame


#: Region colours of :func:`frame_panels` (the Cityscapes colours of road, building, car, sky).
REGION_COLOURS = np.array([[128, 64, 128], [70, 70, 70], [0, 0, 142], [70, 130, 180]], np.uint8)


def frame_panels(
    frame: RenderedFrame,
    flow: dict[str, torch.Tensor] | None = None,
    extra: Sequence[tuple[str, np.ndarray]] = (),
    max_flow: float | None = None,
) -> list[tuple[str, np.ndarray]]:
    """Titled ``(H, W, 3)`` uint8 panels of one rendered frame, for :func:`picture_grid`.

    Panels: the RGB image, the exact flow (Middlebury colours; ``max_flow`` px, default the
    largest valid magnitude, is full saturation, invalid pixels black), the region map
    (road purple, structure grey, moving blue, far field light blue) and the moving-object
    mask; then ``extra`` panels as given (e.g. an estimated flow drawn with the same
    ``max_flow`` and an end-point-error map).
    """
    from mfg_lightning.pictures.colours import flow_to_rgb

    panels = [(f"RGB (frame {frame.frame})", frame.rgb.permute(1, 2, 0).numpy())]
    if flow is not None:
        valid = flow["flow_valid"].numpy()
        f = flow["flow"].numpy()
        if max_flow is None:
            mag = np.sqrt((f**2).sum(0))[valid]
            max_flow = float(mag.max()) if mag.size else 1.0
        image = flow_to_rgb(f, max_flow)
        image[~valid] = 0
        panels.append((f"exact flow (max {max_flow:.1f} px)", image))
    panels.append(
        ("regions: road, structure, moving, far", REGION_COLOURS[frame.region.long().numpy()])
    )
    mask = (frame.instance >= 0).numpy()
    panels.append(("moving-object mask", np.repeat(mask[..., None] * np.uint8(255), 3, -1)))
    panels.extend(extra)
    return panels


def picture_grid(
    columns: Sequence[Sequence[tuple[str, np.ndarray]]], headers: Sequence[str] | None = None
) -> np.ndarray:
    """Columns of titled panels (e.g. :func:`frame_panels` of several frames) side by side.

    Returns:
        ``(H', W', 3)`` uint8, for :func:`mfg_lightning.pictures.object_motion.save_png` or
        TensorBoard (``add_image(tag, image, dataformats="HWC")``).
    """
    from mfg_lightning.pictures.grids import panel_grid

    if not columns or any(len(c) != len(columns[0]) for c in columns):
        raise ValueError("picture_grid needs columns with the same, non-zero number of panels")
    return panel_grid(columns, list(headers) if headers is not None else [""] * len(columns))
