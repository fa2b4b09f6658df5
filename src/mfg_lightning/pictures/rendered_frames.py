"""Pictures of rendered frames (:mod:`mfg_lightning.scene.render`): titled panels of the RGB
image, the exact flow, the regions and the moving-object mask, side by side; and the picture of
one rendered pair with its estimated flow and that estimate's end-point error
(:func:`flow_picture`, what ``flow=dis`` leaves per sequence)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

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


#: End-point errors at or above this many pixels get the brightest colour of the EPE panel.
PICTURE_MAX_EPE = 10.0


def flow_picture(full: dict[str, Any]) -> np.ndarray:
    """The picture grid of one rendered pair at the image size, with the renderer's panels
    (:func:`frame_panels`: RGB, exact flow, regions, object mask)
    and two more: the estimated flow in the exact flow's colour scale and its end-point error
    against it (magma, 0 to :data:`PICTURE_MAX_EPE` px; black where the exact flow is
    unknown).

    Args:
        full: the ``"full"`` entry of
            :meth:`~mfg_lightning.data.rendered.RenderedDrivingDataset.compute_pair`.

    Returns:
        ``(H', W', 3)`` uint8.
    """
    from matplotlib import colormaps

    from mfg_lightning.pictures.colours import flow_to_rgb

    valid = full["exact_valid"]
    magnitude = np.linalg.norm(full["exact_flow"], axis=2)[valid]
    max_flow = float(magnitude.max()) if magnitude.size else 1.0
    estimated = flow_to_rgb(np.moveaxis(full["flow"], 2, 0), max_flow)
    estimated[~full["flow_valid"]] = 0
    epe = np.linalg.norm(full["flow"] - full["exact_flow"], axis=2)
    error = (colormaps["magma"](np.clip(epe / PICTURE_MAX_EPE, 0, 1))[..., :3] * 255).astype(
        np.uint8
    )
    error[~(valid & full["flow_valid"])] = 0
    shown = valid & full["flow_valid"]
    mean = float(epe[shown].mean()) if shown.any() else float("nan")
    panels = frame_panels(
        full["frame"],
        full["exact"],
        extra=[
            ("estimated flow (same colours)", estimated),
            (f"end-point error (0-{PICTURE_MAX_EPE:g} px, mean {mean:.2f})", error),
        ],
        max_flow=max_flow,
    )
    return picture_grid([panels])
